"""`geoavatar ablate`: train and evaluate a matrix of datasets x ablation presets on Ray, then write the
paper's ablation table (Table 3) per dataset and averaged, and mouth crops of A and E.

One code path for a laptop and a cluster: every (dataset, preset) cell is a Ray task asking for
`--threads` CPUs (default: every core of this machine, so a local instance runs one job at a time and
a cluster of bigger nodes runs several). Without --address a local Ray instance is started (and shut
down at the end); `--address auto` joins the cluster this machine belongs to, `--address ray://HOST:10001`
one reached through Ray Client. On a cluster every node needs GeoAvatar installed and the datasets and
DIR at the same paths (a shared file system).

A task trains through `geoavatar train` and evaluates through `geoavatar eval`, called as functions in
its worker process (geoavatar.apps.ablation_job.run_job); the run folders are ordinary RUN folders.
Finished runs are skipped, interrupted ones resumed, so the command can be repeated until the matrix is
complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Literal, Optional

from geoavatar.config import ABLATIONS, PAPER_STEPS
from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.apps.ablation_job import JobSpec, run_job, run_state
from geoavatar.eval.ablation import LOG_DIR, RunMismatch, read_summary, run_folder, write_ablation, write_mouth_crops

DEFAULT_PRESETS = ("A", "B", "C", "D", "E")


def local_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}h{rest // 60:02d}m{rest % 60:02d}s" if hours else f"{rest // 60}m{rest % 60:02d}s"


def ablate(
    data: list[Path],
    out: Path,
    presets: list[str] = list(DEFAULT_PRESETS),
    steps: Optional[int] = None,
    resolution: Optional[int] = None,
    seed: int = 0,
    address: Optional[str] = None,
    threads: Optional[int] = None,
    gpus_per_job: Optional[float] = None,
    max_frames: Optional[int] = None,
    mouth_frames: int = 4,
    redo: bool = False,
    device: str = "auto",
    backend: Literal["auto", "cpu", "torch", "gsplat"] = "auto",
) -> int:
    """Train and evaluate every preset on every dataset (on Ray) and write the ablation table.

    Writes DIR/<dataset>/<preset>/ (a `geoavatar train` run with its `geoavatar eval` in
    eval/test/metrics.json), DIR/logs/<dataset>__<preset>.log (what each job printed), DIR/ablation.md
    and ablation.json (the paper's Table 3 layout per dataset and averaged over the datasets: PSNR, SSIM,
    LPIPS, mouth PSNR, ...) and, when A and E are both in the matrix, DIR/mouth_<dataset>.png: ground
    truth | A | E cropped around the mouth on the test frames with the widest jaw opening (the norm of
    the tracked jaw_pose). Prints one line per finished job. Finished runs are skipped and interrupted
    ones resumed, so running the same command again completes the matrix; a run folder trained with
    other settings is an error unless --redo.

    Args:
        data: Dataset folders (e.g. from `geoavatar synth` or `geoavatar prepare`); the folder names name
            the datasets in DIR and must differ.
        out: Output folder DIR (created; an earlier `geoavatar ablate` DIR is continued).
        presets: Ablation presets to train (A B C D E: the paper's Table 3; F G H I and E-no-mouth,
            E-no-deform also exist).
        steps: Training steps of every run (default: the paper's 200000); milestones scale with it.
        resolution: Train and evaluate at this longer image side in pixels (default: as stored).
        seed: Seed of every run.
        address: Ray cluster to run on: auto (the cluster this machine is part of), HOST:PORT, or
            ray://HOST:10001 (Ray Client); default: start a local Ray instance for this command.
        threads: CPU threads of each job, the CPUs its Ray task reserves (default: every core of this machine).
        gpus_per_job: GPUs each job reserves (default: 1 when this machine has CUDA and --device is not cpu,
            else 0); jobs with 0 all see every GPU.
        max_frames: Evaluate only this many test frames per run, spread evenly (default: all).
        mouth_frames: Rows of the mouth crops: the test frames with the widest jaw opening.
        redo: Delete and train again the run folders whose checkpoints hold other settings than asked.
        device: Device of every job: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.
        backend: Rasterizer: auto (gsplat on CUDA, the native cpu kernel on CPU when it builds, else torch), cpu, torch or gsplat.
    """
    started = time.perf_counter()
    names = _check_options(data, presets, steps, resolution, threads, gpus_per_job, max_frames, mouth_frames)
    steps = steps if steps is not None else PAPER_STEPS
    out = Path(out).resolve()
    if out.exists() and not out.is_dir():
        raise OptionError(f"--out {out}: exists and is not a folder")
    threads = threads if threads is not None else local_cores()
    specs = [JobSpec(data=str(Path(d).resolve()), name=name, preset=p, steps=steps, resolution=resolution, seed=seed,
                     run_dir=str(run_folder(out, name, p)), log=str(out / LOG_DIR / f"{name}__{p}.log"),
                     threads=threads, device=device, backend=backend, max_frames=max_frames)
             for d, name in zip(data, names) for p in presets]
    states = _plan(specs, redo)
    pending = [s for s in specs if states[s] != "done"]
    _print_plan(specs, states, len(names), len(presets), out)
    failed: list[dict] = []
    interrupted = False
    if pending:
        if gpus_per_job is None:  # a GPU each when jobs will run on CUDA here
            import torch

            gpus_per_job = 1.0 if device != "cpu" and torch.cuda.is_available() else 0.0
        failed, interrupted = _run_on_ray(pending, states, address, threads, gpus_per_job, len(specs) - len(pending),
                                          len(specs))
    summaries = {(spec.name, spec.preset): read_summary(spec.run_dir) for spec in specs if run_state(spec) == "done"}
    settings = {"steps": steps, "resolution": resolution, "seed": seed, "max_frames": max_frames,
                "datasets": {name: str(Path(d).resolve()) for d, name in zip(data, names)}}
    table = write_ablation(out, names, presets, summaries, settings)
    if "A" in presets and "E" in presets:
        _write_mouth_crops(out, names, summaries, mouth_frames, device, backend)
    print(f"table: {table} ({len(summaries)} of {len(specs)} runs, {_duration(time.perf_counter() - started)})",
          flush=True)
    return _exit_status(failed, interrupted)


def _print_plan(specs: list[JobSpec], states: dict[JobSpec, str], datasets: int, presets: int, out: Path) -> None:
    """One line for the matrix (how many runs, finished, to run), then one per run finished earlier."""
    total, pending = len(specs), sum(1 for s in specs if states[s] != "done")
    counts = {state: sum(1 for s in specs if states[s] == state) for state in ("resume", "eval")}
    print(f"ablate: {datasets} dataset(s) x {presets} preset(s) = {total} runs, {specs[0].steps} steps each; "
          f"{total - pending} finished, {pending} to run ({counts['resume']} to resume, {counts['eval']} "
          f"to evaluate only) -> {out}", flush=True)
    for n, spec in enumerate(s for s in specs if states[s] == "done"):
        print(f"[{n + 1}/{total}] {spec.label}: finished earlier, skipped "
              f"(PSNR {_psnr(read_summary(spec.run_dir))})", flush=True)


def _write_mouth_crops(out: Path, names: list[str], summaries: dict, mouth_frames: int, device: str,
                       backend: str) -> None:
    """DIR/mouth_<dataset>.png for every dataset whose A and E runs are finished."""
    for name in names:
        if (name, "A") in summaries and (name, "E") in summaries:
            path, chosen = write_mouth_crops(out, name, run_folder(out, name, "A"), run_folder(out, name, "E"),
                                             mouth_frames, device=device, backend=backend)
            frames = ", ".join(f"t={f.timestep} ({f.jaw:.2f} rad)" for f in chosen)
            print(f"mouth crops: {path} (widest jaw opening: {frames})", flush=True)


def _exit_status(failed: list[dict], interrupted: bool) -> int:
    """130 when interrupted (run again to continue), 1 when a job failed (each named on stderr), else 0."""
    if interrupted:
        print("ablate: interrupted; run the same command again to continue", file=sys.stderr)
        return 130
    for record in failed:
        print(f"ablate: {record['dataset']} {record['preset']} failed: {record['message']} (log: {record['log']})",
              file=sys.stderr)
    return 1 if failed else 0


def _psnr(summary: dict) -> str:
    value = summary.get("psnr", {}).get("mean")
    return f"{value:.2f} dB" if value is not None else "–"


def _check_options(data, presets, steps, resolution, threads, gpus_per_job, max_frames, mouth_frames) -> list[str]:
    """One-line errors naming the option, before anything starts; returns the dataset names."""
    if not presets:
        raise OptionError("--presets: give at least one preset")
    for p in presets:
        if p not in ABLATIONS:
            raise OptionError(f"--presets {p}: unknown preset; choose from {', '.join(ABLATIONS)}")
    duplicates = sorted({p for p in presets if presets.count(p) > 1})
    if duplicates:
        raise OptionError(f"--presets: {', '.join(duplicates)} given twice")
    for name, value in (("--steps", steps), ("--resolution", resolution), ("--threads", threads),
                        ("--max-frames", max_frames), ("--mouth-frames", mouth_frames)):
        if value is not None and not value > 0:
            raise OptionError(f"{name} must be positive, got {value}")
    if gpus_per_job is not None and not gpus_per_job >= 0:
        raise OptionError(f"--gpus-per-job must be >= 0, got {gpus_per_job}")
    if not data:
        raise OptionError("--data: give at least one dataset folder")
    from geoavatar.data.dataset import open_subject

    names = []
    for folder in data:
        if not Path(folder).is_dir():
            raise OptionError(f"--data {folder}: dataset folder not found")
        open_subject(folder)  # DatasetError (one line, naming the file) when it is not a dataset
        names.append(Path(folder).resolve().name)
    for name in names:
        if names.count(name) > 1:
            same = [str(d) for d, n in zip(data, names) if n == name]
            raise OptionError(f"--data: {' and '.join(same)} have the same folder name '{name}', which names "
                              "their runs in --out; rename or link one")
    return names


def _plan(specs: list[JobSpec], redo: bool) -> dict[JobSpec, str]:
    """The state of every run; runs with other settings are an error (all named), or removed with --redo."""
    states, mismatched = {}, []
    for spec in specs:
        try:
            states[spec] = run_state(spec)
        except RunMismatch as err:
            if not redo:
                mismatched.append(str(err))
                continue
            shutil.rmtree(spec.run_dir)
            Path(spec.log).unlink(missing_ok=True)
            print(f"--redo: removed {spec.run_dir} ({err})", flush=True)
            states[spec] = "new"
    if mismatched:
        more = f" (and {len(mismatched) - 1} more run(s) like it)" if len(mismatched) > 1 else ""
        raise RunMismatch(mismatched[0] + more)
    return states


def _start_ray(address: str | None, threads: int):
    """ray, started locally (num_cpus = this machine's cores) or connected to --address; True when this
    command owns the instance (and shuts it down)."""
    try:
        import ray
    except ImportError:
        raise GeoAvatarError("geoavatar ablate runs its jobs on Ray, which is not installed: "
                             "pip install 'ray[client]==2.60.0' (`make install` does)") from None
    if ray.is_initialized():  # a caller's instance (e.g. a notebook): use it as it is
        return ray, False
    quiet = {"log_to_driver": False, "logging_level": logging.WARNING}
    if address is None:
        cores = local_cores()
        if threads > cores:
            raise OptionError(f"--threads {threads}: the local Ray instance has {cores} CPU cores; use at most "
                              f"{cores}, or --address to run on a cluster")
        ray.init(num_cpus=cores, include_dashboard=False, **quiet)
    else:
        try:
            ray.init(address=address, **quiet)
        except (ConnectionError, ValueError, RuntimeError) as err:
            raise OptionError(f"--address {address}: cannot connect to Ray ({' '.join(str(err).split())})") from None
    return ray, True


def _run_on_ray(pending: list[JobSpec], states: dict, address: str | None, threads: int, gpus: float,
                done_before: int, total: int) -> tuple[list[dict], bool]:
    """Submit every pending job as a Ray task and print a line as each ends; (failed jobs, interrupted)."""
    ray, owned = _start_ray(address, threads)
    failed: list[dict] = []
    interrupted = False
    previous = None
    if threading.current_thread() is threading.main_thread():  # `kill PID` stops the jobs like Ctrl-C does
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        largest = max((n.get("Resources", {}).get("CPU", 0) for n in nodes), default=0)
        if threads > largest:
            raise OptionError(f"--threads {threads}: no Ray node has that many CPUs (the largest has {largest:g})")
        if gpus > 0 and not any(n.get("Resources", {}).get("GPU", 0) >= gpus for n in nodes):
            raise OptionError(f"--gpus-per-job {gpus:g}: no Ray node has that many GPUs (pass --gpus-per-job 0)")
        task = ray.remote(run_job).options(num_cpus=threads, num_gpus=gpus, max_retries=0)
        refs = {task.remote(spec): spec for spec in pending}
        print(f"ray: {len(refs)} job(s) submitted, {threads} CPU(s){f' and {gpus:g} GPU(s)' if gpus else ''} each, "
              f"on {len(nodes)} node(s) with {sum(n.get('Resources', {}).get('CPU', 0) for n in nodes):g} CPUs",
              flush=True)
        finished = done_before
        remaining = list(refs)
        try:
            while remaining:
                ready, remaining = ray.wait(remaining, num_returns=1)
                spec = refs[ready[0]]
                finished += 1
                try:
                    record = ray.get(ready[0])
                except ray.exceptions.RayError as err:  # the worker died (memory, node lost, ...)
                    lines = [line for line in str(err).splitlines() if line.strip()]
                    record = {"dataset": spec.name, "preset": spec.preset, "status": "failed", "log": spec.log,
                              "message": f"Ray: {lines[-1] if lines else type(err).__name__}", "seconds": 0.0}
                print(_job_line(record, states[spec], finished, total), flush=True)
                if record["status"] == "interrupted":
                    interrupted = True
                elif record["status"] != "done":
                    failed.append(record)
        except KeyboardInterrupt:
            interrupted = True
            print(f"ablate: interrupted; stopping {len(remaining)} job(s) (each saves its checkpoint)", file=sys.stderr,
                  flush=True)
            for ref in remaining:
                ray.cancel(ref)  # a running task gets a KeyboardInterrupt: the trainer saves last.pt and stops
            stopped, _ = ray.wait(remaining, num_returns=len(remaining), timeout=120)
            for ref in stopped:
                try:
                    record = ray.get(ref)
                except ray.exceptions.RayError:  # cancelled before it started
                    continue
                finished += 1
                print(_job_line(record, states[refs[ref]], finished, total), flush=True)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if owned:
            ray.shutdown()
    return failed, interrupted


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def _job_line(record: dict, state: str, finished: int, total: int) -> str:
    what = {"new": "trained + evaluated", "resume": "resumed + evaluated", "eval": "evaluated"}.get(state, state)
    head = f"[{finished}/{total}] {record['dataset']} {record['preset']}"
    if record["status"] == "done":
        psnr = record.get("psnr")
        return (f"{head}: PSNR {psnr:.2f} dB, {_duration(record['seconds'])} ({what}"
                f"{', ' + record['host'] if record.get('host') else ''})") if psnr is not None else \
            f"{head}: done, {_duration(record['seconds'])} ({what})"
    return f"{head}: {record['status'].upper()} after {_duration(record['seconds'])}: {record['message']}"


__all__ = ["ablate", "DEFAULT_PRESETS", "local_cores"]
