"""The ablation matrix of `geoavatar ablate`: which runs exist, one job (train + eval), the tables, the
mouth crops. The scheduling (Ray) lives in geoavatar/apps/ablate.py; everything here is plain
functions on folders, so a job runs the same in a Ray worker, a test or a shell.

    DIR/<dataset>/<preset>/          one RUN folder per (dataset, preset), as `geoavatar train` writes it
    DIR/<dataset>/<preset>/eval/test/metrics.json   its `geoavatar eval` (final checkpoint, test split)
    DIR/logs/<dataset>__<preset>.log what the job's train and eval printed (appended on every attempt)
    DIR/ablation.md, ablation.json   the paper's Table 3 layout per dataset and averaged over datasets
    DIR/mouth_<dataset>.png          ground truth | A | E mouth crops on the widest-open test frames

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
import io
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from geoavatar.errors import GeoAvatarError

METRICS_FILE = Path("eval") / "test" / "metrics.json"
TABLE_FILE = "ablation.md"
JSON_FILE = "ablation.json"
LOG_DIR = "logs"
# The metrics the progress lines and the averaged table are about (the paper's Table 3 + mouth PSNR).
HEADLINE = ("psnr", "ssim", "lpips", "mouth_psnr")


class RunMismatch(GeoAvatarError):
    """A run folder of the matrix holds a run with other settings than the ones asked for."""


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


def run_folder(out: Path, name: str, preset: str) -> Path:
    return out / name / preset


def metrics_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / METRICS_FILE


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


# --- one job: train + eval through the CLI -------------------------------------------------------


def _call_cli(argv: list[str], log) -> tuple[int, str]:
    """geoavatar.cli.main(argv) in this process, its output appended to `log`; (exit status, last line)."""
    from geoavatar.cli import main

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
        print(f"$ geoavatar {' '.join(argv)}", flush=True)
        try:
            code = main(argv)
        except SystemExit as exit_:  # a command's own SystemExit("message"), or tyro's usage error
            if isinstance(exit_.code, str):
                print(exit_.code)
                code = 2
            else:
                code = int(exit_.code or 0)
    text = buffer.getvalue()
    log.write(text)
    log.flush()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if code == 130:  # the trainer's "interrupted at step S: saved ...", not the run folder printed after it
        lines = [line for line in lines if line.startswith("interrupted")] or lines
    return code, (lines[-1] if lines else "")


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


def run_job(spec: JobSpec) -> dict:
    """Train (or resume) and evaluate one run; what happened as a dict (never raises for a failed run:
    status "failed" with the command's last line, so the other jobs of the matrix go on)."""
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
        steps = [("train", train_argv(spec, state == "resume"))] if state in ("new", "resume") else []
        if state != "done":
            steps.append(("eval", eval_argv(spec)))
        for what, argv in steps:
            code, last = _call_cli(argv, log)
            if code != 0:
                status = "interrupted" if code == 130 else "failed"
                return {**record, "status": status, "message": f"{what}: {last or f'exit status {code}'}",
                        "seconds": time.perf_counter() - started}
    summary = read_summary(spec.run_dir)
    return {**record, "status": "done", "psnr": summary.get("psnr", {}).get("mean"),
            "seconds": time.perf_counter() - started}


def read_summary(run_dir: str | os.PathLike) -> dict:
    """The summary of a run's test metrics.json: metric -> {mean, std, count}."""
    path = metrics_path(run_dir)
    try:
        return json.loads(path.read_text())["summary"]
    except (OSError, ValueError, KeyError) as err:
        raise RunMismatch(f"{path}: unreadable evaluation ({err}); delete it to evaluate again") from None


def mouth_share(run_dir: str | os.PathLike) -> tuple[float, float, float, int] | None:
    """How much of each test frame is mouth (eval's mouth region), from a run's metrics.json:
    (mean, min, max) share over the frames where the mouth shows, and their count; None if unreadable.
    Evaluations written before `mouth_share` existed fall back to mouth_pixels / resolution² (square frames)."""
    try:
        body = json.loads(metrics_path(run_dir).read_text())
    except (OSError, ValueError):
        return None
    side = body.get("settings", {}).get("resolution")
    shares = [f["mouth_share"] if "mouth_share" in f else f["mouth_pixels"] / side ** 2 if side else None
              for f in body.get("frames", []) if f.get("mouth_pixels")]
    shares = [v for v in shares if v is not None]
    if not shares:
        return None
    return float(np.mean(shares)), float(min(shares)), float(max(shares)), len(shares)


# --- the tables ---------------------------------------------------------------------------------


def _result(run_dir: str, preset: str, subject: str, summary: dict):
    """An EvalResult carrying only what report.ablation_table reads (run, preset, subject, summary)."""
    from geoavatar.eval.evaluate import EvalResult

    return EvalResult(run_dir=Path(run_dir), label=f"{preset} · {subject}", preset=preset, subject=subject,
                      split="test", step=0, checkpoint="", frames=[], summary=summary, settings={}, seconds=0.0)


def average_summaries(summaries: Sequence[dict]) -> dict:
    """Metric -> {mean: mean over the datasets' means, std: their spread, count: datasets with a value}."""
    out = {}
    for key in {k for s in summaries for k in s}:
        values = [s[key]["mean"] for s in summaries
                  if s.get(key, {}).get("mean") is not None and math.isfinite(s[key]["mean"])]
        out[key] = {"mean": float(np.mean(values)) if values else None,
                    "std": float(np.std(values)) if values else None, "count": len(values)}
    return out


def ablation_tables(out: Path, names: Sequence[str], presets: Sequence[str], summaries: dict[tuple[str, str], dict],
                    settings: dict) -> tuple[str, dict]:
    """(Markdown, JSON body): the presets' components, Table 3 per dataset, the average over datasets."""
    from geoavatar.config import ABLATIONS
    from geoavatar.eval.report import COLUMNS, ablation_table

    lines = [f"# Ablation: {len(presets)} presets on {len(names)} dataset{'s' if len(names) != 1 else ''}", "",
             f"Every run: {settings['steps']} steps, resolution {settings['resolution'] or 'as stored'}, seed "
             f"{settings['seed']}; test split, final checkpoint, LPIPS vgg (`geoavatar eval`). Rows as the paper's "
             "Table 3; **bold** best, <u>underlined</u> second.", "",
             "| Preset | APS | Mouth structure | Part-wise deformation | L_angle | |", "|---|:-:|:-:|:-:|:-:|---|"]
    mark = lambda on: "✓" if on else ""  # noqa: E731
    for p in presets:
        c = ABLATIONS[p]
        sets = {"aps": "✓", "gaussianavatars": ""}.get(c.face_sets, f"all {c.face_sets}")  # F-I: one set for all
        lines.append(f"| {p} | {sets} | {mark(c.mouth == 'geoavatar')} | {mark(c.mouth_deform)} | {mark(c.angle_loss)} "
                     f"| {c.description} |")
    body = {"format": "geoavatar-ablation", "version": 1, "settings": settings, "presets": list(presets),
            "datasets": {}, "average": {}}
    for name in names:
        rows = [_result(f"{name}/{p}", p, name, summaries[(name, p)])
                for p in presets if (name, p) in summaries]
        missing = [p for p in presets if (name, p) not in summaries]
        lines += ["", f"## {name}", ""]
        lines.append(ablation_table(rows).rstrip() if rows else "(no finished run yet)")
        if missing:
            lines += ["", f"Not finished: {', '.join(missing)}."]
        share = next((v for p in presets if (name, p) in summaries
                      for v in [mouth_share(run_folder(out, name, p))] if v is not None), None)
        if share is not None:
            lines += ["", f"Mouth region (the mouth metrics' pixels: visible lips and mouth structure, dilated): "
                          f"{share[0]:.1%} of a test frame on average ({share[1]:.1%}–{share[2]:.1%}, "
                          f"{share[3]} frames where it shows)."]
        body["datasets"][name] = {p: summaries[(name, p)] for p in presets if (name, p) in summaries}
    average_rows = []
    for p in presets:
        found = [summaries[(n, p)] for n in names if (n, p) in summaries]
        if found:
            mean = average_summaries(found)
            body["average"][p] = {"datasets": len(found), "summary": mean}
            average_rows.append(_result("mean", p, f"{len(found)} of {len(names)} datasets", mean))
    lines += ["", "## Average over datasets", ""]
    lines.append(ablation_table(average_rows).rstrip() if average_rows else "(no finished run yet)")
    lines += ["", "Average: the mean of the per-dataset means (every dataset weighs the same; PSNR in dB). "
              f"Columns: {', '.join(c.key for c in COLUMNS)}; per-run details in `<dataset>/<preset>/{METRICS_FILE}`.", ""]
    return "\n".join(lines), body


def write_ablation(out: Path, names: Sequence[str], presets: Sequence[str], summaries: dict[tuple[str, str], dict],
                   settings: dict) -> Path:
    """DIR/ablation.md and DIR/ablation.json (atomic); returns the Markdown's path."""
    from geoavatar.io import atomic_write_json, atomic_write_text

    markdown, body = ablation_tables(out, names, presets, summaries, settings)
    atomic_write_json(out / JSON_FILE, body)
    return atomic_write_text(out / TABLE_FILE, markdown)


# --- mouth crops of A and E ---------------------------------------------------------------------


@dataclass
class MouthFrame:
    index: int  # position in the test split
    timestep: int
    jaw: float  # |jaw_pose| (radians) of the tracked parameters: how wide the mouth opens


def widest_open_frames(dataset, count: int) -> list[MouthFrame]:
    """The `count` test frames with the largest jaw opening, ranked by the norm of the tracked jaw_pose
    (axis-angle, radians), largest first; ties by timestep."""
    frames = []
    for index, frame in enumerate(dataset.frames):
        jaw = dataset.subject.frame_params(frame.row)["jaw_pose"]  # [1, 3]
        frames.append(MouthFrame(index, int(frame.timestep), float(jaw.double().norm())))
    frames.sort(key=lambda f: (-f.jaw, f.timestep))
    return frames[:count]


def _label(image: np.ndarray, text: str, height: int = 14) -> np.ndarray:
    """A white strip with `text` above a uint8 image [H, W, 3]."""
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (image.shape[1], height), (255, 255, 255))
    ImageDraw.Draw(strip).text((3, 1), text, fill=(0, 0, 0))
    return np.concatenate([np.asarray(strip), image], axis=0)


def mouth_crops(run_a: str | os.PathLike, run_e: str | os.PathLike, count: int = 4, height: int = 128,
                device: str = "auto", backend: str = "auto") -> tuple[np.ndarray, list[MouthFrame]]:
    """uint8 image: one row per widest-open test frame, ground truth | A | E cropped around the mouth.

    Both runs render through the evaluation path (eval.evaluate.render_run_frames: tracked parameters
    and T = 0 on test frames, the dataset background). The crop box is the bounding box of both runs'
    mouth masks (mouth structure + lips faces, z-buffered, eval.evaluate.mouth_mask), grown to a
    square of at least a quarter of the image side; each crop is scaled to `height` pixels."""
    from geoavatar.apps.common import fit_height, open_run, to_uint8
    from geoavatar.eval.evaluate import crop_box, mouth_face_mask, mouth_mask, open_run_dataset, render_run_frames

    runs = {"A": open_run(run_a, device), "E": open_run(run_e, device)}
    datasets = {k: open_run_dataset(r, "test") for k, r in runs.items()}
    if datasets["A"].timesteps != datasets["E"].timesteps:
        raise RunMismatch(f"{run_a} and {run_e}: their test splits differ; they were trained on different data")
    chosen = widest_open_frames(datasets["E"], count)
    indices = [f.index for f in chosen]
    rendered = {k: list(render_run_frames(r, datasets[k], indices, backend=backend)) for k, r in runs.items()}
    rows = []
    for n, frame in enumerate(chosen):
        a, e = rendered["A"][n], rendered["E"][n]
        item = e.item
        width, height_px = int(item["width"]), int(item["height"])
        dilate = max(1, round(0.02 * max(width, height_px)))
        masks = [mouth_mask(r.vertices, runs[k].head.faces, mouth_face_mask(runs[k].head), item["viewmat"],
                             item["K"], width, height_px, dilate) for k, r in (("A", a), ("E", e))]
        mask = masks[0].to(masks[1].device) | masks[1]
        box = crop_box(mask, max(8, max(width, height_px) // 4))
        if box is None:  # the mouth is hidden (head turned away): the lower middle of the image
            box = [height_px // 2, height_px, width // 4, width - width // 4]
        y0, y1, x0, x1 = _square(box, height_px, width)
        panels = [fit_height(to_uint8(image[y0:y1, x0:x1]), height) for image in (e.target, a.pred, e.pred)]
        titles = [f"GT t={frame.timestep} jaw {frame.jaw:.2f}", "A", "E"]
        rows.append(np.concatenate([_label(p, t) for p, t in zip(panels, titles)], axis=1))
    widest = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, widest - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows, axis=0), chosen


def _square(box: list[int], height: int, width: int) -> list[int]:
    """[y0, y1, x0, x1] grown to a square about its centre (as large as the image allows), inside the image."""
    side = min(max(box[1] - box[0], box[3] - box[2]), height, width)
    out = []
    for lo, hi, limit in ((box[0], box[1], height), (box[2], box[3], width)):
        start = min(max(int(round((lo + hi) / 2.0 - side / 2.0)), 0), limit - side)
        out += [start, start + side]
    return out


def write_mouth_crops(out: Path, name: str, run_a: Path, run_e: Path, count: int, device: str = "auto",
                      backend: str = "auto") -> tuple[Path, list[MouthFrame]]:
    from geoavatar.io import atomic_write_png

    image, chosen = mouth_crops(run_a, run_e, count, device=device, backend=backend)
    return atomic_write_png(out / f"mouth_{name}.png", image), chosen


__all__ = [
    "JobSpec", "MouthFrame", "RunMismatch", "ablation_tables", "average_summaries", "eval_argv", "metrics_path",
    "mouth_crops", "read_summary", "run_folder", "run_job", "run_state", "train_argv", "widest_open_frames",
    "write_ablation", "write_mouth_crops",
]
