"""The results of `geoavatar ablate`'s matrix: the tables and the mouth crops, plain functions on folders.
Which runs exist and one job (train + eval) are in geoavatar/apps/ablation_job.py, the scheduling (Ray) in
geoavatar/apps/ablate.py.

    DIR/<dataset>/<preset>/          one RUN folder per (dataset, preset), as `geoavatar train` writes it
    DIR/<dataset>/<preset>/eval/test/metrics.json   its `geoavatar eval` (final checkpoint, test split)
    DIR/logs/<dataset>__<preset>.log what the job's train and eval printed (appended on every attempt)
    DIR/ablation.md, ablation.json   the paper's Table 3 layout per dataset and averaged over datasets
    DIR/mouth_<dataset>.png          ground truth | A | E mouth crops on the widest-open test frames
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from geoavatar.errors import GeoAvatarError

METRICS_FILE = Path("eval") / "test" / "metrics.json"
TABLE_FILE = "ablation.md"
JSON_FILE = "ablation.json"
LOG_DIR = "logs"


class RunMismatch(GeoAvatarError):
    """A run folder of the matrix holds a run with other settings than the ones asked for."""


def run_folder(out: Path, name: str, preset: str) -> Path:
    return out / name / preset


def metrics_path(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / METRICS_FILE


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
    from geoavatar.eval.evaluate import crop_box, mouth_face_mask, mouth_mask, open_run_dataset, render_run_frames
    from geoavatar.imaging import fit_height, to_uint8
    from geoavatar.render.mesh import dilation_pixels
    from geoavatar.train.checkpoint import open_run

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
        dilate = dilation_pixels(0.02, width, height_px)
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
    "JSON_FILE", "LOG_DIR", "METRICS_FILE", "MouthFrame", "RunMismatch", "TABLE_FILE", "ablation_tables",
    "average_summaries", "metrics_path", "mouth_crops", "mouth_share", "read_summary", "run_folder",
    "widest_open_frames", "write_ablation", "write_mouth_crops",
]
