"""The web viewer (viser): it serves a page on localhost, poses the avatar for the GUI state, plays the
sequence, and stops cleanly. Uses an untrained run (the trainer's step-0 state) of a 4-frame subject."""

from __future__ import annotations

import math
import socket
import time
import urllib.request

import numpy as np
import pytest
import torch

from apps_fixtures import make_subject, make_untrained_run
from geoavatar.apps import view as view_app
from geoavatar.apps.common import RunFrames, head_centre, open_run, pose_gaussians
from geoavatar.geometry import axis_angle_to_matrix

pytest.importorskip("viser")  # the optional [viewer] extra


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    data = make_subject(root / "data", subject=2, frames=4, size=32)
    return open_run(make_untrained_run(data, root / "run"), "cpu")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def fetch(url: str, attempts: int = 50) -> tuple[int, str, str]:
    for _ in range(attempts):
        try:
            with urllib.request.urlopen(url, timeout=5) as response:
                return response.status, response.headers.get("Content-Type", ""), response.read().decode("utf-8", "replace")
        except OSError:
            time.sleep(0.1)  # the server thread may still be binding
    raise AssertionError(f"no answer from {url}")


def test_viewer_serves_a_page_on_localhost_and_follows_the_gui(run):
    port = free_port()
    viewer = view_app.start_viewer(run, port=port, expr_sliders=4)
    try:
        assert viewer.url == f"http://127.0.0.1:{port}/" and viewer.host == "127.0.0.1"
        status, kind, body = fetch(viewer.url)
        assert status == 200 and "text/html" in kind and "<html" in body.lower()

        n = run.avatar.num_gaussians
        centres = viewer.splats.centers.copy()
        assert centres.shape == (n, 3)
        params, t = RunFrames(run).params(RunFrames(run).timesteps[0])
        expected = pose_gaussians(run, params, t).means.detach().numpy()
        assert np.allclose(centres, expected, atol=1e-6)

        viewer.jaw.value = 0.3  # GUI edits run the update synchronously
        opened = viewer.splats.centers.copy()
        moved = np.linalg.norm(opened - centres, axis=1)
        assert moved.max() > 1e-3 and np.median(moved) < 1e-6  # the jaw moves, the skull does not

        viewer.reset_edits()
        assert np.allclose(viewer.splats.centers, centres, atol=1e-6)
        viewer.frame.value = 2
        assert not np.allclose(viewer.splats.centers, centres)

        viewer.fps.value = 60.0
        viewer.playing.value = True  # playback advances the frame slider on its own thread
        deadline = time.time() + 20.0
        shown = viewer.frame.value
        while shown == 2 and time.time() < deadline:
            time.sleep(0.05)
            shown = viewer.frame.value  # read once: at 60 fps over 4 frames it may be back at 2 a moment later
        viewer.playing.value = False
        assert shown != 2
        time.sleep(0.3)  # a step already under way finishes
        paused_at = viewer.frame.value
        time.sleep(0.3)
        assert viewer.frame.value == paused_at  # pausing stops the playback
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2)


def test_head_turn_edit_turns_the_head_about_its_centre(run):
    frames = RunFrames(run)
    params, _ = frames.params(frames.timesteps[0])
    centre = head_centre(run, params)
    turned = view_app.edited_params(run.head, params, [0.0], 0.0, 30.0, -10.0, centre)
    # Every posed point x' moves to T (x' - c) + c, T = yaw(30 deg about +y) pitch(-10 deg about +x).
    turn = axis_angle_to_matrix(torch.tensor([0.0, math.radians(30.0), 0.0])) @ axis_angle_to_matrix(
        torch.tensor([math.radians(-10.0), 0.0, 0.0]))
    before = run.head.forward_params(params).vertices[0]
    after = run.head.forward_params(turned).vertices[0]
    assert torch.allclose(after, (before - centre) @ turn.T + centre, atol=1e-5)
    assert float((after - before).norm(dim=-1).max()) > 0.01
    same = view_app.edited_params(run.head, params, [0.0, 0.0], 0.0, 0.0, 0.0, centre)
    assert all(torch.equal(same.to_npz()[k], v) for k, v in params.to_npz().items())
    smiling = view_app.edited_params(run.head, params, [0.5], 0.0, 0.0, 0.0, centre)
    assert float(smiling.expr[0, 0] - params.expr[0, 0]) == pytest.approx(0.5)


def test_view_command_starts_and_stops(run, capsys):
    assert view_app.view(run.info.run_dir, port=free_port(), device="cpu", serve_forever=False) == 0
    assert "http://127.0.0.1:" in capsys.readouterr().out


def sent_splats(handle) -> tuple[np.ndarray, np.ndarray]:
    """(centres [N, 3], covariance upper triangles [N, 6]) exactly as viser packs them for the browser:
    rows of 8 uint32 words, float32 centre in words 0-2, float16 covariance terms in words 4-6."""
    buffer = np.asarray(handle.buffer)
    assert buffer.dtype == np.uint32 and buffer.ndim == 2 and buffer.shape[1] == 8
    centres = np.ascontiguousarray(buffer[:, 0:3]).view(np.float32)
    covariance = np.ascontiguousarray(buffer[:, 4:7]).view(np.float16).astype(np.float32)
    return centres, covariance


def test_viewer_sends_only_finite_positions(run):
    """The browser must get finite centres, finite positive-diagonal covariances (float16: no overflow) and a
    finite initial camera, for the first frame and for extreme edits (a NaN here would give three.js a NaN
    bounding sphere)."""
    viewer = view_app.start_viewer(run, port=free_port(), expr_sliders=4)
    try:
        def check() -> None:
            centres, cov = sent_splats(viewer.splats)
            assert centres.shape == (run.avatar.num_gaussians, 3)
            assert np.isfinite(centres).all() and np.isfinite(cov).all()
            assert (cov[:, [0, 3, 5]] >= 0).all() and (cov[:, [0, 3, 5]].sum(axis=1) > 0).all()

        check()
        camera = viewer.server.initial_camera
        for value in (camera.position, camera.look_at, camera.up, (camera.fov,)):
            assert np.isfinite(np.asarray(value, dtype=np.float64)).all()
        assert 0.0 < camera.fov < math.pi
        for slider in viewer.expr:
            slider.value = slider.max
        viewer.jaw.value, viewer.yaw.value, viewer.pitch.value = 0.5, 45.0, -45.0
        check()
        viewer.frame.value = len(viewer.frames) - 1
        check()
    finally:
        viewer.stop()
