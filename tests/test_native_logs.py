"""MediaPipe's and TensorFlow Lite's own log lines (written by their C++ to fd 2) stay out of the terminal, in the
process that loads MediaPipe and in prepare's worker processes; --verbose lets them through.

On a real face (a still photograph that matplotlib installs, no shared data), in fresh processes: each of these
lines is written once per process or per model, so only a new process shows whether they are kept out."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from conftest import face_photo_video
from geoavatar import cli
from geoavatar.runtime import NATIVE_LOGS

# What the libraries write (geoavatar/runtime.py): TFLite's delegate line, absl's pre-init warning, absl's W lines.
MARKERS = ("TensorFlow Lite", "absl::InitializeLog", "inference_feedback_manager.cc",
           "landmark_projection_calculator.cc", "W0000 ")
STOP = "stopped after the masks stage (the test)"

# `geoavatar prepare` as the command line runs it, stopped after the stages that use MediaPipe (frames: face detection;
# landmarks: face mesh; masks: selfie segmentation), so that it takes seconds.
PREPARE = f"""
import sys

if __name__ == "__main__":  # the worker processes are spawned: they import this file as another module
    from geoavatar.prep import pipeline
    from geoavatar.prep.errors import PrepareError

    def stop(*args):
        raise PrepareError({STOP!r})

    pipeline._RUNNERS["tracking"] = stop
    from geoavatar.cli import main

    sys.exit(main(sys.argv[1:]))
"""

# MediaPipe in this process, as drive's tracker and eval's face reader use it: a detector, a face mesh in video and
# in image mode, prepare's person segmenter; the face mesh's first face comes on its third frame.
IN_PROCESS = """
import numpy as np

from geoavatar.prep.landmarks import FaceDetector, FaceMesh
from geoavatar.prep.masks import PersonSegmenter
from geoavatar.prep.video import decode_frames

frames = [rgb for _, rgb in decode_frames(VIDEO)]
blank = np.full_like(frames[0], 90)
with FaceDetector() as detector, FaceMesh() as mesh, FaceMesh(static_images=True) as still, PersonSegmenter() as person:
    assert detector(frames[0]) is not None
    found = [mesh(rgb) is not None for rgb in [blank, blank, *frames]]
    assert found[:2] == [False, False] and all(found[2:]), found
    assert still(frames[0]) is not None and person(frames[0]).shape == frames[0].shape[:2]
print("ran")
"""


def _lines_of_the_libraries(text: str) -> list[str]:
    return [line for line in text.splitlines() if any(marker in line for marker in MARKERS)]


def _environment(**changes: str) -> dict[str, str]:
    env = {key: value for key, value in os.environ.items() if key not in (NATIVE_LOGS, "GLOG_minloglevel",
                                                                          "TF_CPP_MIN_LOG_LEVEL")}
    return {**env, **changes}


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    return face_photo_video(tmp_path_factory.mktemp("native-logs") / "face.mp4", frames=5, size=192)


@pytest.mark.parametrize("verbose", [False, True])
def test_prepare_keeps_them_out_of_the_terminal_unless_verbose(video, tmp_path, verbose):
    script = tmp_path / "prepare_command.py"
    script.write_text(PREPARE)
    argv = [sys.executable, str(script), "prepare", str(video), "--out", str(tmp_path / "out"), "--size", "64",
            "--workers", "2", "--no-progress", "--no-overlay"] + (["--verbose"] if verbose else [])
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300, env=_environment())
    assert done.returncode == 2 and STOP in done.stderr, done.stderr[-3000:]  # every stage before tracking ran
    printed = _lines_of_the_libraries(done.stdout + done.stderr)
    if verbose:  # through, from both workers: every library's kind of line
        for marker in MARKERS:
            assert any(marker in line for line in printed), (marker, done.stderr[-3000:])
    else:
        assert printed == [], printed
        assert done.stderr.strip().splitlines()[-1] == f"geoavatar prepare: {STOP}"  # our own lines still show


@pytest.mark.parametrize("shown", [False, True])
def test_mediapipe_in_the_main_process(video, tmp_path, shown):
    script = tmp_path / "in_process.py"
    script.write_text(f"VIDEO = {str(video)!r}\n" + textwrap.dedent(IN_PROCESS))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                          env=_environment(**({NATIVE_LOGS: "1"} if shown else {})))
    assert done.returncode == 0 and done.stdout == "ran\n", done.stderr[-3000:]
    printed = _lines_of_the_libraries(done.stderr)
    if shown:
        assert any("landmark_projection_calculator.cc" in line for line in printed), done.stderr
    else:
        assert printed == [] and done.stderr == "", done.stderr


def test_verbose_reaches_the_worker_processes_through_the_environment(tmp_path, monkeypatch):
    """prepare and drive --verbose set GEOAVATAR_NATIVE_LOGS=1 while they run (spawned workers inherit it), and
    leave the environment as it was."""
    from geoavatar.apps import drive as drive_app
    from geoavatar.apps import prepare as prepare_app

    monkeypatch.delenv(NATIVE_LOGS, raising=False)
    seen = []
    monkeypatch.setattr(prepare_app, "run_prepare", lambda config: seen.append(os.environ.get(NATIVE_LOGS)) or
                        Path(config.out) / "dataset")
    monkeypatch.setattr(prepare_app, "capture_verdict", lambda out: "capture check: -")
    monkeypatch.setattr(drive_app, "open_video", lambda path: None)
    monkeypatch.setattr(drive_app, "open_run", lambda run, device, flame_dir: None)

    class Stats:
        init_frames, init_seconds = 0, 0.0

        def summary(self):
            return "-"

    monkeypatch.setattr(drive_app, "drive_avatar", lambda *a, **k: seen.append(os.environ.get(NATIVE_LOGS)) or Stats())
    video = tmp_path / "talk.mp4"
    video.write_bytes(b"")
    for verbose in ([], ["--verbose"]):
        assert cli.main(["prepare", str(video), "--out", str(tmp_path / "out"), *verbose]) == 0
        drive = ["drive", str(tmp_path), "--video", str(video), "--out", str(tmp_path / "o.mp4")]
        assert cli.main([*drive, *verbose]) == 0
    assert seen == [None, None, "1", "1"] and NATIVE_LOGS not in os.environ
