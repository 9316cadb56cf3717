"""`geoavatar drive`: a short clip cut from the real test video (128 px) drives a tiny untrained avatar;
frames come out, drops are counted, the online fit follows the landmarks; bad sources are one-line errors."""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np
import pytest

from apps_fixtures import make_subject, make_untrained_run
from conftest import needs_shared_video, shared_video
from geoavatar.animation.sources.capture import NewestFrame, open_video
from geoavatar.animation.sources.capture import VideoInput as Source
from geoavatar.apps.drive import drive_avatar
from geoavatar.cli import main

needs_video = needs_shared_video("wojtek.mp4")
INIT_STEPS = (30, 60)  # the identity stage's tracker steps (prepare uses 100, 300)


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    """The first 30 frames of wojtek.mp4 at 128 px, 25 fps."""
    source = shared_video("wojtek.mp4")
    import cv2

    from geoavatar.io.video import Mp4Writer
    from geoavatar.prep.video import decode_frames

    path = tmp_path_factory.mktemp("drive") / "clip.mp4"
    with Mp4Writer(path, fps=25) as video:
        for _index, rgb in decode_frames(source, max_frames=30):
            video.write(cv2.resize(rgb, (128, 128), interpolation=cv2.INTER_AREA))
    return path


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("drive_run")
    return make_untrained_run(make_subject(root / "subject", frames=6), root / "run")


@pytest.fixture(scope="module")
def run(run_dir):
    from geoavatar.train.checkpoint import open_run

    return open_run(run_dir, "cpu")


def test_newest_frame_drops_what_the_worker_did_not_take():
    box = NewestFrame()
    for i in range(3):
        box.put(i)
    assert box.get() == 2 and box.dropped == 2 and box.delivered == 3
    box.put(3)
    box.close()
    assert box.get() == 3 and box.get() is None  # closed and empty: the end


def test_a_deeper_mailbox_keeps_the_newest_items_in_order():
    box = NewestFrame(depth=2)
    for i in range(4):
        box.put(i)
    assert box.dropped == 2 and box.get() == 2 and box.get() == 3  # the oldest waiting first
    box.close()
    assert box.get() is None


def test_a_lossless_mailbox_makes_the_reader_wait_before_it_stamps_a_frame():
    box = NewestFrame(lossless=True, depth=2)
    box.put(0)
    waited = threading.Event()

    def reader():
        box.wait_for_room()  # the identity stage holds frame 0: the next frame's time is taken after this
        waited.set()

    thread = threading.Thread(target=reader)
    thread.start()
    assert not waited.wait(0.2)
    box.set_lossless(False)  # the identity stage ends: the file's clock starts
    assert waited.wait(5.0)
    thread.join(5)


def test_newest_frame_hands_on_the_reader_error():
    box = NewestFrame()
    box.close(RuntimeError("camera unplugged"))
    with pytest.raises(RuntimeError, match="unplugged"):
        box.get()


def test_lossless_mailbox_waits_for_the_worker():
    box = NewestFrame(lossless=True)
    got = []

    def worker():
        while (item := box.get()) is not None:
            got.append(item)

    thread = threading.Thread(target=worker)
    thread.start()
    for i in range(20):
        box.put(i)
    box.close()
    thread.join(5)
    assert got == list(range(20)) and box.dropped == 0


@needs_video
def test_drive_every_frame_writes_the_video_and_follows_the_face(run, clip, tmp_path):
    out = tmp_path / "drive.mp4"
    stats = drive_avatar(run, open_video(clip), out, size=48, init_seconds=0.2, lossless=True, record=True,
                         status=False, init_steps=INIT_STEPS)
    assert stats.dropped == 0 and stats.delivered == stats.processed == 30
    assert stats.init_frames == 5 and stats.frames == 30 - 5 - 1  # FPS counts from the first online frame's end
    assert all(len(v) == 25 for k, v in stats.stage_ms.items())
    online = [r for r in stats.records if not r.get("init")]
    assert len(online) == 25 and all(r["found"] for r in online)
    errors = np.array([r["error"] for r in online])
    assert np.median(errors) < 0.03, errors  # median landmark error under 3 % of the face width
    jaw = np.array([r["jaw_pose"][0] for r in stats.records])
    assert np.isfinite(jaw).all()
    import av

    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 25 and frames[0].shape == (48, 96, 3)  # driver | avatar


@needs_video
def test_a_fast_source_drops_frames_and_counts_them(run, clip, tmp_path):
    fast = dataclasses.replace(open_video(clip), fps=400.0)  # 2.5 ms a frame: the worker cannot keep up
    out = tmp_path / "fast.mp4"
    stats = drive_avatar(run, fast, out, size=32, init_seconds=5 / 400, status=False, init_steps=INIT_STEPS)
    assert stats.delivered == 30 and stats.dropped > 0
    assert stats.processed + stats.dropped == stats.delivered
    import av

    with av.open(str(out)) as container:  # dropped frames repeat the last output: the video keeps real time
        count = sum(1 for _ in container.decode(video=0))
    assert stats.frames + 1 <= count <= 30


@needs_video
@pytest.mark.parametrize("transfer", ["relative", "subspace"])
def test_relative_and_subspace_driving_render(run, clip, tmp_path, transfer):
    stats = drive_avatar(run, open_video(clip), tmp_path / "rel.mp4", transfer, size=32, init_seconds=0.2,
                         lossless=True, max_frames=8, status=False, init_steps=INIT_STEPS)
    assert stats.init_frames == 5 and stats.processed == 8


@needs_video
def test_view_mode_streams_every_online_frame_to_the_browser(run, clip):
    import struct

    from websockets.sync.client import connect

    from geoavatar.apps.view import start_viewer

    viewer = start_viewer(run, port=0, live=True)
    try:
        shown = []
        show_live = viewer.show_live
        viewer.show_live = lambda vertices, info="", read_time=None, code=None: (
            shown.append((info, read_time)), show_live(vertices, info, read_time, code))
        with connect(viewer.url.replace("http", "ws") + "ws") as browser:
            assert viewer.server.wait_for_client(10.0)
            stats = drive_avatar(run, open_video(clip), None, viewer=viewer, size=32, init_seconds=0.2, lossless=True,
                                 max_frames=10, status=False, init_steps=INIT_STEPS)
            last = browser.recv(timeout=10)  # newest-only: at least the last mesh arrives
        assert stats.processed == 10 and len(shown) == 10 - 5 and shown[-1][0].startswith("live: frame 9")
        assert all(read_time is not None for _, read_time in shown)  # the frame's read time, for read -> sent
        assert not stats.stage_ms["render"]  # --view without --out: the browser renders, the render stage is skipped
        body = np.frombuffer(last[16:], dtype="<f4")  # the posed mesh, then its head pose code (the hair follows)
        vertices, code = body[:run.head.num_vertices * 3], body[run.head.num_vertices * 3:]
        assert struct.unpack("<I", last[:4])[0] == 1 and code.shape == (6,) and run.avatar.follows_head
        assert np.isfinite(vertices).all() and np.isfinite(code).all()
        assert viewer.server.sent >= 1 and len(viewer.server.latency_ms) == viewer.server.sent
        assert "read->sent" in viewer.summary()
    finally:
        viewer.stop()


def test_a_source_too_short_for_the_identity_stage_is_an_error(run, tmp_path):
    from geoavatar.animation.sources.capture import DriveError

    for out in (None, tmp_path / "o.mp4"):  # with an mp4 too: its "no frame" does not hide why
        blank = Source("--video blank", 25.0, lambda: iter([np.zeros((64, 64, 3), np.uint8)] * 3), live=False)
        with pytest.raises(DriveError, match="identity stage"):
            drive_avatar(run, blank, out, size=32, status=False, lossless=True)


def _one_line_error(capsys, argv: list[str], *needles: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("geoavatar drive: "), err
    for needle in needles:
        assert needle in err, err


def test_missing_and_unreadable_videos_are_one_line_errors(run_dir, tmp_path, capsys):
    _one_line_error(capsys, ["drive", str(run_dir), "--video", str(tmp_path / "none.mp4"), "--out", str(tmp_path / "o.mp4")],
                    "none.mp4", "not found")
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"not a video at all" * 64)
    _one_line_error(capsys, ["drive", str(run_dir), "--video", str(bad), "--out", str(tmp_path / "o.mp4")],
                    "broken.mp4", "not a readable video")


def test_missing_camera_is_a_one_line_error(run_dir, tmp_path, capsys):
    if Path("/dev/video63").exists():
        pytest.skip("a /dev/video63 exists here")
    _one_line_error(capsys, ["drive", str(run_dir), "--camera", "63", "--out", str(tmp_path / "o.mp4")],
                    "--camera 63", "cannot open")


def test_options_are_checked(run_dir, tmp_path, capsys):
    _one_line_error(capsys, ["drive", str(run_dir), "--out", str(tmp_path / "o.mp4")], "--camera N or --video FILE")
    _one_line_error(capsys, ["drive", str(run_dir), "--camera", "0", "--video", "x.mp4", "--out", "o.mp4"], "one driving source")
    _one_line_error(capsys, ["drive", str(run_dir), "--camera", "0"], "--out", "--view")
    talk = tmp_path / "talk.mp4"
    talk.write_bytes(b"the user's video")
    _one_line_error(capsys, ["drive", str(run_dir), "--video", str(talk), "--out", str(talk)], "is the input video")
    assert talk.read_bytes() == b"the user's video"
    _one_line_error(capsys, ["drive", str(run_dir), "--video", str(talk), "--out", str(tmp_path / "o.mp4"),
                             "--max-frames", "0"], "--max-frames must be positive")
