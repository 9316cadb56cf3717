"""The capture check (geoavatar.prep.coverage, `geoavatar coverage`): a generated subject whose head never
turns gets a verdict that says so, the scripted one (turns, nods, expressions) does not; test frames beyond
what training saw are found, by reason. Generated subjects of 16 frames at 48 px."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from geoavatar.data.synth import SynthConfig, generate_dataset
from geoavatar.prep import coverage


def _subject(tmp_path_factory, name: str, still_head: bool):
    out = tmp_path_factory.mktemp("coverage") / name
    generate_dataset(out, SynthConfig(frames=16, size=48, seed=0, workers=1, still_head=still_head), progress=False)
    return out


@pytest.fixture(scope="module")
def still(tmp_path_factory):
    root = _subject(tmp_path_factory, "still", still_head=True)
    return root, coverage.dataset_capture_check(root, root.parent / "still_coverage")


@pytest.fixture(scope="module")
def scripted(tmp_path_factory):
    root = _subject(tmp_path_factory, "scripted", still_head=False)
    return root, coverage.dataset_capture_check(root, root.parent / "scripted_coverage")


def test_a_head_that_never_turns_is_called_out(still):
    root, report = still
    train = report["splits"]["train"]
    assert train["frames"] == 12 and report["splits"]["test"]["frames"] == 4
    assert train["yaw"]["max"] - train["yaw"]["min"] < coverage.STILL_DEG  # tracker-like error only
    assert report["verdict"].startswith("capture check: the head hardly turns")
    assert "turn your head slowly left and right" in report["verdict"]
    assert any("hardly nods" in item for item in report["advice"])
    saved = json.loads((root.parent / "still_coverage" / "coverage.json").read_text())
    assert saved["verdict"] == report["verdict"] and saved["dataset"] == str(root)
    with Image.open(root.parent / "still_coverage" / "coverage.png") as picture:
        assert picture.format == "PNG" and picture.size[0] > 1000


def test_a_head_that_turns_and_nods_is_not(scripted):
    _, report = scripted
    train = report["splits"]["train"]
    assert train["yaw"]["max"] - train["yaw"]["min"] > 30.0  # the script sweeps yaw over about -22..+30 degrees
    assert not any("hardly" in item for item in report["advice"])
    assert "hardly" not in report["verdict"]
    assert train["shows"]["smile"] > 0  # a held smile


def _measures(yaw, jaw, count):
    """FrameMeasures of `count` frames looking straight at the camera but for `yaw` (deg) and `jaw` (deg)."""
    yaw, jaw = np.broadcast_to(yaw, count).astype(float), np.broadcast_to(jaw, count).astype(float)
    radians = np.radians(yaw)
    directions = np.stack([np.sin(radians), np.zeros(count), np.cos(radians)], -1)
    zeros = np.zeros(count)
    return coverage.FrameMeasures(yaw=yaw, pitch=zeros, jaw=jaw, smile=zeros, brows=zeros, eyes=np.ones(count),
                                  gaze_yaw=zeros, gaze_pitch=zeros, directions=directions)


def test_test_frames_outside_training_are_found_by_reason():
    # training: yaw -10..+10, jaw up to 15 deg; test: 4 frames within, 3 turned to +30, 2 with the jaw at 25
    yaw = np.r_[np.linspace(-10, 10, 20), [0, 5, -5, 8], [30, 31, 32], [0, 0]]
    jaw = np.r_[np.linspace(0, 15, 20), [5, 5, 5, 5], [5, 5, 5], [25, 25]]
    measures = _measures(yaw, jaw, len(yaw))
    splits = {"train": np.arange(20), "test": np.arange(20, 29)}
    report = coverage.capture_report(measures, splits, np.arange(100, 129))
    outside = report["test_outside"]
    assert outside["frames"] == 5 and outside["timesteps"] == "124-128"
    assert outside["by_measure"]["view"]["timesteps"] == "124-126"
    assert outside["by_measure"]["jaw"]["timesteps"] == "127-128"
    assert any(item.startswith("the test segment leaves what training saw in 56%") for item in report["advice"])


def test_the_command_prints_the_verdict_and_bad_input_is_one_line(still, tmp_path, capsys):
    from geoavatar.cli import main

    root, report = still
    assert main(["coverage", str(root), "--out", str(tmp_path / "c")]) == 0
    printed = capsys.readouterr().out
    assert printed.splitlines()[0] == report["verdict"] and (tmp_path / "c" / "coverage.png").is_file()
    assert main(["coverage", str(tmp_path / "missing")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "missing: dataset folder not found" in error


def test_blinks_the_tracking_smoothed_away_are_told_apart_from_no_blinks():
    measures = _measures(np.zeros(20), np.full(20, 12.0), 20)
    measures.eyes[:] = np.linspace(0.7, 1.1, 20)  # the tracked eyelids never close
    measures.smile[5], measures.brows[6] = 5.0, 3.0  # a smile and raised brows: only the blinks are in question
    splits = {"train": np.arange(20)}
    never = coverage.capture_report(measures, splits, np.arange(20))
    assert "blink now and then" in " ".join(never["advice"])
    detected = np.ones(20)
    detected[[4, 5, 12]] = 0.2  # the face mesh saw two short blinks
    seen = coverage.capture_report(measures, splits, np.arange(20), detected_eyes=detected)
    assert seen["splits"]["train"]["face_mesh_blinks"] == 2
    assert not any("blink now and then" in item for item in seen["advice"])
    assert any(item.startswith("the face mesh saw 2 blink(s) but the tracked eyelids close only to 70%")
               for item in seen["advice"])
