"""`geoavatar reenact RUN --driver-video VIDEO`: a short real clip tracked by prepare's pipeline into a cache that
the next call reuses, then re-enacted as with --driver; and each bad input as one line naming the file.

The clip is 6 frames of the shared test video at half size, the driver crop 64 px and the tracker's steps cut
(through prep.pipeline.tracking_config, which keys the stage too), so that each track costs about ten seconds on 2
cores."""

from __future__ import annotations

import json
from pathlib import Path

import av
import numpy as np
import pytest

from apps_fixtures import make_subject, make_untrained_run
from conftest import needs_shared_video, shared_video
from geoavatar import cli
from geoavatar.animation.sources.driver_video import driver_cache_dir
from geoavatar.apps import reenact as reenact_app
from geoavatar.errors import OptionError
from geoavatar.prep.pipeline import STAGES
from geoavatar.io.video import Mp4Writer
from geoavatar.prep.errors import PrepareError

needs_video = needs_shared_video("wojtek.mp4")
FRAMES = 6


def write_clip(path: Path, frames: list[np.ndarray], fps: int = 25) -> Path:
    with Mp4Writer(path, fps=fps) as video:
        for rgb in frames:
            video.write(rgb)
    return path


def decode(path: Path) -> list[np.ndarray]:
    with av.open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]


@pytest.fixture(autouse=True)
def short_tracking(monkeypatch):
    """The landmark fit with few steps: the stage's key follows, so the cache is still checked honestly."""
    from geoavatar.prep import pipeline
    from geoavatar.prep.tracking import TrackingConfig

    monkeypatch.setattr(pipeline, "tracking_config",
                        lambda config: TrackingConfig(rigid_steps=20, full_steps=30, fit_static_offset=config.static_offset))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("reenact-video")
    return make_untrained_run(make_subject(root / "data", frames=6), root / "run")


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    video = shared_video("wojtek.mp4")
    from geoavatar.prep.video import decode_frames

    frames = [rgb[::2, ::2].copy() for _, rgb in decode_frames(video, max_frames=FRAMES)]  # 256 px
    return write_clip(tmp_path_factory.mktemp("clip") / "talk.mp4", frames, fps=20)


@needs_video
def test_driver_video_is_tracked_cached_and_reenacted(run_dir, clip, tmp_path, capsys):
    out = tmp_path / "first.mp4"
    assert reenact_app.reenact(run_dir, driver_video=clip, driver_size=64, out=out, relative=True, device="cpu",
                               progress=False) == 0
    frames = decode(out)
    assert len(frames) == FRAMES  # every frame of the clip, driver | avatar
    assert frames[0].shape[1] == 2 * frames[0].shape[0]
    with av.open(str(out)) as container:
        assert float(container.streams.video[0].average_rate) == 20.0  # the driver video's own rate
    cache = driver_cache_dir(run_dir, clip)
    assert cache.parent == run_dir / "drivers" and cache.name.startswith("talk-")
    report = json.loads((cache / "report.json").read_text())
    assert report["frames"] == FRAMES and report["size"] == 64 and report["fps"] == 20.0
    from geoavatar.data import open_subject

    assert open_subject(cache / "dataset").head_model == "openhead"
    written = (cache / "dataset" / "transforms.json").stat().st_mtime_ns
    capsys.readouterr()

    # the second call reuses every stage of the cache, and the absolute transfer works the same way
    second = tmp_path / "second.mp4"
    assert reenact_app.reenact(run_dir, driver_video=clip, driver_size=64, out=second, max_frames=3, device="cpu",
                               progress=False) == 0
    printed = capsys.readouterr().out
    assert printed.count("is complete, skipped") == len(STAGES), printed
    assert (cache / "dataset" / "transforms.json").stat().st_mtime_ns == written
    assert len(decode(second)) == 3

    # another crop size is another track: the stages are redone in the same folder
    assert reenact_app.reenact(run_dir, driver_video=clip, driver_size=48, out=second, max_frames=1, device="cpu",
                               progress=False) == 0
    assert "is complete, skipped" not in capsys.readouterr().out
    assert json.loads((cache / "report.json").read_text())["size"] == 48


@needs_video
def test_driver_cache_option_and_default_name(run_dir, clip, tmp_path):
    cache = tmp_path / "cache"
    assert reenact_app.reenact(run_dir, driver_video=clip, driver_cache=cache, driver_size=64, max_frames=1,
                               side_by_side=False, device="cpu", progress=False) == 0
    assert (cache / "dataset" / "transforms.json").is_file()
    assert (run_dir / "videos" / "reenact_talk.mp4").is_file()  # named after the video's stem


def test_exactly_one_driver_and_its_options(run_dir, tmp_path):
    with pytest.raises(OptionError, match="exactly one of --driver"):
        reenact_app.reenact(run_dir)
    with pytest.raises(OptionError, match="exactly one of --driver"):
        reenact_app.reenact(run_dir, tmp_path, driver_video=tmp_path / "a.mp4")
    with pytest.raises(OptionError, match="go with --driver-video"):
        reenact_app.reenact(run_dir, tmp_path, photometric=True)
    with pytest.raises(OptionError, match="--driver-size must be at least 32"):
        reenact_app.reenact(run_dir, driver_video=tmp_path / "a.mp4", driver_size=16)


def test_bad_driver_videos_are_one_line_errors(run_dir, tmp_path, capsys):
    drivers = run_dir / "drivers"
    before = sorted(drivers.iterdir()) if drivers.exists() else None
    missing = tmp_path / "missing.mp4"
    not_video = tmp_path / "notes.mp4"
    not_video.write_bytes(b"not a video at all" * 50)
    blank = write_clip(tmp_path / "blank.mp4", [np.full((96, 96, 3), 40 + 20 * i, np.uint8) for i in range(6)])
    for path, reason in ((missing, "file not found"), (not_video, "not a readable video"),
                         (blank, "no face was found")):
        with pytest.raises(PrepareError, match=f"--driver-video: video '.*{path.name}'.*{reason}"):
            reenact_app.reenact(run_dir, driver_video=path, driver_size=64, device="cpu", progress=False)
        # through the CLI: one line, exit status 2, no traceback
        assert cli.main(["reenact", str(run_dir), "--driver-video", str(path), "--driver-size", "64", "--device",
                         "cpu", "--no-progress"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("geoavatar reenact: --driver-video: video") and path.name in err[-1], err
        assert not any(line.startswith("Traceback") for line in err)
    assert (sorted(drivers.iterdir()) if drivers.exists() else None) == before  # nothing left behind
