"""Tracking against a trained avatar (geoavatar.train.avatar_tracking, `geoavatar track --avatar RUN`): a known
head motion is recovered with the avatar as the appearance model; the command keeps the run's refined
parameters for its training frames and fits the others."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from apps_fixtures import make_subject, make_untrained_run
from geoavatar.avatar import render_avatar
from geoavatar.data.dataset import DataConfig, HeadAvatarDataset, open_subject
from geoavatar.errors import OptionError
from geoavatar.head.params import FRAME_KEYS, HeadParams
from geoavatar.render.camera import Camera
from geoavatar.train.avatar_tracking import AvatarFrame, AvatarTrackingConfig, track_frame, track_frames
from geoavatar.train.checkpoint import load_run


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("avatar_tracking")
    data = make_subject(root / "data", frames=8, size=64)
    run = make_untrained_run(data, root / "run", init_opacity=0.9)
    return data, run


def _frame_of(run, data, index: int = 0):
    """The dataset's frame `index` with the avatar's own render (T = 0) as its image: the truth is its parameters."""
    dataset = HeadAvatarDataset(open_subject(data), "all", DataConfig(resolution=run.info.resolution))
    item = dataset[index]
    params = HeadParams.from_npz(item["params"])
    camera = Camera(item["viewmat"], item["K"], item["width"], item["height"])
    with torch.no_grad():
        image = render_avatar(run.avatar, run.head, params, camera, None, run.deformer, item["background"]).result.rgb
    mask = torch.ones(*image.shape[:2], 1)
    return AvatarFrame(params, camera, image.clamp(0, 1), mask, item["background"]), params


def _vertex_error(run, a: HeadParams, b: HeadParams) -> float:
    with torch.no_grad():
        return float((run.head.forward_params(a).vertices - run.head.forward_params(b).vertices).norm(dim=-1).mean())


def test_a_known_head_motion_is_recovered_against_the_avatar(tiny):
    data, run_dir = tiny
    run = load_run(run_dir, torch.device("cpu"))
    frame, truth = _frame_of(run, data)
    moved = truth.replace(translation=truth.translation + torch.tensor([[0.004, -0.003, 0.002]]),
                          rotation=truth.rotation + torch.tensor([[0.0, 0.03, 0.01]]))
    start = frame._replace(params=moved)
    config = AvatarTrackingConfig(steps=60, keys=("rotation", "translation"))
    trained = {k: v.clone() for k, v in run.avatar.state_dict().items()}
    fitted, before, after = track_frame(run.avatar, run.head, run.deformer, start, config)
    assert after < 0.5 * before
    assert _vertex_error(run, fitted, truth) < 0.3 * _vertex_error(run, moved, truth)
    # the avatar is frozen: the fit moved no Gaussian and accumulated no gradient in it
    assert all(torch.equal(v, trained[k]) for k, v in run.avatar.state_dict().items())
    assert all(p.grad is None for p in run.avatar.parameters())


def test_a_frame_without_a_mask_is_left_as_tracked(tiny):
    data, run_dir = tiny
    run = load_run(run_dir, torch.device("cpu"))
    frame, truth = _frame_of(run, data)
    empty = frame._replace(mask=torch.zeros_like(frame.mask))
    result = track_frames(run.avatar, run.head, run.deformer, [empty, frame], AvatarTrackingConfig(steps=2))
    assert math.isnan(result.loss_before[0]) and math.isnan(result.loss_after[0])
    for key in FRAME_KEYS:
        assert torch.equal(getattr(result.params, key)[:1], getattr(truth, key))
    assert result.loss_after[1] <= result.loss_before[1]


def test_track_command_fits_the_held_out_frames_and_keeps_the_runs_own(tiny, tmp_path):
    from geoavatar.apps.track import track

    data, run_dir = tiny
    run = load_run(run_dir, torch.device("cpu"))
    out = tmp_path / "tracked"
    assert track(data, out, avatar=run_dir, steps=3, progress=False) == 0
    report = json.loads((out / "track.json").read_text())["avatar_tracking"]
    train, test = run.info.timesteps["train"], run.info.timesteps["test"]
    assert report["from_run"] == sorted(train) and report["fitted"] == sorted(test)
    assert len(report["l1"]["per_frame"]) == len(test)
    fitted = open_subject(out).params
    source = open_subject(data).params
    refined = run.info.frame_params
    rows = {t: i for i, t in enumerate(open_subject(out).timesteps)}
    for t in train:  # exactly the run's refined parameters
        assert np.allclose(fitted["translation"][rows[t]].numpy(), refined["translation"][rows[t]].numpy(), atol=1e-7)
    assert any(not np.allclose(fitted["translation"][rows[t]].numpy(), source["translation"][rows[t]].numpy())
               for t in test)  # the held-out frames moved
    # eval on the copy reports beside the run's own report, never over it
    from geoavatar.apps.eval import eval_runs

    assert eval_runs([run_dir], data=out, mouth=False, floaters=False, max_frames=1, progress=False) == 0
    assert (run_dir / "eval" / "test@tracked" / "metrics.json").is_file()
    assert not (run_dir / "eval" / "test").exists()
    # --refit-trained fits every frame
    assert track(data, tmp_path / "all", avatar=run_dir, steps=1, refit_trained=True, progress=False) == 0
    report = json.loads((tmp_path / "all" / "track.json").read_text())["avatar_tracking"]
    assert report["from_run"] == [] and len(report["fitted"]) == len(train) + len(test)


def test_track_fits_the_held_out_frames_as_train_does_on_any_number_of_workers(tiny, tmp_path):
    """`track --avatar` cuts its frames into the held-out fit's blocks: on the run's own dataset it gives train's
    held-out rows, on one worker process or two."""
    import shutil

    from geoavatar.apps.track import track
    from geoavatar.train.held_out_fit import HeldOutFitConfig, fit_held_out, read_held_out

    data, run_dir = tiny
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    fit_held_out(copy, HeldOutFitConfig(steps=2), workers=1, progress=False, log=lambda line: None)
    held = read_held_out(copy, load_run(copy).info.step)
    for workers in (1, 2):
        out = tmp_path / f"tracked_{workers}"
        assert track(data, out, avatar=run_dir, steps=2, workers=workers, progress=False) == 0
        tracked = open_subject(out)
        rows = {t: i for i, t in enumerate(tracked.timesteps)}
        for key in FRAME_KEYS:
            got = np.stack([tracked.params[key][rows[t]].numpy() for t in held.timesteps])
            assert np.allclose(got, held.rows[key], atol=1e-6), key


def test_track_command_refuses_options_that_do_not_apply(tiny, tmp_path):
    from geoavatar.apps.track import track

    data, run_dir = tiny
    with pytest.raises(OptionError, match="--fit-shape"):
        track(data, tmp_path / "x", avatar=run_dir, fit_shape=True, progress=False)
    with pytest.raises(OptionError, match="--refit-trained"):
        track(data, tmp_path / "x", refit_trained=True, progress=False)
    with pytest.raises(OptionError, match="--steps"):
        track(data, tmp_path / "x", avatar=run_dir, steps=-1, progress=False)
    with pytest.raises(OptionError, match="--workers"):
        track(data, tmp_path / "x", workers=2, progress=False)
    with pytest.raises(OptionError, match="--workers"):
        track(data, tmp_path / "x", avatar=run_dir, workers=0, progress=False)
    assert not (tmp_path / "x").exists()
