"""`geoavatar ablate` on a local Ray instance: a tiny matrix (one 48 px subject of 8 frames x presets A
and E, 6 training steps, 1 thread per job so that the two jobs run side by side on 2 cores), the table
and the mouth crops, a second call that skips the finished runs, the run states, and the one-line errors."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from apps_fixtures import make_subject

from geoavatar.apps.ablate import ablate
from geoavatar.apps.ablation_job import JobSpec, eval_argv, run_job, run_state, train_argv
from geoavatar.cli import main
from geoavatar.eval.ablation import RunMismatch, metrics_path

STEPS = 6


@pytest.fixture(scope="module")
def subject(tmp_path_factory) -> Path:
    return make_subject(tmp_path_factory.mktemp("ablate-data") / "tiny", frames=8)


@pytest.fixture(scope="module")
def matrix(subject, tmp_path_factory):
    """DIR after one `geoavatar ablate` call, its exit status and what it printed (module fixtures cannot
    use capsys)."""
    out = tmp_path_factory.mktemp("ablate") / "out"
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = ablate(data=[subject], out=out, presets=["A", "E"], steps=STEPS, resolution=48, threads=1,
                      max_frames=2, mouth_frames=2, device="cpu")
    return out, code, buffer.getvalue()


def _run_files(out: Path) -> dict[Path, int]:
    files = [p for p in out.rglob("*") if p.is_file() and ("checkpoints" in p.parts or p.name == "metrics.json")]
    return {p: p.stat().st_mtime_ns for p in files}


def test_matrix_writes_runs_table_and_mouth_crops(matrix):
    out, code, printed = matrix
    assert code == 0, printed
    # one line per finished job, with its PSNR and wall time, then the table's path
    job_lines = [line for line in printed.splitlines() if line.startswith("[")]
    assert len(job_lines) == 2 and all("PSNR" in line and "dB" in line for line in job_lines), printed
    assert {line.split()[2].rstrip(":") for line in job_lines} == {"A", "E"}
    assert f"table: {out / 'ablation.md'}" in printed
    for preset in ("A", "E"):
        run = out / "tiny" / preset
        assert (run / "checkpoints" / "final.pt").is_file()
        report = json.loads(metrics_path(run).read_text())
        assert report["step"] == STEPS and report["preset"] == preset and report["settings"]["frames_evaluated"] == 2
        assert (out / "logs" / f"tiny__{preset}.log").read_text().count("$ geoavatar") == 2  # train, eval
    table = (out / "ablation.md").read_text()
    assert "## tiny" in table and "## Average over datasets" in table
    rows = [line for line in table.splitlines() if line.startswith("| tiny/") or line.startswith("| mean |")]
    assert [r.split("|")[2].strip() for r in rows] == ["A", "E", "A", "E"]
    # how much of a test frame the mouth metrics cover, from the evaluated frames
    frames = json.loads(metrics_path(out / "tiny" / "A").read_text())["frames"]
    shown = [f["mouth_share"] for f in frames if f["mouth_pixels"]]
    assert shown and all(0.0 < v < 0.5 for v in shown)
    assert "Mouth region" in table and f"{np.mean(shown):.1%} of a test frame" in table
    body = json.loads((out / "ablation.json").read_text())
    psnr_a = json.loads(metrics_path(out / "tiny" / "A").read_text())["summary"]["psnr"]["mean"]
    assert body["datasets"]["tiny"]["A"]["psnr"]["mean"] == pytest.approx(psnr_a)
    assert body["average"]["E"]["datasets"] == 1
    crops = np.asarray(Image.open(out / "mouth_tiny.png"))
    assert crops.ndim == 3 and crops.shape[1] % 3 == 0  # ground truth | A | E
    assert crops.shape[0] > 2 * 128  # two frames of 128 px crops (+ their labels)
    left, middle = crops[:, : crops.shape[1] // 3], crops[:, crops.shape[1] // 3: 2 * crops.shape[1] // 3]
    assert not np.array_equal(left, middle)  # the ground truth is not the render


def test_second_call_skips_finished_runs(matrix, subject, capsys):
    out, code, _ = matrix
    before = _run_files(out)
    assert len(before) == 6  # last.pt, final.pt, metrics.json of each run
    assert ablate(data=[subject], out=out, presets=["A", "E"], steps=STEPS, resolution=48, threads=1, max_frames=2,
                  mouth_frames=2, device="cpu") == 0
    printed = capsys.readouterr().out
    assert "2 finished, 0 to run" in printed and printed.count("finished earlier, skipped") == 2
    assert "ray:" not in printed  # nothing to run: Ray is not even started
    assert _run_files(out) == before


def test_run_states_and_mismatch(matrix, subject, tmp_path):
    out, _, _ = matrix
    spec = JobSpec(data=str(subject), name="tiny", preset="E", steps=STEPS, resolution=48, seed=0,
                   run_dir=str(out / "tiny" / "E"), log=str(tmp_path / "log"), threads=1, max_frames=2)
    assert run_state(spec) == "done"
    assert run_state(replace(spec, max_frames=None)) == "eval"  # evaluated on fewer frames than now asked
    assert run_state(replace(spec, run_dir=str(tmp_path / "new"))) == "new"
    copy = tmp_path / "E"
    shutil.copytree(spec.run_dir, copy)
    (copy / "checkpoints" / "final.pt").unlink()
    assert run_state(replace(spec, run_dir=str(copy))) == "resume"
    assert "--resume" in train_argv(replace(spec, run_dir=str(copy)), resume=True)
    assert eval_argv(spec)[-2:] == ["--max-frames", "2"]
    with pytest.raises(RunMismatch, match=r"steps 6 \(asked 7\).*--redo"):
        run_state(replace(spec, steps=7))
    with pytest.raises(RunMismatch, match=r"preset A \(asked E\)"):
        run_state(replace(spec, run_dir=str(out / "tiny" / "A")))


@pytest.mark.parametrize("words, message", [
    (["--presets", "A", "Z"], "--presets Z: unknown preset"),
    (["--presets", "A", "A"], "--presets: A given twice"),
    (["--steps", "0"], "--steps must be positive"),
    (["--steps", str(STEPS + 1), "--resolution", "48"], "holds a run with steps"),
])
def test_bad_options_are_one_line_errors(matrix, subject, words, message, capsys):
    out, _, _ = matrix
    before = _run_files(out)
    assert main(["ablate", "--data", str(subject), "--out", str(out), *words]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err and err.startswith("geoavatar ablate: ")
    assert _run_files(out) == before  # nothing was touched


def test_missing_dataset_is_a_one_line_error(tmp_path, capsys):
    missing = tmp_path / "no-such-dataset"
    assert main(["ablate", "--data", str(missing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"geoavatar ablate: --data {missing}: dataset folder not found"
    assert not (tmp_path / "out").exists()


def test_a_failing_job_reports_one_line_and_does_not_raise(subject, tmp_path):
    """run_job in this process (as a Ray worker runs it): a command's error comes back as the record's message."""
    import torch

    threads = torch.get_num_threads()
    spec = JobSpec(data=str(subject), name="tiny", preset="E", steps=2, resolution=48, seed=0,
                   run_dir=str(tmp_path / "tiny" / "E"), log=str(tmp_path / "logs" / "tiny__E.log"), threads=1,
                   device="cpu", backend="gsplat")  # gsplat needs CUDA tensors: the trainer refuses on the CPU
    try:
        record = run_job(spec)
    finally:
        torch.set_num_threads(threads)
    assert record["status"] == "failed" and record["state"] == "new"
    assert record["message"].startswith("train: geoavatar train: ") and "gsplat" in record["message"]
    assert "\n" not in record["message"]
    log = Path(spec.log).read_text()
    assert "$ geoavatar train --data" in log and "gsplat" in log


def test_a_job_reads_each_command_s_exit_status_from_its_return_value(monkeypatch, tmp_path):
    """run_command calls the command function: its return value is the status (130: interrupted, saved), a
    GeoAvatarError its one-line message; nothing is read back from what the command printed."""
    from geoavatar.apps import ablation_job
    from geoavatar.errors import OptionError

    def interrupted(args):
        print("a line that is not the status")
        return 130

    def refused(args):
        raise OptionError("--steps must be\npositive")

    for command in (interrupted, refused):
        command.parse_argv = lambda argv, prog: argv
    log = (tmp_path / "log").open("w+", encoding="utf-8")
    monkeypatch.setattr(ablation_job, "_command", lambda name: interrupted)
    result = ablation_job.run_command(["train", "--steps", "5"], log)
    assert result == ablation_job.CommandResult(130, "geoavatar train: interrupted; its checkpoint is saved")
    monkeypatch.setattr(ablation_job, "_command", lambda name: refused)
    result = ablation_job.run_command(["eval", "RUN"], log)
    assert result == ablation_job.CommandResult(2, "geoavatar eval: --steps must be positive")
    log.seek(0)
    assert log.read().splitlines() == ["$ geoavatar train --steps 5", "a line that is not the status",
                                       "geoavatar train: interrupted; its checkpoint is saved", "$ geoavatar eval RUN",
                                       "geoavatar eval: --steps must be positive"]
