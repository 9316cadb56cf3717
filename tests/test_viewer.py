"""`geoavatar view` and the live player server: the page and the avatar over HTTP on localhost, view's slider
edits posed in Python and streamed back over the websocket, live meshes counted by a real browser, a port in use
as one line. Uses an untrained run (the trainer's step-0 state) of a 4-frame subject."""

from __future__ import annotations

import json
import math
import socket
import struct
import urllib.request

import numpy as np
import pytest
import torch

from apps_fixtures import make_subject, make_untrained_run
from web_fixtures import small_player
from geoavatar import cli
from geoavatar.animation.posing import head_centre, posed_head_vertices
from geoavatar.animation.sinks.browser import edited_params
from geoavatar.apps import view as view_app
from geoavatar.avatar.hair_motion import head_pose_code
from geoavatar.geometry import axis_angle_to_matrix
from geoavatar.train.checkpoint import open_run
from geoavatar.train.run_frames import RunFrames
from geoavatar.web.browser import browser_missing, chromium_page
from geoavatar.web.live import KIND_VERTICES, LiveServer, LiveServerError, vertex_message


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer")
    data = make_subject(root / "data", subject=2, frames=4, size=32)
    return open_run(make_untrained_run(data, root / "run"), "cpu")


def fetch(url: str) -> tuple[int, str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as response:
        return response.status, response.headers.get("Content-Type", ""), response.read()


def received_mesh(message: bytes, vertex_count: int) -> tuple[int, np.ndarray]:
    sequence, mesh, _code = received_frame(message, vertex_count)
    return sequence, mesh


def received_frame(message: bytes, vertex_count: int) -> tuple[int, np.ndarray, np.ndarray]:
    """sequence, vertices [V, 3] and the head pose code ([6], or [0] when the hair does not follow the head)."""
    kind, sequence, _sent = struct.unpack("<IId", message[:16])
    assert kind == KIND_VERTICES
    body = np.frombuffer(message[16:], dtype="<f4")
    assert len(body) in (vertex_count * 3, vertex_count * 3 + 6)
    return sequence, body[:vertex_count * 3].reshape(vertex_count, 3), body[vertex_count * 3:]


def test_view_serves_the_player_and_streams_slider_edits(run):
    from websockets.sync.client import connect

    viewer = view_app.start_viewer(run, port=0, expr_sliders=3)
    try:
        assert viewer.url.startswith("http://127.0.0.1:") and viewer.port > 0
        status, kind, body = fetch(viewer.url)
        assert status == 200 and "text/html" in kind and b"player.js" in body
        assert "javascript" in fetch(viewer.url + "player.js")[1]
        manifest = json.loads(fetch(viewer.url + "avatar.json")[2])
        assert manifest["live"] == "view" and len(manifest["edit"]["expressions"]) == 3
        assert manifest["clip"]["timesteps"] == RunFrames(run).timesteps
        with pytest.raises(OSError):
            fetch(viewer.url + "nothing.bin")

        with connect(viewer.url.replace("http", "ws") + "ws") as socket_:
            socket_.send(json.dumps({"type": "edit", "frame": 1, "expr": [0.8, 0.0, 0.0], "jaw": 0.3, "yaw": 20.0}))
            _, mesh, code = received_frame(socket_.recv(timeout=30), run.head.num_vertices)
            socket_.send("not json")  # ignored
            socket_.send(json.dumps({"type": "edit", "frame": 99, "expr": [], "jaw": 0.0}))  # out of range: ignored
        params, _ = RunFrames(run).params(RunFrames(run).timesteps[1])
        edited = edited_params(run.head, params, [0.8, 0.0, 0.0], 0.3, 20.0, 0.0, viewer.centre)
        np.testing.assert_allclose(mesh, posed_head_vertices(run, edited, None).detach().numpy(), atol=1e-5)
        # the default avatar's hair follows the head: the turned head's pose code travels with its mesh, clamped to the
        # training frames' box as the CPU renderer clamps it (a 20 degree turn leaves the box)
        np.testing.assert_allclose(code, run.avatar.clamp_pose_code(head_pose_code(edited)).numpy(), atol=1e-6)
        assert np.abs(code - head_pose_code(edited).numpy()).max() > 0.1
        assert np.abs(code - head_pose_code(params).numpy()).max() > 0.01
        unedited = posed_head_vertices(run, *RunFrames(run).params(RunFrames(run).timesteps[1])).detach().numpy()
        assert np.abs(mesh - unedited).max() > 1e-3  # the jaw opened, the head turned
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        fetch(viewer.url)


def test_head_turn_edit_turns_the_head_about_its_centre(run):
    frames = RunFrames(run)
    params, _ = frames.params(frames.timesteps[0])
    centre = head_centre(run, params)
    turned = edited_params(run.head, params, [0.0], 0.0, 30.0, -10.0, centre)
    # Every posed point x' moves to T (x' - c) + c, T = yaw(30 deg about +y) pitch(-10 deg about +x).
    turn = axis_angle_to_matrix(torch.tensor([0.0, math.radians(30.0), 0.0])) @ axis_angle_to_matrix(
        torch.tensor([math.radians(-10.0), 0.0, 0.0]))
    before = run.head.forward_params(params).vertices[0]
    after = run.head.forward_params(turned).vertices[0]
    assert torch.allclose(after, (before - centre) @ turn.T + centre, atol=1e-5)
    assert float((after - before).norm(dim=-1).max()) > 0.01
    same = edited_params(run.head, params, [0.0, 0.0], 0.0, 0.0, 0.0, centre)
    assert all(torch.equal(same.to_npz()[k], v) for k, v in params.to_npz().items())
    smiling = edited_params(run.head, params, [0.5], 0.0, 0.0, 0.0, centre)
    assert float(smiling.expr[0, 0] - params.expr[0, 0]) == pytest.approx(0.5)


def test_view_command_starts_and_stops(run, capsys):
    assert view_app.view(run.info.run_dir, port=0, device="cpu", serve_forever=False) == 0
    assert "http://127.0.0.1:" in capsys.readouterr().out


def test_a_port_in_use_is_one_line(run, capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        with pytest.raises(LiveServerError, match=f"--port {port}: already in use"):
            view_app.start_viewer(run, port=port)
        assert cli.main(["view", str(run.info.run_dir), "--port", str(port), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("geoavatar view: ") and "already in use" in err
    with pytest.raises(LiveServerError, match="--host x..y"):  # a host name that cannot be encoded: one line, no hang
        view_app.start_viewer(run, host="x..y", port=0)
    server = LiveServer(small_player(1)[0], host="::1", port=0).start()  # IPv6: the address in brackets
    try:
        assert server.url.startswith("http://[::1]:")
    finally:
        server.stop()


def test_the_server_keeps_the_two_newest_meshes_per_browser(run):
    """Three meshes published before the loop's writer runs (the machine busy for a moment): the two newest are
    sent, in order, the oldest dropped and counted."""
    import threading

    from websockets.sync.client import connect

    viewer = view_app.start_viewer(run, port=0, live=True)
    try:
        server, count = viewer.server, run.head.num_vertices
        with connect(viewer.url.replace("http", "ws") + "ws") as client:
            assert server.wait_for_client(10.0)
            messages = [vertex_message(np.full((count, 3), k, np.float32), k) for k in range(3)]
            published = threading.Event()

            def burst() -> None:  # one callback of the loop: its writer cannot run between the three
                for message in messages:
                    server._publish(message, None)
                published.set()

            server._loop.call_soon_threadsafe(burst)
            assert published.wait(10.0)
            got = [received_mesh(client.recv(timeout=10), count) for _ in range(2)]
        assert [sequence for sequence, _ in got] == [1, 2] and float(got[1][1][0, 0]) == 2.0
        assert server.dropped == 1 and server.sent == 2
    finally:
        viewer.stop()


@pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")
def test_a_browser_counts_and_draws_every_live_mesh(run):
    viewer = view_app.start_viewer(run, port=0, live=True)
    try:
        frames = RunFrames(run)
        meshes = [posed_head_vertices(run, *frames.params(t)).detach() for t in frames.timesteps]
        codes = [head_pose_code(frames.params(t)[0]) for t in frames.timesteps]  # [6] each
        with chromium_page(160, 120) as page:
            page.goto(viewer.url)
            page.wait_for_function("window.geoavatar && window.geoavatar.stats.ready", timeout=120_000)
            assert viewer.server.wait_for_client(30.0)
            for k, mesh in enumerate(meshes):
                viewer.show_live(mesh, read_time=None, code=codes[k])
                page.wait_for_function(f"window.geoavatar.stats.received === {k + 1}", timeout=60_000)
            shown = np.asarray(page.evaluate("Array.from(window.geoavatar.player.liveVertices)"), dtype=np.float32)
            np.testing.assert_array_equal(shown, meshes[-1].numpy().reshape(-1))
            shown_code = page.evaluate("Array.from(window.geoavatar.player.liveCode)")
            np.testing.assert_allclose(shown_code, codes[-1].numpy(), rtol=1e-6)
            page.wait_for_function("window.geoavatar.stats.frameCostMs > 0")
        assert viewer.server.sent == len(meshes)
    finally:
        viewer.stop()


@pytest.mark.skipif(browser_missing() is not None, reason=f"browser tests: {browser_missing()}")
def test_the_pages_jaw_slider_is_posed_in_python_and_shown(run):
    viewer = view_app.start_viewer(run, port=0, expr_sliders=2)
    try:
        with chromium_page(320, 240) as page:
            page.goto(viewer.url + "?frame=2&paused=1")
            page.wait_for_function("window.geoavatar && window.geoavatar.stats.ready", timeout=120_000)
            sliders = page.locator("#edits input[type=range]")
            assert sliders.count() == 5  # two expressions, the jaw, head yaw and pitch
            sliders.nth(2).fill("0.25")
            sliders.nth(2).dispatch_event("input")
            page.wait_for_function("window.geoavatar.stats.received >= 1 && window.geoavatar.player.liveVertices",
                                   timeout=60_000)
            shown = np.asarray(page.evaluate("Array.from(window.geoavatar.player.liveVertices)"), dtype=np.float32)
            page.click("#edits button")  # reset: the page plays its own clip again
            page.wait_for_function("window.geoavatar.player.liveVertices === null", timeout=30_000)
        params, _ = RunFrames(run).params(RunFrames(run).timesteps[2])
        expected = posed_head_vertices(run, edited_params(run.head, params, [0.0, 0.0], 0.25, 0.0, 0.0,
                                                          viewer.centre), None)
        np.testing.assert_allclose(shown, expected.detach().numpy().reshape(-1), atol=1e-6)
    finally:
        viewer.stop()
