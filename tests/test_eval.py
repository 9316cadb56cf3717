"""`geoavatar eval` end to end on a tiny generated subject (64 px, 8 frames: 2 test frames).

Runs: preset E trained for 2 steps with `train()`, and an untrained preset-A run (its step-0
checkpoint written with the trainer's own state functions) for the comparison table: the metrics'
values are checked in test_metrics.py; here the protocol, the files and the errors.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from geoavatar.apps.eval import eval_runs
from geoavatar.config import preset
from geoavatar.data.splits import ShortVideoWarning
from geoavatar.errors import OptionError
from geoavatar.eval import evaluate as evaluate_module
from geoavatar.eval.evaluate import crop_box, mouth_face_mask, mouth_mask, open_run_dataset, render_run_frames
from geoavatar.train import checkpoint as ckpt
from geoavatar.train.checkpoint import RunError
from geoavatar.train.checkpoint import state_payload
from geoavatar.train.options import RunOptions
from geoavatar.train.state import new_state, open_training_data
from geoavatar.train.trainer import train


def _options(data: Path, out: Path, name: str) -> RunOptions:
    return RunOptions(data=data, out=out, seed=1, device="cpu", progress=False, val_every=1000, ckpt_every=1000,
                      preset=name)


@pytest.fixture(scope="module")
def subject(tmp_path_factory) -> Path:
    from geoavatar.data.synth.generate import SynthConfig, generate_dataset

    out = tmp_path_factory.mktemp("eval-subject") / "tiny"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        generate_dataset(out, SynthConfig(subject=0, frames=8, size=64, seed=0), progress=False)
    return out


@pytest.fixture(scope="module")
def run_e(subject, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("eval-runs") / "E"
    config = preset("E", steps=2)
    config = replace(config, model=replace(config.model, init_opacity=0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        train(_options(subject, out, "E"), config)
    return out


@pytest.fixture(scope="module")
def run_a(subject, tmp_path_factory) -> Path:
    """An untrained preset-A run: the step-0 state saved as the trainer saves its checkpoints."""
    out = tmp_path_factory.mktemp("eval-runs") / "A"
    options, config = _options(subject, out, "A"), preset("A", steps=2).validate()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        data = open_training_data(options, config)
    ckpt.save_checkpoint(ckpt.run_checkpoint_path(out, "last"), state_payload(new_state(data, config, 1), data, config,
                                                                              options))
    return out


def _table_rows(markdown: str) -> list[str]:
    return [line.split("|")[1].strip() for line in markdown.splitlines() if line.startswith("| ")]


def test_eval_one_run_writes_json_and_table(run_e, capsys):
    assert eval_runs([run_e], progress=False, device="cpu", save_images=True) == 0
    folder = run_e / "eval" / "test"
    report = json.loads((folder / "metrics.json").read_text())
    assert report["format"] == "geoavatar-eval" and report["split"] == "test" and report["preset"] == "E"
    assert [f["timestep"] for f in report["frames"]] == [6, 7]  # the last 25 % of 8 frames
    for frame in report["frames"]:
        assert frame["psnr"] == pytest.approx(-10 * math.log10(frame["mse"]))
        assert 0.0 < frame["ssim"] < 1.0 and frame["lpips"] > 0.0
        assert frame["mouth_pixels"] > 0 and frame["mouth_psnr"] is not None and frame["mouth_lpips"] > 0.0
        y0, y1, x0, x1 = frame["mouth_box"]
        assert y1 - y0 >= 32 and x1 - x0 >= 32
    summary = report["summary"]
    psnrs = [f["psnr"] for f in report["frames"]]
    assert summary["psnr"]["mean"] == pytest.approx(sum(psnrs) / 2)
    assert summary["psnr"]["std"] == pytest.approx(abs(psnrs[0] - psnrs[1]) / 2)  # population std of 2
    assert summary["mouth_lpips"]["count"] == 2
    assert report["settings"]["lpips_net"] == "vgg" and report["settings"]["timestep_mode"] == "auto"

    markdown = (folder / "metrics.md").read_text()
    assert _table_rows(markdown)[:7] == ["Metric", "MSE (×10⁻³) ↓", "PSNR ↑", "SSIM ↑", "LPIPS (×10⁻¹) ↓",
                                         "Mouth PSNR ↑", "Mouth LPIPS (×10⁻¹) ↓"]
    mse_row = next(line for line in markdown.splitlines() if line.startswith("| MSE"))
    assert f"{summary['mse']['mean'] * 1e3:.3f} ± {summary['mse']['std'] * 1e3:.2f}" in mse_row
    assert sorted(p.name for p in (folder / "frames").iterdir()) == ["00006_00.png", "00007_00.png"]
    assert not list(folder.glob(".*.tmp"))  # atomic writes leave no temporary files
    assert "PSNR ↑" in capsys.readouterr().out


def test_eval_several_runs_writes_one_comparison(run_e, run_a, tmp_path, capsys):
    out = tmp_path / "ablation"
    assert eval_runs([run_e, run_a], out=out, max_frames=1, lpips_net="alex", progress=False, device="cpu") == 0
    markdown = (tmp_path / "ablation.md").read_text()
    body = json.loads((tmp_path / "ablation.json").read_text())
    assert [r["label"] for r in body["runs"]] == ["E · tiny", "A · tiny"]
    assert all(r["settings"]["frames_evaluated"] == 1 and r["settings"]["lpips_net"] == "alex" for r in body["runs"])
    assert "| Metric | E · tiny | A · tiny |" in markdown  # Table 1 layout: one column per run
    ablation_rows = [line for line in markdown.splitlines() if line.startswith(f"| {run_e}") or
                     line.startswith(f"| {run_a}")]
    assert len(ablation_rows) == 2 and "| E | tiny |" in ablation_rows[0]  # ablation layout: one row per run
    assert markdown.count("**") >= 2 * 6  # the best value of each metric is bold
    assert "comparison:" in capsys.readouterr().out


def test_test_frames_use_tracking_and_t0_training_frames_their_own(run_e, monkeypatch):
    calls = []
    real = evaluate_module.render_avatar

    def spy(avatar, head, params, camera, timestep, *args):
        calls.append((params, timestep))
        return real(avatar, head, params, camera, timestep, *args)

    monkeypatch.setattr(evaluate_module, "render_avatar", spy)
    run = ckpt.load_run(run_e)
    test_set, train_set = open_run_dataset(run, "test"), open_run_dataset(run, "train")
    next(render_run_frames(run, test_set, [0]))
    frame = next(render_run_frames(run, train_set, [1]))
    (test_params, test_t), (train_params, train_t) = calls
    assert test_t is None and train_t == frame.item["timestep"]
    assert torch.equal(test_params.expr, test_set[0]["params"]["expr"])  # tracked, never refined
    refined = run.info.frame_params["expr"][frame.item["row"]]
    assert torch.equal(train_params.expr[0], refined)

    next(render_run_frames(run, train_set, [1], timestep_mode="zero"))
    assert calls[-1][1] is None


def test_each_frame_poses_the_head_once(run_e, monkeypatch):
    import geoavatar.avatar.render as avatar_render

    posings = []
    real = avatar_render.posed_head

    def counting(*args, **kwargs):
        out = real(*args, **kwargs)
        posings.append(out.vertices)
        return out

    monkeypatch.setattr(avatar_render, "posed_head", counting)
    run = ckpt.load_run(run_e)
    frames = list(render_run_frames(run, open_run_dataset(run, "test"), [0, 1]))
    assert len(posings) == 2  # the mouth mask uses the vertices the render was posed with
    assert all(torch.equal(frame.vertices, posed[0]) for frame, posed in zip(frames, posings))


def test_mouth_mask_and_crop_box(run_e):
    run = ckpt.load_run(run_e)
    frame = next(render_run_frames(run, open_run_dataset(run, "test"), [0]))
    selected = mouth_face_mask(run.head)
    assert 0 < int(selected.sum()) < run.head.num_faces
    item = frame.item
    mask = mouth_mask(frame.vertices, run.head.faces, selected, item["viewmat"], item["K"], 64, 64)
    wider = mouth_mask(frame.vertices, run.head.faces, selected, item["viewmat"], item["K"], 64, 64, dilate_px=2)
    everything = mouth_mask(frame.vertices, run.head.faces, torch.ones_like(selected), item["viewmat"], item["K"],
                            64, 64)
    assert 0 < int(mask.sum()) < int(wider.sum()) and bool(wider[mask].all())
    assert int(mask.sum()) < int(everything.sum()) / 5  # the mouth is a small part of the head
    box = torch.zeros(64, 64, dtype=torch.bool)
    box[60:62, 3:9] = True
    assert crop_box(box, 32) == [32, 64, 0, 32]  # grown to 32 px about its centre, pushed inside the image
    assert crop_box(torch.zeros(8, 8, dtype=torch.bool), 4) is None


def test_bad_run_folders_fail_clearly(run_e, tmp_path):
    with pytest.raises(RunError, match="run folder not found"):
        eval_runs([tmp_path / "missing"], progress=False, device="cpu")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunError, match="not a GeoAvatar run"):
        eval_runs([tmp_path / "empty"], progress=False, device="cpu")
    broken = tmp_path / "broken" / "checkpoints"
    broken.mkdir(parents=True)
    (broken / "last.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(RunError, match="not a readable GeoAvatar checkpoint"):
        eval_runs([tmp_path / "broken"], progress=False, device="cpu")
    with pytest.raises(RunError, match="dataset folder .* not found; pass --data"):
        eval_runs([run_e], data=tmp_path / "moved", progress=False, device="cpu")
    with pytest.raises(OptionError, match="--max-frames must be positive"):
        eval_runs([run_e], max_frames=0, progress=False, device="cpu")


def test_eval_out_never_overwrites_a_run_report(run_e, tmp_path, capsys):
    report = run_e / "eval" / "test"
    assert eval_runs([run_e], max_frames=1, lpips_net="alex", progress=False, device="cpu") == 0
    before = (report / "metrics.json").read_bytes()
    with pytest.raises(OptionError, match="--out"):  # the mistake: --out taken for an output folder's file
        eval_runs([run_e], out=report / "metrics", max_frames=1, lpips_net="alex", progress=False, device="cpu")
    assert (report / "metrics.json").read_bytes() == before
    with pytest.raises(OptionError, match="is a folder"):  # the table would land beside it
        eval_runs([run_e], out=tmp_path, max_frames=1, lpips_net="alex", progress=False, device="cpu")
    table = tmp_path / "one"  # with --out, one run gets its comparison too; a second call replaces it
    for _ in range(2):
        assert eval_runs([run_e], out=table, max_frames=1, lpips_net="alex", progress=False, device="cpu") == 0
    assert "-comparison" in json.loads((tmp_path / "one.json").read_text())["format"]
    assert (tmp_path / "one.md").read_text().count("E · tiny") >= 1


def test_comparison_labels_tell_runs_of_one_preset_and_dataset_apart():
    from pathlib import Path

    from geoavatar.eval.evaluate import EvalResult
    from geoavatar.eval.report import distinct_labels

    def result(run_dir: str, label: str) -> EvalResult:
        return EvalResult(Path(run_dir), label, "E", "s0", "test", 1, "last", [], {}, {}, 0.0)

    results = [result("runs/old/E", "E · s0"), result("runs/new/E", "E · s0"), result("runs/E_long", "E · s0"),
               result("runs/A", "A · s0")]
    labels = [r.label for r in distinct_labels(results)]
    assert labels == ["E · s0 (runs/old/E)", "E · s0 (runs/new/E)", "E · s0 (E_long)", "A · s0"]
    assert len(set(labels)) == len(labels)


def test_which_folder_is_the_runs_own_dataset_and_where_a_copys_report_goes(tmp_path):
    """The recorded folder is the run's own; once it is gone any folder is (a moved dataset) but a tracked copy,
    which holds its track.json; a copy's report is named by the copy, by OUT for prepare's OUT/dataset."""
    from geoavatar.apps.eval import report_dir
    from geoavatar.train.run_frames import is_own_dataset

    recorded, moved, copy = tmp_path / "talk" / "dataset", tmp_path / "moved", tmp_path / "tracked"
    for folder in (recorded, moved, copy):
        folder.mkdir(parents=True)
    (copy / "track.json").write_text("{}")
    assert is_own_dataset(recorded, recorded) and not is_own_dataset(recorded, moved)
    assert report_dir(tmp_path / "run", "test", moved, recorded).name == "test@talk"  # not test@dataset
    recorded.rmdir()
    assert is_own_dataset(recorded, moved) and not is_own_dataset(recorded, copy)
