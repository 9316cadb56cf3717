"""prepare's gaussian stage on a few frames of a real video: every frame's parameters refitted against a quick
Gaussian head (train/gaussian_refit.py), and the written ones back when the stage is turned off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_video
from geoavatar.head.params import FRAME_KEYS


def _config(video: Path, out: Path, refit: bool):
    from geoavatar.apps.prepare import _gaussian_refit
    from geoavatar.prep.pipeline import PrepareConfig

    return PrepareConfig(video=video, out=out, size=96, max_frames=8, tracking_steps=(40, 60), photometric=False,
                         overlay=False, workers=1, progress=False, log=lambda message: None, gaussian_refit=refit,
                         gaussian_steps=40, gaussian_resolution=64, gaussian_runner=_gaussian_refit)


def _rows(dataset: Path, like: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The dataset's per-frame rows [T, W], each cut to the width of `like`'s (the files pad expressions)."""
    from geoavatar.data.dataset import open_subject

    params = open_subject(dataset).params
    return {key: params[key].numpy().reshape(len(like[key]), -1)[:, :like[key].shape[-1]] for key in FRAME_KEYS}


@pytest.fixture(scope="module")
def refitted(tmp_path_factory):
    from geoavatar.prep.pipeline import fit_file, run_prepare

    out = tmp_path_factory.mktemp("gaussian") / "wojtek"
    config = _config(shared_video("wojtek.mp4"), out, refit=True)
    dataset = run_prepare(config)
    fit = dict(np.load(fit_file(config, out / ".prepare")))
    written = {key: fit[f"param_{key}"].reshape(len(fit[f"param_{key}"]), -1) for key in FRAME_KEYS}  # [T, W]
    return out, dataset, written


def test_every_frame_is_refitted_and_the_test_frames_fit_better(refitted):
    out, dataset, written = refitted
    report = json.loads((out / "report.json").read_text())["gaussian_refit"]
    assert report["frames"] == 8 and report["test_frames"] == 2  # prepare's last 20 %, rounded up
    assert report["l1"]["mean"] < report["l1"]["mean_before"]  # the fit improved the test frames against the head
    rows = _rows(dataset, written)
    for key in ("rotation", "translation", "expr"):
        moved = np.abs(rows[key] - written[key]).max(axis=1)  # [T]
        assert (moved > 0).all(), key  # training frames refined by the head's training, test frames fitted
    assert report["test_head_moved_mm"]["max"] > 0
    head = next((out / ".prepare").glob("gaussian-*/head"))
    assert (head / "train.log").is_file() and not (head / "checkpoints").exists()  # no hundreds of MB left behind
    assert (out / ".prepare" / "gaussian.applied").is_file()


def test_turning_the_refit_off_gives_the_written_parameters_back(refitted):
    from geoavatar.prep.pipeline import run_prepare

    out, dataset, written = refitted
    messages: list[str] = []
    config = _config(shared_video("wojtek.mp4"), out, refit=False)
    config.log = messages.append
    run_prepare(config)
    assert "prepare: stage 'write' is complete, skipped" in messages  # only the last stage ran again
    rows = _rows(dataset, written)
    for key in FRAME_KEYS:
        np.testing.assert_allclose(rows[key], written[key], atol=1e-6)
    assert not (out / ".prepare" / "gaussian.applied").exists()
    assert not list((out / ".prepare").glob("gaussian-*"))  # the head's log and pictures go with it


def test_the_stage_refuses_to_run_without_its_runner(tmp_path):
    from geoavatar.prep.errors import PrepareError
    from geoavatar.prep.pipeline import stage_gaussian

    video = tmp_path / "talk.mp4"  # never decoded: the stage's key only reads the file's size and time
    video.write_bytes(b"")
    config = _config(video, tmp_path, refit=True)
    config.gaussian_runner = None
    (tmp_path / "work").mkdir()
    with pytest.raises(PrepareError, match="gaussian_runner"):
        stage_gaussian(config, tmp_path / "work", None)
