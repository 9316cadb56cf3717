"""One cell of `geoavatar ablate`'s matrix: the state of its run folder, and the job that trains (or resumes)
and evaluates it. The scheduling (Ray) is geoavatar/apps/ablate.py; the tables and mouth crops are
geoavatar/eval/ablation.py. Everything here is plain functions on folders, so a job runs the same in a Ray
worker, a test or a shell.

A job runs `geoavatar train` and `geoavatar eval` as function calls in its process: a command's exit status is
its return value and a failure its exception (never a line read back from what it printed); what the
commands print goes to the job's log, DIR/logs/<dataset>__<preset>.log.

State of a run (`run_state`), decided from its checkpoints and metrics.json:
    "done"    final.pt holds the requested preset/steps/resolution/seed/dataset and metrics.json is
              the evaluation of that final checkpoint (with the requested --max-frames): skipped
    "eval"    trained (final.pt matches), evaluation missing or stale: evaluate only
    "resume"  last.pt matches but the run is not finished: `geoavatar train --resume`, then evaluate
    "new"     no checkpoint: train from the start, then evaluate
A checkpoint with other settings is a RunMismatch naming the run and the differences.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO

from geoavatar.errors import GeoAvatarError, one_line
from geoavatar.eval.ablation import RunMismatch, metrics_path, read_summary

INTERRUPTED = 130  # `geoavatar train`'s exit status when Ctrl-C (or Ray's cancel) stopped it after saving


@dataclass(frozen=True)
class JobSpec:
    """One cell of the matrix: train `preset` on `data` into `run_dir`, then evaluate it. Plain values
    only (paths as absolute strings), so that it travels to a Ray worker on any node."""

    data: str  # dataset folder (absolute)
    name: str  # dataset name: the folder's name, the first level of DIR
    preset: str
    steps: int
    resolution: int | None
    seed: int
    run_dir: str  # DIR/<name>/<preset> (absolute)
    log: str  # DIR/logs/<name>__<preset>.log
    threads: int
    device: str = "auto"
    backend: str = "auto"
    max_frames: int | None = None  # eval --max-frames

    @property
    def label(self) -> str:
        return f"{self.name} {self.preset}"


# --- which runs are finished ----------------------------------------------------------------------


def _checkpoint_settings(path: Path) -> dict:
    """preset, steps, resolution, seed, data, step and model settings recorded in a checkpoint of `geoavatar train`."""
    from geoavatar.train.checkpoint import RunError, config_from_json, load_checkpoint

    payload = load_checkpoint(path)  # RunError naming the file when it is unreadable
    try:
        config = config_from_json(payload["config"], where=str(path))
        run = json.loads(payload.get("run", "{}"))
    except (KeyError, TypeError, ValueError) as err:
        raise RunMismatch(f"{path}: the checkpoint does not record its configuration ({err})") from None
    except RunError as err:
        raise RunMismatch(str(err)) from None
    return {"preset": run.get("preset"), "steps": config.steps, "resolution": run.get("resolution"),
            "seed": run.get("seed"), "data": run.get("data"), "step": int(payload.get("step", -1)),
            "model": _model_values(config)}


# The sections of a run's configuration that a preset fixes; a default changed since the run was trained (e.g. #18's
# normal shading) makes it another model than `--preset` asks for today.
MODEL_SECTIONS = ("model.", "loss.")


def _model_values(config) -> dict:
    """The MODEL_SECTIONS fields of a TrainConfig, by dotted name."""
    from geoavatar.config import config_values

    return {k: v for k, v in config_values(config).items() if k.startswith(MODEL_SECTIONS)}


def _differences(spec: JobSpec, saved: dict) -> list[str]:
    wanted = {"preset": spec.preset, "steps": spec.steps, "resolution": spec.resolution, "seed": spec.seed}
    out = [f"{key} {saved.get(key)} (asked {value})" for key, value in wanted.items() if saved.get(key) != value]
    data = saved.get("data")
    if data is None or Path(data).resolve() != Path(spec.data).resolve():
        out.append(f"dataset {data} (asked {spec.data})")
    if not out:  # same preset name: the model it stands for today
        from geoavatar.config import preset

        asked = _model_values(preset(spec.preset, spec.steps))
        out += [f"{key} {saved['model'].get(key)!r} (preset {spec.preset} today: {value!r})"
                for key, value in asked.items() if saved["model"].get(key) != value]
    return out


def _evaluated(spec: JobSpec) -> bool:
    """metrics.json exists and is the evaluation of the run's final checkpoint at the requested settings."""
    path = metrics_path(spec.run_dir)
    if not path.is_file():
        return False
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError):
        return False  # torn or foreign: evaluate again (eval rewrites it atomically)
    settings = report.get("settings") or {}
    return (report.get("step") == spec.steps and str(report.get("checkpoint", "")).endswith("final.pt")
            and report.get("split") == "test" and settings.get("max_frames") == spec.max_frames)


def run_state(spec: JobSpec) -> str:
    """"done", "eval", "resume" or "new" (see the module docstring); RunMismatch for other settings."""
    from geoavatar.train.checkpoint import run_checkpoint_path

    final, last = run_checkpoint_path(spec.run_dir, "final"), run_checkpoint_path(spec.run_dir, "last")
    path = final if final.is_file() else last if last.is_file() else None
    if path is None:
        return "new"
    saved = _checkpoint_settings(path)
    differences = _differences(spec, saved)
    if differences:
        raise RunMismatch(f"{spec.run_dir}: holds a run with {', '.join(differences)}; pass --redo to train it "
                          "again with the requested settings, or choose another --out")
    if path == final and saved["step"] == spec.steps:
        return "done" if _evaluated(spec) else "eval"
    return "resume"


# --- one job: train + eval as function calls -------------------------------------------------------


def train_argv(spec: JobSpec, resume: bool) -> list[str]:
    argv = ["train", "--data", spec.data, "--out", spec.run_dir, "--preset", spec.preset, "--steps", str(spec.steps),
            "--seed", str(spec.seed), "--device", spec.device, "--backend", spec.backend, "--no-progress"]
    if spec.resolution is not None:
        argv += ["--resolution", str(spec.resolution)]
    return argv + (["--resume"] if resume else [])


def eval_argv(spec: JobSpec) -> list[str]:
    argv = ["eval", spec.run_dir, "--split", "test", "--checkpoint", "final", "--device", spec.device,
            "--backend", spec.backend, "--no-progress"]
    return argv + (["--max-frames", str(spec.max_frames)] if spec.max_frames is not None else [])


def _command(name: str) -> Callable:
    """The function behind `geoavatar <name>` for the two commands a job runs (imported when first needed)."""
    if name == "train":
        from geoavatar.apps.train import train

        return train
    if name == "eval":
        from geoavatar.apps.eval import eval_runs

        return eval_runs
    raise ValueError(f"an ablation job runs train and eval, not {name!r}")


@dataclass(frozen=True)
class CommandResult:
    """How one command of a job ended."""

    code: int  # its exit status: 0 finished, INTERRUPTED (saved, resumable), 2 refused (a GeoAvatarError)
    message: str = ""  # one line when it did not finish: "geoavatar <command>: <why>"


def run_command(argv: list[str], log: TextIO) -> CommandResult:
    """`geoavatar <argv>` as a function call in this process, what it prints appended to `log` (with the words
    first, as `$ geoavatar ...`). The exit status is the command's return value; a GeoAvatarError is its message."""
    from geoavatar.apps import call_command

    prog = f"geoavatar {argv[0]}"
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        print(f"$ geoavatar {' '.join(argv)}", flush=True)
        try:
            code = int(call_command(_command(argv[0]), argv[1:], prog) or 0)
        except GeoAvatarError as err:
            code, message = 2, f"{prog}: {one_line(str(err))}"
        except SystemExit as exit_:  # tyro's usage error: its message is in the log
            code = exit_.code if isinstance(exit_.code, int) else 2
            message = f"{prog}: invalid arguments (exit status {code}, see the log)"
        else:
            message = "" if code == 0 else f"{prog}: interrupted; its checkpoint is saved" if code == INTERRUPTED \
                else f"{prog}: exit status {code}"
        if message:
            print(message, flush=True)
    return CommandResult(code, message)


def job_commands(spec: JobSpec, state: str) -> list[list[str]]:
    """The commands a run in `state` still needs: train (new) or resume, then eval; none when done."""
    commands = [train_argv(spec, state == "resume")] if state in ("new", "resume") else []
    return commands + ([eval_argv(spec)] if state != "done" else [])


def run_job(spec: JobSpec) -> dict:
    """Train (or resume) and evaluate one run; what happened as a dict (never raises for a failed run:
    status "failed" with the command's message, so the other jobs of the matrix go on)."""
    import torch

    from geoavatar.runtime import setup_process

    started = time.perf_counter()
    setup_process()
    torch.set_num_threads(spec.threads)  # the job's share of the node (a reused worker may have had another)
    record = {"dataset": spec.name, "preset": spec.preset, "run": spec.run_dir, "log": spec.log,
              "host": os.uname().nodename, "threads": spec.threads}
    Path(spec.log).parent.mkdir(parents=True, exist_ok=True)
    with open(spec.log, "a", encoding="utf-8") as log:
        log.write(f"--- {time.strftime('%Y-%m-%d %H:%M:%S')} on {record['host']}, {spec.threads} threads\n")
        try:
            state = run_state(spec)
        except GeoAvatarError as err:
            return {**record, "status": "failed", "message": str(err), "seconds": time.perf_counter() - started}
        record["state"] = state
        for argv in job_commands(spec, state):
            result = run_command(argv, log)
            if result.code != 0:
                status = "interrupted" if result.code == INTERRUPTED else "failed"
                return {**record, "status": status, "message": f"{argv[0]}: {result.message}",
                        "seconds": time.perf_counter() - started}
    summary = read_summary(spec.run_dir)
    return {**record, "status": "done", "psnr": summary.get("psnr", {}).get("mean"),
            "seconds": time.perf_counter() - started}


__all__ = ["CommandResult", "INTERRUPTED", "JobSpec", "eval_argv", "job_commands", "run_command", "run_job",
           "run_state", "train_argv"]
