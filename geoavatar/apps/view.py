"""`geoavatar view RUN`: the browser player of the animated avatar, served on http://127.0.0.1:8080 by default.

The page is the web player of `geoavatar export --format web` (geoavatar/web: the browser places, rotates,
scales and shades every splat on its GPU from the posed head mesh), playing the run's whole sequence with its
controls (play/pause, scrub, orbit, background), plus what needs Python: expression, jaw and head-turn sliders
(turning the head differs from turning the camera: the normal shading's lights stay fixed to the world). A slider
sends the shown frame and the edits over the page's websocket; this process poses the head with them
(`edited_params`; an edited frame is a new animation: T = 0) and streams the posed mesh back. Without edits the
page plays its clip by itself (the T rule of apps/common.py: training frames with their own T and refined
parameters).

Live mode (`live=True`, used by `geoavatar drive --view`): the page has no clip of its own and draws every mesh
the caller sends with `LiveViewer.show_live(vertices, info, read_time, code)`.

`start_viewer(...)` returns a running `LiveViewer` (tests and notebooks: `viewer.stop()` ends it); `view(...)`
serves until Ctrl-C. The server listens on 127.0.0.1 unless --host says otherwise: only this machine can connect
(use --host 0.0.0.0 to serve the network, e.g. through an SSH tunnel's far end).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor

from geoavatar.apps.common import RunPath, browser_pose_code, head_centre, posed_head_vertices
from geoavatar.errors import OptionError
from geoavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from geoavatar.head.params import HeadParams
from geoavatar.train.checkpoint import LoadedRun, open_run
from geoavatar.train.run_frames import RunFrames
from geoavatar.web.live import LiveServer

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
    """The player served with a websocket (web/live.py): view's sliders, or drive's live meshes."""

    def __init__(self, run: LoadedRun, host: str = "127.0.0.1", port: int = 8080, expr_sliders: int = 10,
                 fps: float = 25.0, data: Path | None = None, live: bool = False):
        from geoavatar.apps.web_export import split_clip, web_assets

        self.run = run
        self.frames = RunFrames(run)
        self.live = live
        timesteps = self.frames.timesteps[:1] if live else list(self.frames.timesteps)
        first, _ = self.frames.params(timesteps[0])
        self.centre = head_centre(run, first)  # [3]
        clip = split_clip(run, self.frames, timesteps, show_progress=False)
        assets = web_assets(run, clip, first, timesteps, fps, "live" if live else "split all", data, timesteps)
        assets.manifest["live"] = "drive" if live else "view"
        if not live:
            names = list(run.head.data.metadata.get("expression_names", []))
            count = min(expr_sliders, run.head.num_expr)
            assets.manifest["edit"] = {"expressions": [names[i] if i < len(names) else f"expr {i}" for i in range(count)],
                                       "exprRange": EXPR_RANGE, "jawRange": list(JAW_RANGE), "headRange": HEAD_RANGE}
        self.timesteps = timesteps
        self.server = LiveServer(assets, host, port, on_edit=None if live else self.edit).start()
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
                  code: Tensor | None = None) -> None:
        """Live mode: send a posed mesh [V, 3] and its head pose code [6] (apps/common.browser_pose_code) to the
        browsers (the caller poses it, e.g. `drive`)."""
        self.server.send_vertices(vertices, read_time, code)

    def summary(self) -> str:
        """The stream's counts and its latency from frame read to message sent (median)."""
        latency = self.server.latency_ms
        p50 = f"{sorted(latency)[len(latency) // 2]:.0f} ms" if latency else "-"
        return f"browser stream: {self.server.sent} meshes sent, {self.server.dropped} replaced, read->sent {p50} (median)"

    def stop(self) -> None:
        self.server.stop()


def start_viewer(run: LoadedRun, host: str = "127.0.0.1", port: int = 8080, expr_sliders: int = 10,
                 fps: float = 25.0, data: Path | None = None, live: bool = False) -> LiveViewer:
    """Start serving `run` and return the running LiveViewer (call .stop() to end it); `live`: see show_live.
    LiveServerError (one line, naming --port) when the address cannot be served."""
    if not 0 <= port <= 65535:
        raise OptionError(f"--port must be in [0, 65535], got {port}")
    if expr_sliders < 0:
        raise OptionError(f"--expr-sliders must be >= 0, got {expr_sliders}")
    if fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    return LiveViewer(run, host, port, expr_sliders, fps, data, live)


def view(
    run: RunPath,
    host: str = "127.0.0.1",
    port: int = 8080,
    expr_sliders: int = 10,
    fps: float = 25.0,
    data: Optional[Path] = None,
    device: str = "auto",
    flame_dir: Optional[Path] = None,
    serve_forever: bool = True,
) -> int:
    """Serve the browser player of the avatar: play the run's sequence, turn the view, edit expression and jaw.

    Open the printed address in a browser (any WebGL2 browser: it draws the avatar on its own GPU; the edits are
    posed here and streamed). Ctrl-C stops the server.

    Args:
        run: Run folder written by `geoavatar train`.
        host: Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every network interface).
        port: Port to listen on (0: any free port).
        expr_sliders: Number of leading expression coefficients with a slider.
        fps: Playback speed of the sequence in frames per second.
        data: The run's dataset folder, when it moved since training (the camera comes from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        serve_forever: Keep serving until Ctrl-C (off: start, print the address and stop; a smoke test).
    """
    loaded = open_run(run, device, flame_dir)
    viewer = start_viewer(loaded, host, port, expr_sliders, fps, data)
    print(f"GeoAvatar player: {viewer.url}  ({loaded.avatar.num_gaussians} Gaussians, {len(viewer.frames)} frames; "
          "Ctrl-C stops)", flush=True)
    try:
        while serve_forever:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


__all__ = ["LiveViewer", "edited_params", "start_viewer", "view"]
