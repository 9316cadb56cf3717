"""The browser player served live (web/live.py's LiveServer): view's sliders, and drive's live stream.

    viewer = LiveViewer(run, assets, timesteps, host, port, expr_sliders, live)  # the page, its clip, the websocket
    sinks = [LiveStream(viewer, run, source)]                                      # drive --view: a live source

View mode: the page plays its clip by itself (sinks/web.py's assets of the run's frames), plus what needs Python:
expression, jaw and head-turn sliders (turning the head differs from turning the camera: the normal shading's lights
stay fixed to the world). A slider sends the shown frame and the edits over the page's websocket; this process poses
the head with them (`edited_params`; an edited frame is a new animation: T = 0) and streams the posed mesh back.

Live mode (`live=True`, or `live="speak"`): the page has no clip of its own and draws every mesh sent with
`LiveViewer.show_live(vertices, info, read_time, code, capture_time)`; LiveStream sends each frame's posed head mesh
and its head pose code (the browser places, shades and draws the splats on its GPU: nothing is rasterized here). With
"speak" the page is also the microphone: its sound goes to `on_audio` (web/live.py), and a frame made from sound
carries the capture time of its own instant of sound (AnimationFrame.heard), from which the page measures
sound-to-picture latency.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from geoavatar.animation.frames import AnimationFrame
from geoavatar.animation.posing import PosedFrame, browser_pose_code, head_centre, posed_head_vertices
from geoavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from geoavatar.head.params import HeadParams
from geoavatar.train.checkpoint import LoadedRun
from geoavatar.train.run_frames import RunFrames
from geoavatar.web.live import LiveServer
from geoavatar.web.pack import PlayerAssets

EXPR_RANGE = 3.0  # expression offsets in units of the basis (FLAME's coefficients are ~N(0, 1))
JAW_RANGE = (-0.1, 0.5)  # radians
HEAD_RANGE = 45.0  # degrees: the head turned (not the camera: the normal shading's lights stay with the world)


def edited_params(head, params: HeadParams, expr_offsets: list[float], jaw: float, yaw_deg: float,
                  pitch_deg: float, centre: Tensor) -> HeadParams:
    """`params` (per-frame keys [1, ...]) with the viewer's edits applied (see the module docstring).

    The head turn is a world rotation T (yaw about +y after pitch about +x) about `centre` [3]: every
    posed point x' becomes T (x' - c) + c. The head model poses x' = R (x - J0) + J0 + t about its root
    joint J0, so the edit sets R' = T R and t' = T (J0 + t - c) + c - J0."""
    out = params
    if any(expr_offsets):
        expr = params.expr.clone()
        count = min(len(expr_offsets), expr.shape[-1])
        expr[0, :count] += torch.tensor(expr_offsets[:count], dtype=expr.dtype, device=expr.device)
        out = out.replace(expr=expr)
    if jaw:
        jaw_pose = params.jaw_pose.clone()
        jaw_pose[0, 0] += jaw
        out = out.replace(jaw_pose=jaw_pose)
    if yaw_deg or pitch_deg:
        rotation, translation = params.rotation, params.translation
        axis = torch.tensor([[0.0, math.radians(yaw_deg), 0.0], [math.radians(pitch_deg), 0.0, 0.0]],
                            dtype=rotation.dtype, device=rotation.device)
        turn_yaw, turn_pitch = axis_angle_to_matrix(axis)  # [3, 3] each
        turn = turn_yaw @ turn_pitch
        root = head.forward_params(out).joints[0, 0] - translation[0]  # [3] J0, rest pose (with the edits)
        out = out.replace(rotation=matrix_to_axis_angle(turn @ axis_angle_to_matrix(rotation[0]))[None],
                          translation=(turn @ (root + translation[0] - centre) + centre - root)[None])
    return out


class LiveViewer:
    """The player served with a websocket (web/live.py): view's sliders on the clip of `timesteps`, or (`live`) drive's
    live meshes. `assets`: the player's avatar and clip (sinks/web.py's WebClip of those timesteps)."""

    def __init__(self, run: LoadedRun, assets: PlayerAssets, timesteps: list[int], host: str = "127.0.0.1",
                 port: int = 8080, expr_sliders: int = 10, live: bool | str = False, frames: RunFrames | None = None,
                 on_audio=None, on_microphone_error=None):
        self.run = run
        self.frames = frames if frames is not None else RunFrames(run)
        self.live = bool(live)
        first, _ = self.frames.params(timesteps[0])
        self.centre = head_centre(run, first)  # [3]
        assets.manifest["live"] = live if isinstance(live, str) else ("drive" if live else "view")
        if not live:
            names = list(run.head.data.metadata.get("expression_names", []))
            count = min(expr_sliders, run.head.num_expr)
            assets.manifest["edit"] = {"expressions": [names[i] if i < len(names) else f"expr {i}" for i in range(count)],
                                       "exprRange": EXPR_RANGE, "jawRange": list(JAW_RANGE), "headRange": HEAD_RANGE}
        self.timesteps = list(timesteps)
        self.server = LiveServer(assets, host, port, on_edit=None if live else self.edit, on_audio=on_audio,
                                 on_microphone_error=on_microphone_error).start()
        self.host, self.port = host, self.server.port

    @property
    def url(self) -> str:
        return self.server.url

    def edit_params(self, request: dict) -> HeadParams | None:
        """The parameters a slider message asks for (None when malformed): the clip frame with the edits."""
        try:
            index = int(request["frame"])
            expr = [float(v) for v in request.get("expr", [])]
            jaw, yaw, pitch = (float(request.get(key, 0.0)) for key in ("jaw", "yaw", "pitch"))
        except (KeyError, TypeError, ValueError):
            return None
        if not 0 <= index < len(self.timesteps) or not all(map(math.isfinite, [*expr, jaw, yaw, pitch])):
            return None
        expr = [min(max(v, -EXPR_RANGE), EXPR_RANGE) for v in expr]
        yaw, pitch = (min(max(v, -HEAD_RANGE), HEAD_RANGE) for v in (yaw, pitch))
        params, _ = self.frames.params(self.timesteps[index])
        return edited_params(self.run.head, params, expr, min(max(jaw, JAW_RANGE[0]), JAW_RANGE[1]), yaw, pitch,
                             self.centre)

    @torch.no_grad()
    def edit(self, request: dict) -> None:
        """A slider message from the page: pose the edited frame (T = 0) and stream it back."""
        params = self.edit_params(request)
        if params is not None:
            self.server.send_vertices(posed_head_vertices(self.run, params, None), None,
                                      browser_pose_code(self.run, params))

    def show_live(self, vertices: Tensor, info: str = "", read_time: float | None = None,
                  code: Tensor | None = None, capture_time: float | None = None) -> None:
        """Live mode: send a posed mesh [V, 3] and its head pose code [6] (posing.browser_pose_code) to the browsers
        (the caller poses it: LiveStream); `capture_time`: Unix time of the sound it was made from (speech)."""
        self.server.send_vertices(vertices, read_time, code, capture_time=capture_time)

    def summary(self) -> str:
        """The stream's counts and its latency from frame read to message sent (median)."""
        latency = self.server.latency_ms
        p50 = f"{sorted(latency)[len(latency) // 2]:.0f} ms" if latency else "-"
        return f"browser stream: {self.server.sent} meshes sent, {self.server.dropped} replaced, read->sent {p50} (median)"

    def stop(self) -> None:
        self.server.stop()


class LiveStream:
    """Sink: each frame's posed head mesh and head pose code streamed to a LiveViewer in live mode, captioned with the
    live `source`'s frame rate and drops (its `stats` and `dropped`)."""

    rasterizes = False

    def __init__(self, viewer: LiveViewer, run: LoadedRun, source):
        self.viewer, self.run, self.source = viewer, run, source

    def __enter__(self) -> "LiveStream":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        return False

    def write(self, frame: AnimationFrame, posed: PosedFrame) -> None:
        started = time.perf_counter()
        caption = f"live: frame {frame.index}, {self.source.stats.fps:.1f} fps, dropped {self.source.dropped}"
        heard = {"capture_time": frame.heard} if frame.heard is not None else {}  # speech: its sound's capture
        self.viewer.show_live(posed.vertices, caption, frame.available, browser_pose_code(self.run, frame.params),
                              **heard)
        frame.add_time("pose", time.perf_counter() - started)  # the browser draws: streaming counts as posing


__all__ = ["EXPR_RANGE", "HEAD_RANGE", "JAW_RANGE", "LiveStream", "LiveViewer", "edited_params"]
