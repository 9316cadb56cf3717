"""`geoavatar view RUN`: a web viewer (viser) of the animated avatar, on http://127.0.0.1:8080 by default.

The browser draws the Gaussians itself (viser's splat renderer: centres, covariances, colours,
opacities); this process poses them. The GUI:

    Sequence     frame slider over the run's timesteps, play / pause, playback speed (frames per second)
    Edit         offsets added to the shown frame's parameters: the leading expression coefficients
                 (named after the head model's modes when it names them), jaw opening (radians about the
                 jaw's x axis), head yaw and pitch (degrees, turning the head about its own centre);
                 "Reset edits" sets them back to 0

Live mode (`live=True`, used by `geoavatar drive --view`): the sequence and edit controls are off and
the caller sends each posed frame with `Viewer.show_live(gaussians, info)`.

A frame without edits uses the T rule of apps/common.py (a training frame with its own T and refined
parameters); an edited frame is a new animation and uses T = 0.

`start_viewer(...)` returns a running `Viewer` (tests and notebooks: `viewer.stop()` ends it);
`view(...)` serves until Ctrl-C. The server listens on 127.0.0.1 unless --host says otherwise: only
this machine can connect (use --host 0.0.0.0 to serve the network, e.g. through an SSH tunnel's far end).

Browser console: viser 1.1.1's client logs "THREE.BufferGeometry.computeBoundingSphere(): Computed radius
is NaN" once per splat set. It is not our data (every centre, covariance and the initial camera we send
are finite; tests/test_viewer.py decodes viser's packed buffer to check): viser draws each splat on a
quad whose "position" attribute has 2 components (client/src/Splatting/GaussianSplatsHelpers.ts), and
three.js's frustum test reads 3, so the quad's bounding sphere is NaN. The NaN sphere never culls, so
the avatar always draws; the message goes away when viser marks that mesh frustumCulled={false}.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from geoavatar.apps.common import RunFrames, RunPath, head_centre, open_run, pose_gaussians, record_camera
from geoavatar.avatar import GlobalGaussians
from geoavatar.data import DatasetError, open_subject
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle, quaternion_to_matrix
from geoavatar.head.params import HeadParams
from geoavatar.render.camera import camera_centre
from geoavatar.train.checkpoint import LoadedRun

EXPR_RANGE = 3.0  # expression offsets in units of the basis (FLAME's coefficients are ~N(0, 1))
JAW_RANGE = (-0.1, 0.5)  # radians
HEAD_RANGE = 45.0  # degrees


def covariances(g: GlobalGaussians) -> Tensor:
    """[N, 3, 3] world covariances R diag(s^2) R^T of the Gaussians."""
    rot = quaternion_to_matrix(torch.nn.functional.normalize(g.quats, dim=-1))  # [N, 3, 3]
    return (rot * g.scales[:, None, :] ** 2) @ rot.transpose(-1, -2)


def splat_arrays(g: GlobalGaussians) -> dict[str, np.ndarray]:
    """What viser's splat set takes: centres, covariances, colours in [0, 1], opacities [N, 1] (numpy)."""
    numpy = lambda x: x.detach().float().cpu().numpy()  # noqa: E731
    return {"centers": numpy(g.means), "covariances": numpy(covariances(g)), "rgbs": numpy(g.colors.clamp(0.0, 1.0)),
            "opacities": numpy(g.opacities[:, None])}


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


class Viewer:
    """A running viser server showing one run; `stop()` ends it."""

    def __init__(self, run: LoadedRun, host: str = "127.0.0.1", port: int = 8080, expr_sliders: int = 10,
                 fps: float = 25.0, data: Path | None = None, live: bool = False):
        try:
            import viser
        except ImportError as err:
            raise ImportError(f"the viewer needs viser ({err}); install it with: pip install 'geoavatar[viewer]'") from err

        self.run = run
        self.frames = RunFrames(run)
        self._lock = threading.RLock()
        self._batch = False
        self.live = live
        self._stopped = threading.Event()
        self.server = viser.ViserServer(host=host, port=port, label="GeoAvatar", verbose=False)
        self.host, self.port = host, self.server.get_port()
        self.server.scene.set_up_direction("+y")  # head coordinates: +y up, +z out of the face

        gui = self.server.gui
        count = len(self.frames)
        with gui.add_folder("Sequence"):
            self.frame = gui.add_slider("frame", min=0, max=max(count - 1, 1), step=1, initial_value=0,
                                        disabled=count < 2 or live, hint="position in the run's sequence")
            self.playing = gui.add_checkbox("play", initial_value=False, disabled=count < 2 or live)
            self.fps = gui.add_slider("fps", min=1.0, max=60.0, step=1.0, initial_value=float(fps))
            self.info = gui.add_markdown("")
        names = list(run.head.data.metadata.get("expression_names", []))
        with gui.add_folder("Edit"):
            self.expr = [gui.add_slider(names[i] if i < len(names) else f"expr {i}", min=-EXPR_RANGE,
                                        max=EXPR_RANGE, step=0.05, initial_value=0.0)
                         for i in range(min(expr_sliders, run.head.num_expr))]
            self.jaw = gui.add_slider("jaw open (rad)", min=JAW_RANGE[0], max=JAW_RANGE[1], step=0.01, initial_value=0.0)
            self.yaw = gui.add_slider("head yaw (deg)", min=-HEAD_RANGE, max=HEAD_RANGE, step=1.0, initial_value=0.0)
            self.pitch = gui.add_slider("head pitch (deg)", min=-HEAD_RANGE, max=HEAD_RANGE, step=1.0, initial_value=0.0)
            self.reset = gui.add_button("Reset edits")
        for handle in (self.frame, *self.expr, self.jaw, self.yaw, self.pitch):
            handle.on_update(lambda _event: self.update())
        self.reset.on_click(lambda _event: self.reset_edits())

        params, _ = self.frames.params(self.frames.timesteps[0])
        self.centre = head_centre(run, params)  # [3], fixed: the edits turn the head about it
        g = self._gaussians()
        self.splats = self.server.scene.add_gaussian_splats("/avatar", **g)
        self._show_info()
        self._aim_camera(data)
        self._player = threading.Thread(target=self._play, name="geoavatar-view-player", daemon=True)
        self._player.start()

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}/"

    def current_params(self) -> tuple[HeadParams, int | None]:
        """The shown frame's parameters with the edits applied, and its T (None when edited)."""
        timestep = self.frames.timesteps[min(int(self.frame.value), len(self.frames) - 1)]
        params, t = self.frames.params(timestep)
        offsets = [float(s.value) for s in self.expr]
        jaw, yaw, pitch = float(self.jaw.value), float(self.yaw.value), float(self.pitch.value)
        if not (any(offsets) or jaw or yaw or pitch):
            return params, t
        return edited_params(self.run.head, params, offsets, jaw, yaw, pitch, self.centre), None

    @torch.no_grad()
    def _gaussians(self) -> dict[str, np.ndarray]:
        params, t = self.current_params()
        return splat_arrays(pose_gaussians(self.run, params, t))

    def update(self) -> None:
        """Pose the avatar for the current GUI state and send it to the browsers."""
        if self._batch or self.live or self._stopped.is_set():
            return
        with self._lock:
            g = self._gaussians()
            self.splats.set_gaussians(g["centers"], g["covariances"], g["rgbs"], g["opacities"])
            self._show_info()

    @torch.no_grad()
    def show_live(self, gaussians: GlobalGaussians, info: str = "") -> None:
        """Live mode: send these posed Gaussians to the browsers (the caller poses them, e.g. `drive`)."""
        if self._stopped.is_set():
            return
        g = splat_arrays(gaussians)
        with self._lock:
            self.splats.set_gaussians(g["centers"], g["covariances"], g["rgbs"], g["opacities"])
            if info:
                self.info.content = info

    def _show_info(self) -> None:
        timestep = self.frames.timesteps[min(int(self.frame.value), len(self.frames) - 1)]
        self.info.content = f"timestep {timestep} ({len(self.frames)} frames), {self.run.avatar.num_gaussians} Gaussians"

    def reset_edits(self) -> None:
        self._batch = True
        try:
            for handle in (*self.expr, self.jaw, self.yaw, self.pitch):
                handle.value = 0.0
        finally:
            self._batch = False
        self.update()

    def _aim_camera(self, data: Path | None) -> None:
        """Start the browser's camera where the dataset camera was, looking at the head."""
        try:
            root = Path(data) if data is not None else self.run.info.data_root
            camera = record_camera(open_subject(root), self.frames.timesteps[0], None)
        except DatasetError:
            return  # no dataset: viser's default camera
        viewmat = camera.viewmat.double()
        eye = camera_centre(viewmat)  # [3] world
        fov = 2.0 * math.atan(0.5 * camera.height / float(camera.K[1, 1]))
        initial = self.server.initial_camera
        initial.position = tuple(float(v) for v in eye)
        initial.look_at = tuple(float(v) for v in self.centre.cpu())
        initial.up = (0.0, 1.0, 0.0)
        initial.fov = fov

    def _play(self) -> None:
        while not self._stopped.is_set():
            if self.playing.value and len(self.frames) > 1:
                started = time.perf_counter()
                self.frame.value = (int(self.frame.value) + 1) % len(self.frames)  # runs update()
                wait = 1.0 / max(float(self.fps.value), 1e-3) - (time.perf_counter() - started)
                self._stopped.wait(max(wait, 0.0))
            else:
                self._stopped.wait(0.05)

    def stop(self) -> None:
        self._stopped.set()
        self._player.join(timeout=5.0)
        self.server.stop()


def start_viewer(run: LoadedRun, host: str = "127.0.0.1", port: int = 8080, expr_sliders: int = 10,
                 fps: float = 25.0, data: Path | None = None, live: bool = False) -> Viewer:
    """Start serving `run` and return the running Viewer (call .stop() to end it); `live`: see show_live."""
    if not 0 <= port <= 65535:
        raise OptionError(f"--port must be in [0, 65535], got {port}")
    if expr_sliders < 0:
        raise OptionError(f"--expr-sliders must be >= 0, got {expr_sliders}")
    return Viewer(run, host, port, expr_sliders, fps, data, live)


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
    """Serve a web viewer of the avatar: play the dataset's sequence, edit expression, jaw and head pose.

    Open the printed address in a browser. Ctrl-C stops the server.

    Args:
        run: Run folder written by `geoavatar train`.
        host: Address to listen on (127.0.0.1: this machine only; 0.0.0.0: every network interface).
        port: Port to listen on (0: any free port; viser moves to the next free one when it is taken).
        expr_sliders: Number of leading expression coefficients with a slider.
        fps: Initial playback speed in frames per second.
        data: The run's dataset folder, when it moved since training (the initial camera comes from it).
        device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        flame_dir: Folder with your FLAME model files (runs trained on FLAME data only).
        serve_forever: Keep serving until Ctrl-C (off: start, print the address and stop; a smoke test).
    """
    loaded = open_run(run, device, flame_dir)
    try:
        viewer = start_viewer(loaded, host, port, expr_sliders, fps, data)
    except (ImportError, OSError) as err:  # viser missing; the address cannot be bound
        raise GeoAvatarError(f"cannot start the viewer: {err}") from err
    print(f"GeoAvatar viewer: {viewer.url}  ({loaded.avatar.num_gaussians} Gaussians, {len(viewer.frames)} frames; "
          "Ctrl-C stops)", flush=True)
    try:
        while serve_forever:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


__all__ = ["Viewer", "covariances", "edited_params", "splat_arrays", "start_viewer", "view"]
