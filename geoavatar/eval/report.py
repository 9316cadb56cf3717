"""Evaluation reports: one run's metrics.json + metrics.md, and one comparison table over runs.

Markdown follows the paper. Table 1 layout (`metric_table`): one row per metric, one column per run,
"mean ± std" with the paper's scaling (MSE x 10^-3, LPIPS x 10^-1, 3 decimals for the mean and 2 for
the std). Ablation layout (`ablation_table`, Tables 3 / 6): one row per run, one column per metric.
In comparisons the best value of each metric is bold and the second underlined, as in the paper.

Files (all written atomically through geoavatar.io: the umask's mode, DiskFullError on a full disk):

    RUN/eval/<split>/metrics.json    per-frame metrics, summary (mean, std, count), settings, run info
    RUN/eval/<split>/metrics.md      the Table 1 column of this run
    RUN/eval/<split>/frames/*.png    with --save-images: gt | pred | |error| x 4 | mouth mask per frame
    OUT.md / OUT.json                with several runs or --out: the comparison (both layouts) and every summary
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from geoavatar.errors import OptionError
from geoavatar.eval.evaluate import TRAINED_VIEW_TOLERANCE, EvalResult, frame_dicts
from geoavatar.imaging import to_uint8
from geoavatar.io.atomic import atomic_write_json, atomic_write_png, atomic_write_text

REPORT_FORMAT = "geoavatar-eval"
REPORT_VERSION = 1


@dataclass(frozen=True)
class MetricColumn:
    key: str
    title: str
    scale: float
    higher_is_better: bool


COLUMNS: tuple[MetricColumn, ...] = (
    MetricColumn("mse", "MSE (×10⁻³) ↓", 1e3, False),
    MetricColumn("psnr", "PSNR ↑", 1.0, True),
    MetricColumn("ssim", "SSIM ↑", 1.0, True),
    MetricColumn("lpips", "LPIPS (×10⁻¹) ↓", 1e1, False),
    MetricColumn("mouth_psnr", "Mouth PSNR ↑", 1.0, True),
    MetricColumn("mouth_lpips", "Mouth LPIPS (×10⁻¹) ↓", 1e1, False),
    MetricColumn("id_similarity", "ID similarity (dlib) ↑", 1.0, True),
    MetricColumn("expression_similarity", "Expression similarity ↑", 1.0, True),
)


def eval_dir(run_dir: str | Path, split: str) -> Path:
    return Path(run_dir) / "eval" / split


def _fmt(stats: dict, column: MetricColumn, with_std: bool = True) -> str:
    mean, std = stats.get("mean"), stats.get("std")
    if mean is None or not math.isfinite(mean):
        return "–"
    text = f"{mean * column.scale:.3f}"
    if with_std and std is not None and math.isfinite(std):
        text += f" ± {std * column.scale:.2f}"
    return text


def _ranks(results: Sequence[EvalResult], column: MetricColumn) -> dict[int, int]:
    """Position -> rank (0 best, 1 second) of the runs with a value, on the rounded printed mean."""
    values = [(i, round(r.summary[column.key]["mean"] * column.scale, 3)) for i, r in enumerate(results)
              if r.summary.get(column.key, {}).get("mean") is not None]
    distinct = sorted({v for _, v in values}, reverse=column.higher_is_better)
    return {i: distinct.index(v) for i, v in values if distinct.index(v) < 2}


def _mark(text: str, rank: int | None) -> str:
    if rank == 0:
        return f"**{text}**"
    if rank == 1:
        return f"<u>{text}</u>"
    return text


def _escape(text: str) -> str:
    return text.replace("|", "\\|")


def metric_table(results: Sequence[EvalResult], mark_best: bool | None = None) -> str:
    """Table 1 layout: rows = metrics, columns = runs, 'mean ± std'."""
    mark_best = len(results) > 1 if mark_best is None else mark_best
    lines = ["| Metric | " + " | ".join(_escape(r.label) for r in results) + " |",
             "|---|" + "---:|" * len(results)]
    for column in COLUMNS:
        ranks = _ranks(results, column) if mark_best else {}
        cells = [_mark(_fmt(r.summary.get(column.key, {}), column), ranks.get(i)) for i, r in enumerate(results)]
        lines.append(f"| {column.title} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def ablation_table(results: Sequence[EvalResult], with_std: bool = False) -> str:
    """Tables 3 / 6 layout: rows = runs (preset, subject), columns = metrics (means; best bold)."""
    lines = ["| Run | Preset | Subject | " + " | ".join(c.title for c in COLUMNS) + " |",
             "|---|---|---|" + "---:|" * len(COLUMNS)]
    ranks = {c.key: _ranks(results, c) for c in COLUMNS}
    for i, r in enumerate(results):
        cells = [_mark(_fmt(r.summary.get(c.key, {}), c, with_std), ranks[c.key].get(i)) for c in COLUMNS]
        lines.append(f"| {_escape(str(r.run_dir))} | {_escape(r.preset or '–')} | {_escape(r.subject)} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def view_table(results: Sequence[EvalResult]) -> str:
    """Novel views: one row per view (in the dataset's order), per run PSNR / SSIM / LPIPS (x10^-1) and
    the share of opacity outside the head silhouette (%, the ground truth's share in brackets)."""
    views = list(dict.fromkeys(v for r in results for v in r.by_view))
    if not views:
        return ""
    head = ["| View |"] + [f" {_escape(r.label)} PSNR ↑ | SSIM ↑ | LPIPS (×10⁻¹) ↓ | outside % (gt) |" for r in results]
    lines = ["".join(head), "|---|" + "---:|---:|---:|---:|" * len(results)]
    for view in views:
        cells = []
        for r in results:
            stats = r.by_view.get(view)
            if stats is None:
                cells += ["–"] * 4
                continue
            mean = {k: stats.get(k, {}).get("mean") for k in ("psnr", "ssim", "lpips", "outside", "gt_outside")}
            cells += [f"{mean['psnr']:.2f}" if mean["psnr"] is not None else "–",
                      f"{mean['ssim']:.3f}" if mean["ssim"] is not None else "–",
                      f"{mean['lpips'] * 10:.3f}" if mean["lpips"] is not None else "–",
                      (f"{mean['outside'] * 100:.1f} ({mean['gt_outside'] * 100:.1f})"
                       if mean["outside"] is not None and mean["gt_outside"] is not None else "–")]
        lines.append(f"| {_escape(view)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def view_range_table(results: Sequence[EvalResult]) -> str:
    """Novel views split by the angle the face is seen from: per view and run, PSNR / LPIPS (x10^-1) of the
    frames whose head-relative view some training frame saw ("trained") and of the rest ("beyond"), with counts."""
    views = list(dict.fromkeys(v for r in results for v in r.by_view_range))
    if not views:
        return ""
    head = ["| View |"] + [f" {_escape(r.label)} trained: PSNR / LPIPS (n) | beyond: PSNR / LPIPS (n) |"
                           for r in results]
    lines = ["".join(head), "|---|" + "---:|---:|" * len(results)]

    def cell(stats: dict | None) -> str:
        if not stats or stats.get("psnr", {}).get("mean") is None:
            return "–"
        lpips = stats.get("lpips", {}).get("mean")
        return (f"{stats['psnr']['mean']:.2f} / {lpips * 10:.3f} ({stats['psnr']['count']})" if lpips is not None
                else f"{stats['psnr']['mean']:.2f} ({stats['psnr']['count']})")

    for view in views:
        cells = [cell(r.by_view_range.get(view, {}).get(part)) for r in results for part in ("trained", "beyond")]
        lines.append(f"| {_escape(view)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def side_view_table(results: Sequence[EvalResult]) -> str:
    """Floaters at side views: one row per run, the mean share of opacity outside the head silhouette (%)."""
    views = list(dict.fromkeys(v for r in results for v in r.side_views))
    if not views:
        return ""
    lines = ["| Run | " + " | ".join(views) + " |", "|---|" + "---:|" * len(views)]
    for r in results:
        cells = [f"{r.side_views[v] * 100:.1f}" if v in r.side_views else "–" for v in views]
        lines.append(f"| {_escape(r.label)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def face_table(results: Sequence[EvalResult]) -> str:
    """Face metrics beyond the per-frame means: renders with a face and the landmark agreement, one row per run."""
    rows = [r for r in results if r.faces]
    if not rows:
        return ""
    from geoavatar.eval.landmark_agreement import SIGNALS

    lines = ["| Run | renders with a face | landmark agreement ↑ | " + " | ".join(SIGNALS) + " |",
             "|---|---:|---:|" + "---:|" * len(SIGNALS)]
    for r in rows:
        faces, agreement = r.faces["faces"], r.faces["landmark_agreement"]
        cells = [f"{faces['render_found']} of {faces['frames']}", _number(agreement["agreement"])]
        cells += [_number(agreement["correlations"][name]) for name in SIGNALS]
        lines.append(f"| {_escape(r.label)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _number(value: float | None, digits: int = 3) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def extra_sections(results: Sequence[EvalResult]) -> str:
    out = ""
    faces = face_table(results)
    if faces:
        out += ("\n## Faces (dlib identity similarity and FER2013 expression similarity above; landmark agreement: "
                "Pearson r of mouth / eye openings and brow height, render vs ground truth, over the clip)\n\n" + faces)
    views = view_table(results)
    if views:
        out += "\n## Per view (novel views)\n\n" + views
    ranges = view_range_table(results)
    if ranges:
        out += ("\n## Per view, by the angle the face is seen from (trained: some training frame saw the face from "
                f"within {TRAINED_VIEW_TOLERANCE:g}°)\n\n" + ranges)
    sides = side_view_table(results)
    if sides:
        out += ("\n## Floaters at side views (% of rendered opacity outside the dilated head silhouette)\n\n"
                + sides)
    return out


def _settings_lines(result: EvalResult) -> str:
    s = result.settings
    frames = f"{s['frames_evaluated']} of {s['frames_in_split']} frames" if s["frames_evaluated"] != s["frames_in_split"] \
        else f"{s['frames_in_split']} frames"
    mouth = s.get("mouth")
    mouth_text = (f"mouth region: mouth-structure + lips faces visible in the z-buffer, dilated by "
                  f"{mouth['dilate_fraction']:g} of the image side; LPIPS on its bounding box (>= {mouth['min_crop']} px)"
                  if mouth else "mouth region: off")
    return "\n".join([
        f"- split `{result.split}`: {frames} of `{s['data_root']}` (resolution {s['resolution'] or 'as stored'})",
        f"- checkpoint `{result.checkpoint}` (step {result.step})",
        f"- images composited on the dataset background {s['background']}; LPIPS {s['lpips_net']}, inputs "
        f"{s['lpips_inputs']}; SSIM {s['ssim']}",
        f"- {mouth_text}",
        f"- mean ± std ({s['std']}); frames outside training: T = 0, parameters from "
        f"{s.get('test_params', 'the dataset')}",
    ]) + "\n"


def run_markdown(result: EvalResult) -> str:
    return (f"# Evaluation of {result.label}\n\n" + metric_table([result], mark_best=False) + extra_sections([result])
            + "\n" + _settings_lines(result))


def run_json(result: EvalResult) -> dict:
    return {
        "format": REPORT_FORMAT, "version": REPORT_VERSION,
        "run": str(result.run_dir), "label": result.label, "preset": result.preset, "subject": result.subject,
        "checkpoint": result.checkpoint, "step": result.step, "split": result.split,
        "seconds": round(result.seconds, 3),
        "summary": result.summary, "by_view": result.by_view, "by_view_range": result.by_view_range,
        "side_views": result.side_views, "faces": result.faces,
        "settings": result.settings, "frames": frame_dicts(result),
    }


def write_frame_images(result: EvalResult, folder: Path) -> list[Path]:
    """gt | pred | |error| x 4 | mouth mask for each kept frame, as PNG files named by timestep and camera."""
    paths = []
    for frame, images in zip(result.frames, result.images):
        gt, pred = images["gt"], images["pred"]
        error = ((pred - gt).abs() * 4.0).clamp(0.0, 1.0)
        panels = [gt, pred, error]
        if images.get("mouth") is not None:
            panels.append(images["mouth"].float()[..., None].expand_as(gt))
        row = to_uint8(np.concatenate([p.numpy() for p in panels], axis=1))
        path = folder / f"{frame.timestep:05d}_{frame.camera:02d}.png"
        paths.append(atomic_write_png(path, row))
    return paths


def write_run_report(result: EvalResult, out_dir: str | Path | None = None) -> dict[str, Path]:
    """RUN/eval/<split>/metrics.json and metrics.md (+ frames/*.png when the result kept images)."""
    folder = Path(out_dir) if out_dir is not None else eval_dir(result.run_dir, result.split)
    written = {"json": atomic_write_json(folder / "metrics.json", run_json(result)),
               "markdown": atomic_write_text(folder / "metrics.md", run_markdown(result))}
    if result.images:
        write_frame_images(result, folder / "frames")
        written["frames"] = folder / "frames"
    return written


def comparison_markdown(results: Sequence[EvalResult]) -> str:
    splits = sorted({r.split for r in results})
    nets = sorted({r.settings["lpips_net"] for r in results})
    return (f"# Comparison on the {'/'.join(splits)} split ({len(results)} runs, LPIPS {'/'.join(nets)})\n\n"
            "## Table 1 layout (mean ± std)\n\n" + metric_table(results)
            + "\n## Ablation layout (means)\n\n" + ablation_table(results) + extra_sections(results)
            + "\n**Bold**: best, <u>underlined</u>: second. Per-run details: `RUN/eval/<split>/metrics.json`.\n")


def comparison_paths(path: str | Path) -> tuple[Path, Path]:
    """The comparison's Markdown (`path`, .md added when missing) and its JSON beside it."""
    path = Path(path)
    markdown = path if path.suffix.lower() == ".md" else path.with_name(path.name + ".md")
    return markdown, markdown.with_suffix(".json")


def check_comparison_target(path: str | Path) -> None:
    """OptionError unless writing the comparison at `path` replaces nothing but an earlier comparison: `--out
    RUN/eval/test/metrics` would otherwise overwrite that run's own report."""
    if Path(path).is_dir():  # the table would land beside the folder, as FOLDER.md and FOLDER.json
        raise OptionError(f"--out {path} is a folder; --out names the comparison file (e.g. {Path(path) / 'table.md'})")
    markdown, summary = comparison_paths(path)
    if not (markdown.exists() or summary.exists()):
        return
    try:
        earlier = json.loads(summary.read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        earlier = None
    if earlier != REPORT_FORMAT + "-comparison":
        raise OptionError(f"--out {path}: {markdown.name} / {summary.name} exist there and are not an earlier "
                          "comparison table; --out names the comparison file, not a folder (give a new name)")


def distinct_labels(results: Sequence[EvalResult]) -> list[EvalResult]:
    """The results with every label that names more than one of them ('E · s0', the same preset on the same dataset)
    followed by its run folder's name, or its whole path where those are alike too, so each column says which run."""
    from collections import Counter
    from dataclasses import replace

    counts = Counter(r.label for r in results)
    named = [replace(r, label=f"{r.label} ({Path(r.run_dir).name})") if counts[r.label] > 1 else r for r in results]
    counts = Counter(r.label for r in named)
    return [replace(n, label=f"{r.label} ({r.run_dir})") if counts[n.label] > 1 else n for n, r in zip(named, results)]


def write_comparison(results: Sequence[EvalResult], path: str | Path) -> dict[str, Path]:
    """The comparison Markdown at `path` (.md added when missing) and a JSON of every summary beside it."""
    markdown, summary = comparison_paths(path)
    body = {"format": REPORT_FORMAT + "-comparison", "version": REPORT_VERSION, "runs": [
        {k: v for k, v in run_json(r).items() if k != "frames"} for r in results]}
    return {"markdown": atomic_write_text(markdown, comparison_markdown(results)),
            "json": atomic_write_json(summary, body)}


__all__ = ["COLUMNS", "MetricColumn", "ablation_table", "check_comparison_target", "comparison_paths", "extra_sections",
           "face_table",
           "side_view_table", "view_range_table", "view_table",
           "comparison_markdown", "distinct_labels", "eval_dir", "metric_table",
           "run_json", "run_markdown", "write_comparison", "write_frame_images", "write_run_report"]
