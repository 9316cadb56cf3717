"""The capture check: what a tracked video shows of a head, per split, and where its test frames leave it.

What the camera never saw cannot be learned (issue #18): an avatar trained on a video whose head never
turns guesses every side view, one whose mouth never opens guesses the mouth's inside. This is a function
of the tracked parameters alone, so it runs on a fresh `prepare` and on any dataset:

    measures = measure_frames(head, params: HeadParams [T], viewmat [T, 4, 4])   # FrameMeasures, one row a frame
    report = capture_report(measures, {"train": rows, "test": rows}, timesteps)  # JSON-able; report["verdict"]
    plot_coverage(measures, splits, report, "coverage.png")

Measures per frame (conventions of `geoavatar.head.view_angles`: head axes, +x the head's left, +y up):
- yaw, pitch (degrees): where the camera sees the face from, in the head's own axes (neck and global rotation
  alike; yaw > 0: the camera sees the head's left side, pitch > 0: from above);
- jaw (degrees): the jaw's opening rotation (jaw_pose x);
- smile (mm): how far the mouth corners (MediaPipe 61 / 291) move up and outward from the neutral face;
- brows (mm): how far the upper brow contours move up (> 0) or down from the neutral face;
- eyes: the smaller of the two eyelid gaps (middle points of the eye contours) over the neutral face's gap:
  1 open as at rest, below BLINK_OPENNESS closed (a blink);
- gaze_yaw, gaze_pitch (degrees): where the eyeballs look relative to the head (mean of both eyes).
The expression measures pose the head's embedded landmarks with the frame's expression only (no head pose, no
jaw: an open jaw moves the mouth corners too), against the same person's neutral face, so they read alike for
any head model with a MediaPipe landmark embedding (NaN without one).

A test frame lies outside training when no training frame saw the face from within TRAINED_VIEW_TOLERANCE
degrees (eval's rule, `within_trained_views`), or when one of the other measures goes beyond the training
frames' range by more than its MARGINS entry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from geoavatar.head import landmarks_mediapipe as mpids
from geoavatar.head.params import HeadParams

MEASURES = ("yaw", "pitch", "jaw", "smile", "brows", "eyes", "gaze_yaw", "gaze_pitch")
UNITS = {"yaw": "deg", "pitch": "deg", "jaw": "deg", "smile": "mm", "brows": "mm", "eyes": "of rest",
         "gaze_yaw": "deg", "gaze_pitch": "deg"}
# How far beyond the training range a test frame may go before it counts as outside (units of UNITS).
MARGINS = {"jaw": 3.0, "smile": 1.5, "brows": 1.0, "eyes": 0.15, "gaze_yaw": 5.0, "gaze_pitch": 5.0}
TRAINED_VIEW_TOLERANCE = 5.0  # degrees: eval's rule for "a training frame saw the face so"
BLINK_OPENNESS = 0.5  # eyes below half their resting gap: closed
# What a video "shows" (calibrated on OpenHead: its smile mode at 1 lifts the corners 8 mm, brow_raise 4.6 mm).
SMILE_MM = 3.0
BROW_RAISE_MM = 2.0
BROW_LOWER_MM = -1.5
# Advice thresholds: the head turns enough when the views reach TURN_DEG to each side, NOD_DEG up and down.
TURN_DEG = 15.0
NOD_DEG = 10.0
STILL_DEG = 10.0  # a yaw or pitch span under this: the head hardly turns / nods (tracking wobbles a few degrees)
JAW_OPEN_DEG = 10.0
GAZE_DEG = 8.0
TEST_OUTSIDE_SHARE = 0.25  # more of the test frames outside training than this: the verdict says so
CHUNK = 256  # frames posed at once (a long video's meshes at once would take gigabytes)


@dataclass
class FrameMeasures:
    """The measures of every frame (see the module docstring), each [T]; `directions` [T, 3] the view
    directions in head axes (what the trained-view test compares)."""

    yaw: np.ndarray
    pitch: np.ndarray
    jaw: np.ndarray
    smile: np.ndarray
    brows: np.ndarray
    eyes: np.ndarray
    gaze_yaw: np.ndarray
    gaze_pitch: np.ndarray
    directions: np.ndarray

    def rows(self, index: np.ndarray) -> "FrameMeasures":
        return FrameMeasures(**{f.name: getattr(self, f.name)[index] for f in fields(self)})


def _contour_points(ids) -> tuple[int, ...]:
    """The middle three points of an eye contour (the lid's highest / lowest stretch)."""
    middle = len(ids) // 2
    return tuple(ids[middle - 1:middle + 2])


# Landmark groups (MediaPipe ids) of the expression measures.
MOUTH_CORNERS = (mpids.LIPS_OUTER_UPPER[0], mpids.LIPS_OUTER_UPPER[-1])  # 61 (the head's right), 291 (left)
BROWS = mpids.RIGHT_BROW_UPPER + mpids.LEFT_BROW_UPPER
EYELIDS = ((_contour_points(mpids.RIGHT_EYE_UPPER), _contour_points(mpids.RIGHT_EYE_LOWER)),
           (_contour_points(mpids.LEFT_EYE_UPPER), _contour_points(mpids.LEFT_EYE_LOWER)))
EXPRESSION_IDS = (*MOUTH_CORNERS, *BROWS, *(i for lids in EYELIDS for ids in lids for i in ids))


def _expression_landmarks(head, params: HeadParams) -> Tensor | None:
    """[B, L, 3] the embedded landmarks with only the expression of each frame (no pose, no jaw, no eyes)."""
    if head.landmark_ids is None:
        return None
    still = params.map(torch.zeros_like).replace(shape=params.shape, static_offset=params.static_offset,
                                                 expr=params.expr)
    return head.forward_params(still, vertex_ids=head.landmark_vertex_ids).landmarks


def _expression_measures(points: Tensor, neutral: Tensor, column: dict[int, int]) -> dict[str, np.ndarray]:
    """smile, brows (mm) and eyes (gap over the neutral gap) of landmarks [B, L, 3] against neutral [L, 3]."""
    def mean_of(p: Tensor, ids) -> Tensor:  # [..., 3]
        return p[..., [column[i] for i in ids], :].mean(-2)

    right, left = (points[:, column[i]] - neutral[column[i]] for i in MOUTH_CORNERS)  # [B, 3] each
    smile = ((right[:, 1] - right[:, 0]) + (left[:, 1] + left[:, 0])) / (2 * math.sqrt(2))  # up and outward
    brows = mean_of(points, BROWS)[:, 1] - mean_of(neutral, BROWS)[1]
    openness = []
    for upper, lower in EYELIDS:
        gap = (mean_of(points, upper) - mean_of(points, lower)).norm(dim=-1)  # [B]
        rest = (mean_of(neutral, upper) - mean_of(neutral, lower)).norm().clamp_min(1e-6)
        openness.append(gap / rest)
    eyes = torch.minimum(*openness)
    return {"smile": 1000 * smile.numpy(), "brows": 1000 * brows.numpy(), "eyes": eyes.numpy()}


def _gaze(eyes_pose: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Gaze yaw, pitch (degrees) [B] relative to the head: the mean of both eyeballs' forward axes."""
    from geoavatar.geometry import axis_angle_to_matrix

    forward = sum(axis_angle_to_matrix(eyes_pose[:, k:k + 3].double())[..., :, 2] for k in (0, 3))  # [B, 3]
    x, y, z = forward.unbind(-1)
    return np.degrees(torch.atan2(x, z).numpy()), np.degrees(torch.atan2(y, torch.hypot(x, z)).numpy())


def measure_frames(head, params: HeadParams, viewmat: Tensor) -> FrameMeasures:
    """The measures of every frame of `params` [T] seen by cameras `viewmat` [T, 4, 4] (world-to-camera)."""
    from geoavatar.head.view_angles import rest_skull, view_directions, yaw_pitch
    from geoavatar.head.regions import skull_vertex_ids

    params = params.detach().map(lambda x: x.float().cpu())
    viewmat = torch.as_tensor(viewmat, dtype=torch.float32).expand(params.batch, 4, 4)
    skull = skull_vertex_ids(head)
    parts: dict[str, list[np.ndarray]] = {name: [] for name in (*MEASURES, "directions")}
    with torch.no_grad():
        rest = rest_skull(head, params)  # [S, 3]
        column = {int(i): k for k, i in enumerate(head.landmark_ids.tolist())} if head.landmark_ids is not None else {}
        neutral = _expression_landmarks(head, params.rows(slice(0, 1)).map(torch.zeros_like).replace(
            shape=params.shape, static_offset=params.static_offset))
        for start in range(0, params.batch, CHUNK):
            chunk = params.rows(slice(start, start + CHUNK))
            posed = head.forward_params(chunk, vertex_ids=skull).vertices  # [B, S, 3]
            directions = view_directions(rest, posed, viewmat[start:start + CHUNK])  # [B, 3]
            yaw, pitch = yaw_pitch(directions)
            parts["directions"].append(directions.numpy())
            parts["yaw"].append(yaw.numpy())
            parts["pitch"].append(pitch.numpy())
            parts["jaw"].append(np.degrees(chunk.jaw_pose[:, 0].double().numpy()))
            gaze_yaw, gaze_pitch = _gaze(chunk.eyes_pose)
            parts["gaze_yaw"].append(gaze_yaw)
            parts["gaze_pitch"].append(gaze_pitch)
            expression = _expression_landmarks(head, chunk)
            if expression is not None and all(i in column for i in EXPRESSION_IDS):
                for name, values in _expression_measures(expression, neutral[0], column).items():
                    parts[name].append(values)
            else:  # no landmark embedding: what the landmarks measure stays unknown
                for name in ("smile", "brows", "eyes"):
                    parts[name].append(np.full(chunk.batch, np.nan))
    return FrameMeasures(**{name: np.concatenate(values).astype(np.float64) for name, values in parts.items()})


# --- the report ----------------------------------------------------------------------------------


def _finite(values: np.ndarray) -> np.ndarray:
    return values[np.isfinite(values)]


def _events(flags: np.ndarray) -> int:
    """Runs of True in flags [T] (a blink held over 3 frames is one blink)."""
    flags = np.asarray(flags, bool)
    return int(np.count_nonzero(flags[1:] & ~flags[:-1]) + (1 if flags.size and flags[0] else 0))


def eye_openness(points: np.ndarray) -> np.ndarray:
    """[T] the face mesh's own eye opening: the smaller eyelid gap of detected landmarks [T, 478, >=2] over its
    median over the frames (1: as usual, below BLINK_OPENNESS: a blink)."""
    gaps = [np.linalg.norm(points[:, list(upper), :2].mean(1) - points[:, list(lower), :2].mean(1), axis=-1)
            for upper, lower in EYELIDS]
    gap = np.minimum(*gaps)
    return gap / max(float(np.median(gap)), 1e-9)


def summarize_split(m: FrameMeasures, detected_eyes: np.ndarray | None = None) -> dict:
    """Range of every measure over one split's frames (min, 5th / 50th / 95th percentile, max) and how often
    the face smiles, raises or lowers its brows, blinks, opens the jaw; with the face mesh's eye opening of the
    frames (`eye_openness`), how often it saw a blink too (the tracking can smooth a short one away)."""
    out: dict = {"frames": int(m.yaw.size)}
    for name in MEASURES:
        values = _finite(getattr(m, name))
        out[name] = None if values.size == 0 else {
            "min": round(float(values.min()), 2), "p5": round(float(np.percentile(values, 5)), 2),
            "median": round(float(np.median(values)), 2), "p95": round(float(np.percentile(values, 95)), 2),
            "max": round(float(values.max()), 2)}
    share = lambda flags: round(float(np.mean(flags)), 3) if flags.size else 0.0  # noqa: E731
    closed = m.eyes < BLINK_OPENNESS
    out["shows"] = {"smile": share(m.smile >= SMILE_MM), "brow_raise": share(m.brows >= BROW_RAISE_MM),
                    "brow_lower": share(m.brows <= BROW_LOWER_MM), "eyes_closed": share(closed),
                    "jaw_open": share(m.jaw >= JAW_OPEN_DEG), "blinks": _events(closed)}
    if detected_eyes is not None:
        out["face_mesh_blinks"] = _events(detected_eyes < BLINK_OPENNESS)
    return out


def outside_training(train: FrameMeasures, test: FrameMeasures) -> dict[str, np.ndarray]:
    """{reason: [N_test] bool}: test frames seen from a view no training frame had ("view"), or beyond the
    training range of a measure by more than its margin (MARGINS; an unmeasured value never counts)."""
    from geoavatar.head.view_angles import within_trained_views

    seen = within_trained_views(torch.as_tensor(test.directions), torch.as_tensor(train.directions),
                                TRAINED_VIEW_TOLERANCE).numpy()
    reasons = {"view": ~seen}
    for name, margin in MARGINS.items():
        known = _finite(getattr(train, name))
        values = getattr(test, name)
        if known.size == 0:
            reasons[name] = np.zeros(values.shape, bool)
            continue
        with np.errstate(invalid="ignore"):
            reasons[name] = (values > known.max() + margin) | (values < known.min() - margin)
    return reasons


def timestep_ranges(timesteps) -> str:
    """'120-135, 140' from sorted timesteps."""
    timesteps = [int(t) for t in timesteps]
    runs: list[list[int]] = []
    for t in timesteps:
        if runs and t == runs[-1][1] + 1:
            runs[-1][1] = t
        else:
            runs.append([t, t])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def capture_report(measures: FrameMeasures, splits: dict[str, np.ndarray], timesteps,
                   detected_eyes: np.ndarray | None = None) -> dict:
    """The capture check of a video: per split the range of every measure, the test frames outside training
    (by reason, as timestep ranges), the advice and a one-line verdict. splits: name -> row ids into measures;
    timesteps [T] the dataset timestep of each row; detected_eyes [T] the face mesh's eye opening, or None."""
    timesteps = np.asarray(timesteps)
    report: dict = {"units": dict(UNITS), "splits": {}}
    for name, rows in splits.items():
        rows = np.asarray(rows, np.int64)
        eyes = None if detected_eyes is None else detected_eyes[rows]
        report["splits"][name] = summarize_split(measures.rows(rows), eyes)
    train, test = (np.asarray(splits.get(name, []), np.int64) for name in ("train", "test"))
    if train.size and test.size:
        reasons = outside_training(measures.rows(train), measures.rows(test))
        outside = np.logical_or.reduce(list(reasons.values()))
        report["test_outside"] = {
            "frames": int(outside.sum()), "share": round(float(outside.mean()), 3),
            "timesteps": timestep_ranges(timesteps[test][outside]),
            "by_measure": {name: {"frames": int(flags.sum()), "timesteps": timestep_ranges(timesteps[test][flags])}
                           for name, flags in reasons.items() if flags.any()}}
    report["advice"] = advice(report)
    report["verdict"] = verdict(report)
    return report


# Advice on the head's reach, per measure: the reach wanted each way, the verb, what to do when the head hardly moves,
# and where to move when the high side, the low side or both fall short. yaw > 0: the camera sees the head's left side,
# i.e. the head turned to its own right; pitch > 0: the camera sees it from above, the head bowed.
POSE_ADVICE = {
    "yaw": (TURN_DEG, "turns", "turn your head slowly left and right", "turn it further",
            ("to your right", "to your left", "left and right")),
    "pitch": (NOD_DEG, "nods", "nod slowly up and down", "tilt it further", ("down", "up", "up and down")),
}


def _pose_advice(summary: dict, name: str) -> str | None:
    """Advice on the head's yaw or pitch, or None when it reaches far enough both ways."""
    reach, verb, still, further, (high_way, low_way, both_ways) = POSE_ADVICE[name]
    low, high = summary[name]["min"], summary[name]["max"]
    span = f"{name} {low:+.0f}..{high:+.0f} deg"
    guessed = "" if name != "yaw" else (f"; side views beyond yaw {low - TRAINED_VIEW_TOLERANCE:+.0f}.."
                                        f"{high + TRAINED_VIEW_TOLERANCE:+.0f} deg will be guesses")
    if high - low < STILL_DEG:
        return f"the head hardly {verb} ({span}): {still}{guessed}"
    short_high, short_low = high < reach, -low < reach
    if not (short_high or short_low):
        return None
    where = both_ways if short_high and short_low else (high_way if short_high else low_way)
    return f"the head {verb} only to {span}: {further} {where} (to about {reach:.0f} deg){guessed}"


def _expression_advice(summary: dict) -> list[str]:
    """Advice on the jaw, the expressions and the gaze."""
    items = []
    jaw = summary["jaw"]
    if jaw is not None and jaw["max"] < JAW_OPEN_DEG:
        items.append(f"the mouth never opens wide (jaw at most {jaw['max']:.0f} deg): talk and laugh with your mouth "
                     "open; its inside will be guessed")
    shows = summary["shows"]
    if summary["smile"] is not None:  # the landmark measures exist
        seen_blinks = summary.get("face_mesh_blinks", 0)  # blinks the tracking smoothed away are still blinks filmed
        missing = [what for what, seen in (("smile", shows["smile"]), ("raise your eyebrows", shows["brow_raise"]),
                                           ("blink", shows["blinks"] or seen_blinks)) if not seen]
        if missing:
            listed = ", ".join(missing[:-1]) + (" and " if len(missing) > 1 else "") + missing[-1]
            items.append(f"{listed} now and then: expressions the video never shows will be guesses")
        if seen_blinks and not shows["blinks"]:
            items.append(f"the face mesh saw {seen_blinks} blink(s) but the tracked eyelids close only to "
                         f"{summary['eyes']['min']:.0%} of their rest: the avatar will not learn closed eyes")
    spans = [summary[name]["max"] - summary[name]["min"] for name in ("gaze_yaw", "gaze_pitch") if summary[name]]
    if spans and max(spans) < GAZE_DEG:
        items.append("the eyes never look around: move your gaze now and then")
    return items


def advice(report: dict) -> list[str]:
    """What to film differently, most important first (empty: the video covers what an avatar needs): the head's
    reach (what novel views need), then a test segment beyond training (it decides what the scores mean), then the
    jaw, the expressions and the gaze."""
    splits = report["splits"]
    summary = splits.get("train") or next(iter(splits.values()))
    items = [text for text in (_pose_advice(summary, "yaw"), _pose_advice(summary, "pitch")) if text]
    outside = report.get("test_outside")
    if outside and outside["share"] > TEST_OUTSIDE_SHARE:
        reasons = sorted(outside["by_measure"].items(), key=lambda item: -item[1]["frames"])
        why = ", ".join(f"{name} {item['frames']}" for name, item in reasons[:3])
        items.append(f"the test segment leaves what training saw in {outside['share']:.0%} of its frames "
                     f"({why} frames): its scores measure unseen poses and expressions; end the video as it began")
    return items + _expression_advice(summary)


def verdict(report: dict) -> str:
    """One line: what the video covers, or the first two pieces of advice."""
    items = report["advice"]
    if items:
        more = f" (+{len(items) - 2} more in coverage.png / report.json)" if len(items) > 2 else ""
        return "capture check: " + "; ".join(items[:2]) + more
    splits = report["splits"]
    s = splits.get("train") or next(iter(splits.values()))
    return (f"capture check: good: yaw {s['yaw']['min']:+.0f}..{s['yaw']['max']:+.0f} deg, pitch "
            f"{s['pitch']['min']:+.0f}..{s['pitch']['max']:+.0f} deg, jaw up to {s['jaw']['max']:.0f} deg, smiles, "
            "brows and blinks; the test frames stay within what training saw")


# --- the picture ---------------------------------------------------------------------------------

SPLIT_COLOURS = {"train": "#3b75af", "test": "#ef8636"}
OUTSIDE_COLOUR = "#c0392b"
TIMELINES = (  # panel title, measures drawn in it, reference lines
    ("view yaw / pitch (deg)", ("yaw", "pitch"), (-TURN_DEG, TURN_DEG)),
    ("jaw opening (deg)", ("jaw",), (JAW_OPEN_DEG,)),
    ("smile / brows (mm)", ("smile", "brows"), (SMILE_MM, BROW_RAISE_MM)),
    ("eye opening (of rest)", ("eyes", "face mesh eyes"), (BLINK_OPENNESS,)),
    ("gaze yaw / pitch (deg)", ("gaze_yaw", "gaze_pitch"), ()),
)


def _outside_rows(report: dict, timesteps: np.ndarray) -> np.ndarray:
    """Rows of the test frames outside training (from the report's timestep ranges)."""
    text = report.get("test_outside", {}).get("timesteps", "")
    wanted: set[int] = set()
    for part in filter(None, (p.strip() for p in text.split(","))):
        a, _, b = part.partition("-")
        wanted.update(range(int(a), int(b or a) + 1))
    return np.flatnonzero(np.isin(timesteps, list(wanted)))


def plot_coverage(measures: FrameMeasures, splits: dict[str, np.ndarray], report: dict, timesteps, path,
                  detected_eyes: np.ndarray | None = None) -> Path:
    """coverage.png: the views of the face (yaw x pitch, per split, test frames outside training marked) beside
    every measure over the frames (the test segment shaded; the face mesh's own eye opening beside the tracked one
    when given), under the verdict. Written atomically."""
    import textwrap
    import warnings

    from geoavatar.io.atomic import atomic_file

    with warnings.catch_warnings():  # matplotlib warns about its own use of pyparsing (import, first text)
        warnings.simplefilter("ignore")
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        timesteps = np.asarray(timesteps)
        outside = _outside_rows(report, timesteps)
        figure = plt.figure(figsize=(13, 7.5), dpi=100)
        grid = figure.add_gridspec(len(TIMELINES), 2, width_ratios=(1.0, 1.6), hspace=0.45, wspace=0.18,
                                   top=0.86, bottom=0.07, left=0.06, right=0.98)
        _draw_views(figure.add_subplot(grid[:, 0]), measures, splits, outside)
        test = np.asarray(splits.get("test", []), np.int64)
        series = {name: getattr(measures, name) for name in MEASURES}
        if detected_eyes is not None:
            series["face mesh eyes"] = detected_eyes
        for k, panel in enumerate(TIMELINES):
            _draw_timeline(figure.add_subplot(grid[k, 1]), panel, series, test, outside, last=k == len(TIMELINES) - 1)
        figure.suptitle("\n".join(textwrap.wrap(report["verdict"], 150)), fontsize=10, x=0.01, ha="left")
        path = Path(path)
        with atomic_file(path, suffix=".png") as tmp:
            figure.savefig(tmp, format="png")
        plt.close(figure)
    return path


def _draw_views(axis, measures: FrameMeasures, splits: dict[str, np.ndarray], outside: np.ndarray) -> None:
    """Yaw x pitch of every frame, one colour per split, the test frames outside training as crosses."""
    from matplotlib.patches import Rectangle

    for name, rows in splits.items():
        axis.scatter(measures.yaw[rows], measures.pitch[rows], s=7, alpha=0.6, color=SPLIT_COLOURS.get(name, "grey"),
                     label=f"{name} ({len(rows)} frames)")
    if outside.size:
        axis.scatter(measures.yaw[outside], measures.pitch[outside], s=22, marker="x", color=OUTSIDE_COLOUR,
                     label=f"test, outside training ({outside.size})")
    axis.add_patch(Rectangle((-TURN_DEG, -NOD_DEG), 2 * TURN_DEG, 2 * NOD_DEG, fill=False, linestyle="--",
                             color="grey", label="advised reach"))
    reach = max(35.0, float(np.nanmax(np.abs(np.r_[measures.yaw, measures.pitch]))) + 5.0)
    axis.set(xlim=(-reach, reach), ylim=(-reach, reach), aspect="equal", title="where the camera saw the face from",
             xlabel="yaw (deg; + sees the head's left side)", ylabel="pitch (deg; + sees it from above)")
    axis.grid(alpha=0.3)
    axis.legend(loc="lower left", fontsize=8)


def _draw_timeline(axis, panel, series: dict[str, np.ndarray], test: np.ndarray, outside: np.ndarray,
                   last: bool) -> None:
    """One TIMELINES panel over the frames: its measures (those `series` has), reference lines, the test segment
    shaded."""
    title, names, lines = panel
    names = [name for name in names if name in series]
    frames = np.arange(series["yaw"].size)
    for index, name in enumerate(names):
        axis.plot(frames, series[name], lw=1.0, color=("#333333", "#8e44ad")[index], label=name)
    for value in lines:
        axis.axhline(value, color="grey", lw=0.7, ls="--")
    if test.size:
        axis.axvspan(test.min() - 0.5, test.max() + 0.5, color=SPLIT_COLOURS["test"], alpha=0.15, lw=0)
    if outside.size:
        axis.plot(outside, np.full(outside.size, axis.get_ylim()[1]), "|", color=OUTSIDE_COLOUR, ms=6)
    axis.set_title(title, fontsize=9, loc="left")
    axis.tick_params(labelsize=8)
    axis.set_xlim(-0.5, frames.size - 0.5)
    if len(names) > 1:
        axis.legend(fontsize=7, loc="upper left", ncol=2)
    if last:
        axis.set_xlabel("frame (shaded: the test segment)", fontsize=8)


# --- entry points --------------------------------------------------------------------------------


def capture_check(head, params: HeadParams, viewmat, splits: dict[str, np.ndarray], timesteps, picture,
                  detected_eyes: np.ndarray | None = None) -> dict:
    """measure_frames + capture_report + plot_coverage (to `picture`): prepare's write stage (which passes the
    face mesh's eye opening, `eye_openness`) and the `geoavatar coverage` command. viewmat [4, 4] (one camera) or
    [T, 4, 4]. Returns the report."""
    measures = measure_frames(head, params, torch.as_tensor(np.asarray(viewmat), dtype=torch.float32))
    report = capture_report(measures, splits, timesteps, detected_eyes)
    plot_coverage(measures, splits, report, timesteps, picture, detected_eyes)
    return report


def dataset_capture_check(root, out, flame_dir=None) -> dict:
    """The capture check of a dataset folder (any layout `open_subject` reads): OUT/coverage.json and
    OUT/coverage.png. Splits are the dataset's own (transforms_*.json) or the split rule's."""
    import warnings

    from geoavatar.data.dataset import check_head_model, open_subject
    from geoavatar.data.splits import ShortVideoWarning
    from geoavatar.head import load_head_model
    from geoavatar.io.atomic import atomic_write_json

    subject = open_subject(root)
    options = {"flame_dir": flame_dir} if subject.head_model == "flame" and flame_dir is not None else {}
    check_head_model(subject, **options)
    head = load_head_model(subject.head_model, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShortVideoWarning)
        split = subject.split()
    row_of = {t: k for k, t in enumerate(subject.timesteps)}
    splits = {name: np.array([row_of[t] for t in split.timesteps(name)], np.int64) for name in ("train", "test")}
    first_view = {}
    for frame in sorted(subject.frames, key=lambda f: (f.row, f.camera)):  # a multi-camera dataset: its first camera
        first_view.setdefault(frame.row, frame.viewmat)
    viewmat = np.stack([first_view[row] for row in range(subject.num_timesteps)])
    params = HeadParams.from_npz({k: v.float() for k, v in subject.params.items()})
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = capture_check(head, params, viewmat, splits, subject.timesteps, out / "coverage.png")
    atomic_write_json(out / "coverage.json", {"dataset": str(root), **report})
    return report


__all__ = ["FrameMeasures", "MEASURES", "advice", "capture_check", "capture_report", "dataset_capture_check",
           "eye_openness", "measure_frames", "outside_training", "plot_coverage", "summarize_split", "verdict"]
