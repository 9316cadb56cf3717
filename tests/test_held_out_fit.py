"""train's held-out fit (geoavatar.train.held_out_fit): the test frames fitted against the finished avatar, kept
beside the checkpoint, laid over the run's parameters while they belong to its step, used by eval on the run's
own dataset (and said so in metrics.json), never for another copy; the carry between neighbouring frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from apps_fixtures import make_subject, make_untrained_run
from geoavatar.avatar import render_avatar
from geoavatar.data.dataset import DataConfig, HeadAvatarDataset, open_subject
from geoavatar.head.params import FRAME_KEYS, HeadParams
from geoavatar.render.camera import Camera
from geoavatar.train import held_out_fit
from geoavatar.train.avatar_tracking import AvatarFrame, AvatarTrackingConfig, track_frames
from geoavatar.train.checkpoint import load_run
from geoavatar.train.held_out_fit import (HELD_OUT_FILE, RUN_LENGTH, WARM_UP, HeldOutFitConfig, fill_between,
                                          fit_held_out, fit_plan, is_fitted)
from geoavatar.train.run_frames import RunFrames


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("held_out")
    data = make_subject(root / "data", frames=10, size=64)
    run = make_untrained_run(data, root / "run", init_opacity=0.9)
    return data, run


def _own_render_frames(run, data, offset: dict[str, torch.Tensor], count: int = 5):
    """The first `count` frames of the dataset with the avatar's own render as its image (the truth: its parameters), and its
    start moved by the same `offset` (key -> [1, ...]): a tracker error the frames share."""
    dataset = HeadAvatarDataset(open_subject(data), "all", DataConfig(resolution=run.info.resolution))
    frames, truths = [], []
    for index in range(count):
        item = dataset[index]
        truth = HeadParams.from_npz(item["params"])
        camera = Camera(item["viewmat"], item["K"], item["width"], item["height"])
        with torch.no_grad():
            image = render_avatar(run.avatar, run.head, truth, camera, None, run.deformer, item["background"]).result.rgb
        moved = truth.replace(**{key: getattr(truth, key) + value for key, value in offset.items()})
        frames.append(AvatarFrame(moved, camera, image.clamp(0, 1), torch.ones(*image.shape[:2], 1), item["background"]))
        truths.append(truth)
    return frames, truths


def _vertex_error(run, fitted: HeadParams, truths: list[HeadParams]) -> float:
    errors = []
    with torch.no_grad():
        for row, truth in enumerate(truths):
            frame = fitted.replace(**{key: getattr(fitted, key)[row:row + 1] for key in FRAME_KEYS})
            errors.append(float((run.head.forward_params(frame).vertices
                                 - run.head.forward_params(truth).vertices).norm(dim=-1).mean()))
    return float(np.mean(errors[1:]))  # the first frame has nothing to carry from


def test_the_carry_reaches_a_shared_tracker_error_in_fewer_steps(tiny):
    data, run_dir = tiny
    run = load_run(run_dir, torch.device("cpu"))
    offset = {"translation": torch.tensor([[0.004, -0.003, 0.002]]), "rotation": torch.tensor([[0.0, 0.03, 0.01]])}
    frames, truths = _own_render_frames(run, data, offset)
    keys = ("rotation", "translation")
    plain = track_frames(run.avatar, run.head, run.deformer, frames, AvatarTrackingConfig(steps=6, keys=keys))
    carried = track_frames(run.avatar, run.head, run.deformer, frames,
                           AvatarTrackingConfig(steps=6, keys=keys, carry=True))
    assert _vertex_error(run, carried.params, truths) < 0.7 * _vertex_error(run, plain.params, truths)
    # the L1 before is the tracked start's either way
    assert np.allclose(carried.loss_before, plain.loss_before)


def test_the_fit_is_kept_with_its_step_and_rendered_on_the_runs_own_dataset_only(tiny, tmp_path, monkeypatch):
    data, run_dir = tiny
    before = load_run(run_dir, torch.device("cpu"))
    test = before.info.timesteps["test"]
    assert test and not before.info.held_out
    monkeypatch.setattr(held_out_fit, "BLOCK", 1)  # one task a frame: two workers share them
    report = fit_held_out(run_dir, HeldOutFitConfig(steps=3), workers=2, progress=False, log=lambda line: None)
    assert report["frames"] == len(test) and report["checkpoint_step"] == before.info.step
    assert json.loads((run_dir / "held_out.json").read_text())["steps"] == 3
    run = load_run(run_dir, torch.device("cpu"))
    assert sorted(run.info.held_out) == sorted(test)
    frames = RunFrames(run)
    tracked = open_subject(data).params
    moved = False
    for t in test:
        row = frames.row(t)
        from_dataset = HeadParams.from_npz({k: v[row:row + 1].float() for k, v in tracked.items()})
        own, _ = frames.params(t, from_dataset)
        copy, _ = frames.params(t, from_dataset, own_dataset=False)
        assert torch.equal(own.translation, run.info.frame_params["translation"][row:row + 1])
        assert torch.equal(copy.translation, from_dataset.translation)
        moved |= not torch.allclose(own.translation, from_dataset.translation)
    assert moved
    for t in run.info.timesteps["train"]:  # the training frames' rows are untouched
        row = frames.row(t)
        assert torch.equal(run.info.frame_params["expr"][row], before.info.frame_params["expr"][row])
    # one worker gives the same rows (the blocks do not depend on the worker count)
    first = dict(np.load(run_dir / HELD_OUT_FILE))
    fit_held_out(run_dir, HeldOutFitConfig(steps=3), workers=1, progress=False, log=lambda line: None)
    again = dict(np.load(run_dir / HELD_OUT_FILE))
    assert all(np.allclose(first[key], again[key], atol=1e-6) for key in FRAME_KEYS)


def test_eval_says_where_the_test_parameters_came_from_and_a_stale_fit_is_ignored(tiny):
    from geoavatar.apps.eval import eval_runs
    from geoavatar.io.atomic import atomic_write_npz

    data, run_dir = tiny
    fit_held_out(run_dir, HeldOutFitConfig(steps=1), workers=1, progress=False, log=lambda line: None)
    assert eval_runs([run_dir], mouth=False, floaters=False, faces=False, max_frames=1, progress=False) == 0
    settings = json.loads((run_dir / "eval" / "test" / "metrics.json").read_text())["settings"]
    assert settings["test_params"].startswith("fitted against this avatar")
    stored = dict(np.load(run_dir / HELD_OUT_FILE))
    atomic_write_npz(run_dir / HELD_OUT_FILE, **{**stored, "step": np.asarray(int(stored["step"]) + 5)})
    assert load_run(run_dir, torch.device("cpu")).info.held_out == []  # trained on since: stale
    assert eval_runs([run_dir], mouth=False, floaters=False, faces=False, max_frames=1, progress=False) == 0
    settings = json.loads((run_dir / "eval" / "test" / "metrics.json").read_text())["settings"]
    assert settings["test_params"] == "as the dataset holds them (no prepare or track report beside it)"


def test_a_long_split_is_fitted_in_runs_of_neighbours_spread_over_it():
    blocks, scored = fit_plan(70, 144)
    assert [len(b) for b in blocks] == [35, 35] and scored == list(range(70))  # all of a short video's, 2 tasks
    assert [len(b) for b in fit_plan(80, 144)[0]] == [20, 20, 20, 20]  # even: neither worker waits at the end
    assert [b[0] for b in fit_plan(144, 144)[0]] == [0, 36, 72, 108] and fit_plan(1, 144)[0] == [(0,)]
    blocks, scored = fit_plan(302, 144)
    picked = np.concatenate(blocks)
    assert len(picked) == 144 and picked[0] == 0 and picked[-1] == 301 and len(blocks) == 6
    runs = picked.reshape(-1, RUN_LENGTH)  # [24, 6] neighbours each, gaps between
    assert (np.diff(runs, axis=1) == 1).all() and (np.diff(runs[:, 0]) > RUN_LENGTH).all()
    assert scored == runs[:, WARM_UP:].reshape(-1).tolist()  # a run's first frames hand their correction on
    assert len(fit_plan(51, 2 * RUN_LENGTH)[0]) == 2  # two runs: a task each, both cores busy


def test_rows_between_fitted_frames_carry_their_neighbours_correction():
    timesteps = [10, 11, 12, 13, 14]
    tracked = {"translation": np.arange(15, dtype=np.float32).reshape(5, 3)}  # [N, 3]
    picked = [1, 3]
    fitted = {"translation": tracked["translation"][picked] + np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 3.0]], np.float32)}
    rows = fill_between(timesteps, tracked, picked, fitted)["translation"]
    correction = rows[:, 2] - tracked["translation"][:, 2]
    assert np.allclose(correction, [1.0, 1.0, 2.0, 3.0, 3.0])  # held beyond the ends, linear between
    assert np.array_equal(rows[picked], fitted["translation"]) and np.allclose(rows[:, :2], tracked["translation"][:, :2])


def test_a_long_test_split_is_fitted_in_runs_and_eval_scores_their_scored_frames(tmp_path):
    from geoavatar.apps.eval import eval_runs

    data = make_subject(tmp_path / "data", frames=40, size=64)
    run_dir = make_untrained_run(data, tmp_path / "run", init_opacity=0.9)
    before = load_run(run_dir, torch.device("cpu"))
    test = before.info.timesteps["test"]
    assert len(test) > RUN_LENGTH
    report = fit_held_out(run_dir, HeldOutFitConfig(steps=1, max_frames=RUN_LENGTH), workers=1, progress=False,
                          log=lambda line: None)
    assert report["frames"] == RUN_LENGTH and report["scored_frames"] == RUN_LENGTH - WARM_UP
    assert report["test_frames"] == len(test)
    run = load_run(run_dir, torch.device("cpu"))
    assert sorted(run.info.held_out) == sorted(test)  # every test frame has its row (the others filled between)
    assert run.info.held_out_scored == test[WARM_UP:RUN_LENGTH]  # one run, from the start
    frames, start = RunFrames(run), RunFrames(before)
    last = test[RUN_LENGTH - 1]
    for t in test[RUN_LENGTH:]:  # beyond the run: the tracker's rows plus the last fitted frame's correction
        correction = frames.values.translation[frames.row(last)] - start.values.translation[start.row(last)]
        assert torch.allclose(frames.values.translation[frames.row(t)],
                              start.values.translation[start.row(t)] + correction, atol=1e-6)
    assert eval_runs([run_dir], mouth=False, floaters=False, faces=False, progress=False) == 0
    metrics = json.loads((run_dir / "eval" / "test" / "metrics.json").read_text())
    assert [f["timestep"] for f in metrics["frames"]] == test[WARM_UP:RUN_LENGTH]
    assert metrics["settings"]["frames_left_out_unscored"] == len(test) - (RUN_LENGTH - WARM_UP)
    assert f"{RUN_LENGTH - WARM_UP} of the {len(test)} held-out frames scored" in metrics["settings"]["test_params"]
    # a --resume of the finished run keeps a fit made with its settings, and fits again with others
    assert is_fitted(run_dir, HeldOutFitConfig(steps=1, max_frames=RUN_LENGTH))
    assert not is_fitted(run_dir, HeldOutFitConfig(steps=1, max_frames=None))
    assert not is_fitted(run_dir, HeldOutFitConfig(steps=2, max_frames=RUN_LENGTH))
