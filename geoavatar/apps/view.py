"""`geoavatar view RUN`: the browser player of the animated avatar, served on http://127.0.0.1:8080 by default.

The page is the web player of `geoavatar export --format web` (geoavatar/web: the browser places, rotates,
scales and shades every splat on its GPU from the posed head mesh), playing the run's whole sequence with its
controls (play/pause, scrub, orbit, background), plus what needs Python: expression, jaw and head-turn sliders,
posed here and streamed back (animation/sinks/browser.py's LiveViewer). The clip is the run's frames as the animation
layer plays them (sources/split.py's SplitFrames into sinks/web.py's WebClip: RunFrames' T rule, training frames
with their own T and refined parameters).

Live mode (`live=True`, used by `geoavatar drive --view`): the page has no clip of its own and draws every mesh
the caller sends with `LiveViewer.show_live(vertices, info, read_time, code)` (sinks/browser.py's LiveStream).

`start_viewer(...)` returns a running `LiveViewer` (tests and notebooks: `viewer.stop()` ends it); `view(...)`
serves until Ctrl-C. The server listens on 127.0.0.1 unless --host says otherwise: only this machine can connect
(use --host 0.0.0.0 to serve the network, e.g. through an SSH tunnel's far end).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from geoavatar.animation.play import play
from geoavatar.animation.sinks.browser import LiveViewer
from geoavatar.animation.sinks.web import WebClip
from geoavatar.animation.sources.split import SplitFrames
from geoavatar.apps.common import RunPath, serve_until_interrupted
from geoavatar.errors import OptionError
from geoavatar.train.checkpoint import LoadedRun, open_run, open_run_dataset
from geoavatar.train.run_frames import RunFrames
from geoavatar.web.live import check_address


def start_viewer(run: LoadedRun, host: str = "127.0.0.1", port: int = 8080, expr_sliders: int = 10,
                 fps: float = 25.0, data: Path | None = None, live: bool | str = False, **callbacks) -> LiveViewer:
    """Start serving `run` and return the running LiveViewer (call .stop() to end it); `live`: see show_live ("speak":
    the page is also the microphone, `callbacks` on_audio / on_microphone_error receive it). LiveServerError (one
    line, naming --port) when the address cannot be served."""
    if not 0 <= port <= 65535:
        raise OptionError(f"--port must be in [0, 65535], got {port}")
    if expr_sliders < 0:
        raise OptionError(f"--expr-sliders must be >= 0, got {expr_sliders}")
    if fps <= 0:
        raise OptionError(f"--fps must be positive, got {fps}")
    open_run_dataset(run, "all", data)  # the page's camera comes from it: RunError now, not after the posing
    check_address(host, port)
    frames = RunFrames(run)
    timesteps = frames.timesteps[:1] if live else list(frames.timesteps)  # live: the page's first view only
    clip = WebClip(run, fps, "live" if live else "split all", data=data)
    play(run, SplitFrames(run, timesteps, fps, frames), [clip])
    return LiveViewer(run, clip.assets(), timesteps, host, port, expr_sliders, live, frames, **callbacks)


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
    serve_until_interrupted(viewer, serve_forever)
    return 0


__all__ = ["start_viewer", "view"]
