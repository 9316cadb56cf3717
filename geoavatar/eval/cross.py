"""Cross re-enactment scored without ground truth (`geoavatar eval RUN --driver DATA | --driver-video FILE`).

    scored = score_cross(driven.pictures(modes), modes, scorer)           # mode -> (timestep, FaceScores) per frame
    result = CrossResult(run_dir, label, driver, root, scored, ...)       # summaries per mode (face_summary)
    write_cross_report(result, cross_dir(run_dir, driver_name))           # RUN/eval/cross@<driver>/metrics.{json,md}

apps/eval.py's evaluate_cross drives the avatar (animation/sources/driver.py's DrivenAvatar) and scores it with
these.

Every driver frame (evenly spaced with --max-frames) is rendered once per transfer mode, exactly as `geoavatar
reenact` renders it, and scored by eval/face_scores.py against the driver's frame: dlib identity similarity to the
avatar's own training frames, FER2013 expression similarity to the driver frame (the paper appendix's two scores)
and the landmark agreement of mouth, eyes and brows over the clip. The driver's own face is scored against the
avatar's identity too (`source_id_similarity`): a render that copied the driver's face would score that. Renders
in which no face is detected are counted per mode (`faces.render_missing`) and get no score.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

from geoavatar.eval.face_scores import FaceScores, face_summary, scores_dict
from geoavatar.eval.landmark_agreement import SIGNALS
from geoavatar.io.atomic import atomic_write_json, atomic_write_text

if TYPE_CHECKING:
    from geoavatar.eval.face_scores import FaceScorer

DrivenPicture = tuple  # (driver timestep, driver frame uint8 [H, W, 3], {transfer mode: render uint8 [H', W', 3]})

REPORT_FORMAT = "geoavatar-eval-cross"
REPORT_VERSION = 1


@dataclass
class CrossResult:
    run_dir: Path
    label: str  # the run's label (eval's run_label)
    driver: str  # the driver's name (dataset folder or video stem)
    driver_root: Path
    modes: dict[str, list[tuple[int, FaceScores]]]  # transfer mode -> (driver timestep, scores) per frame
    settings: dict = field(default_factory=dict)
    seconds: float = 0.0
    summaries: dict[str, dict] = field(init=False)  # transfer mode -> face_summary of its frames

    def __post_init__(self):
        self.summaries = {mode: face_summary([scores for _, scores in frames]) for mode, frames in self.modes.items()}


def cross_dir(run_dir: str | Path, driver: str) -> Path:
    """RUN/eval/cross@<driver>: the report of the avatar driven by `driver`."""
    return Path(run_dir) / "eval" / f"cross@{driver}"


def score_cross(pictures: Iterable[DrivenPicture], modes: Sequence[str], scorer: "FaceScorer",
                progress: bool = True, label: str = "eval cross") -> dict[str, list[tuple[int, FaceScores]]]:
    """Transfer mode -> (driver timestep, scores) of each render against its driver frame; pictures:
    (timestep, driver frame uint8 [H, W, 3], {mode: render uint8 [H', W', 3]}), the driver frame read once."""
    from tqdm.auto import tqdm

    scored: dict[str, list[tuple[int, FaceScores]]] = {mode: [] for mode in modes}
    for timestep, driver, renders in tqdm(pictures, disable=not progress, desc=label, unit="frame"):
        source = scorer.read(driver)
        for mode in modes:
            scored[mode].append((timestep, scorer.score(renders[mode], source)))
    return scored


def _cell(stats: dict, digits: int = 3) -> str:
    if stats.get("mean") is None:
        return "–"
    return f"{stats['mean']:.{digits}f} ± {stats['std']:.2f}" if stats.get("std") is not None else \
        f"{stats['mean']:.{digits}f}"


def _number(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"


def mode_table(summaries: dict[str, dict]) -> str:
    """Rows = transfer modes; columns = the paper appendix's scores, the landmark agreement, renders with a face."""
    lines = ["| Transfer | ID similarity (dlib) ↑ | Expression similarity ↑ | Landmark agreement ↑ | "
             "renders with a face |", "|---|---:|---:|---:|---:|"]
    for mode, s in summaries.items():
        faces = s["faces"]
        lines.append(f"| {mode} | {_cell(s['id_similarity'])} | {_cell(s['expression_similarity'])} | "
                     f"{_number(s['landmark_agreement']['agreement'])} | "
                     f"{faces['render_found']} of {faces['frames']} |")
    return "\n".join(lines) + "\n"


def signal_table(summaries: dict[str, dict]) -> str:
    """Landmark agreement per signal (Pearson r, driver vs render), one row per mode."""
    lines = ["| Transfer | " + " | ".join(SIGNALS) + " |", "|---|" + "---:|" * len(SIGNALS)]
    for mode, s in summaries.items():
        correlations = s["landmark_agreement"]["correlations"]
        lines.append(f"| {mode} | " + " | ".join(_number(correlations[name]) for name in SIGNALS) + " |")
    return "\n".join(lines) + "\n"


def cross_markdown(result: CrossResult) -> str:
    first = next(iter(result.summaries.values()))
    driver_id, faces = first["source_id_similarity"], first["faces"]
    s = result.settings
    return (f"# Cross re-enactment: {result.label} driven by {result.driver}\n\n" + mode_table(result.summaries)
            + "\n## Landmark agreement per signal\n\n" + signal_table(result.summaries)
            + f"\n- the driver's own face against the avatar's identity: {_cell(driver_id)} (what a render copying "
              f"the driver's face would score); driver frames with a face: {faces['source_found']} of {faces['frames']}"
            + f"\n- {s['frames_evaluated']} of {s['frames_in_driver']} driver frames ({s['driver_split']}) of "
              f"`{result.driver_root}`; camera {s['camera']}; neutral frames: driver {s['driver_neutral']}, avatar "
              f"{s['avatar_neutral']}; identity reference: {s['faces']['reference_faces']} of "
              f"{s['faces']['reference_frames']} training frames with a face"
            + "\n- ID similarity: dlib face-recognition descriptors, cosine to the mean of the avatar's training "
              "frames (not ArcFace); expression similarity: cosine of FER2013 mini-Xception probabilities, render "
              "vs driver; landmark agreement: mean Pearson r of the signals above over the frames with both faces\n")


def cross_json(result: CrossResult) -> dict:
    return {"format": REPORT_FORMAT, "version": REPORT_VERSION, "run": str(result.run_dir), "label": result.label,
            "driver": result.driver, "driver_root": str(result.driver_root), "seconds": round(result.seconds, 3),
            "summary": result.summaries, "settings": result.settings,
            "frames": {mode: [{"timestep": t, **scores_dict(scores)} for t, scores in frames]
                       for mode, frames in result.modes.items()}}


def write_cross_report(result: CrossResult, folder: str | Path | None = None) -> dict[str, Path]:
    """metrics.json (per frame and summary, per mode) and metrics.md in RUN/eval/cross@<driver>/, atomically."""
    folder = Path(folder) if folder is not None else cross_dir(result.run_dir, result.driver)
    return {"json": atomic_write_json(folder / "metrics.json", cross_json(result)),
            "markdown": atomic_write_text(folder / "metrics.md", cross_markdown(result))}


__all__ = ["CrossResult", "DrivenPicture", "cross_dir", "cross_json", "cross_markdown", "mode_table", "score_cross",
           "signal_table", "write_cross_report"]
