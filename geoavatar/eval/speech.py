"""How well a voice model makes the avatar speak, on the held-out segment driven by its own sound (`geoavatar eval
RUN --speech`), against the segment's tracked parameters and against three baselines.

    result = evaluate_speech(run, voice)                  # SpeechResult: scores of the voice model and the baselines
    write_speech_report(result, RUN/eval/speech)          # metrics.json + metrics.md

Scores (head model's canonical frame: the head pose at zero, identity fixed; face.FaceProbe):
    lip_vertex_error       FaceFormer's LVE: per frame the largest squared distance over the lip vertices between
                           predicted and tracked, mean over frames (m^2)
    mouth_open_correlation Pearson r of the lips' opening (inner lip rings), predicted against tracked
    lag_ms                 the shift of the predicted opening (-300..+300 ms) that maximises that r; positive: the
                           predicted mouth moves later than the tracked one
    upper_face_dynamics    FaceFormer / CodeTalker's FDD: per upper-face vertex the standard deviation over time of
                           its squared displacement from the neutral face, averaged over the vertices, tracked minus
                           predicted (m^2; near 0: the brows and eyelids move as much as tracked)
    psnr, lpips, mouth_psnr  the held-out frames rendered with the tracked head pose, gaze and T = 0 and the
                           predicted expression and jaw, against the ground-truth pictures; `tracked` gives the same
                           for the tracked parameters (40 frames spread over the segment by default: five renders
                           and LPIPS each; the face scores use every frame)
Baselines, scored the same way: mean_face (the training frames' mean expression, the jaw at rest), nearest (the
training frame whose sound window, as the voice model hears it, is nearest) and linear (ridge regression from
+-120 ms of log-mel and MFCC frames to the parameters, its strength chosen on the last tenth of the training frames).
Everything learned here (nearest, linear) sees the training frames only; the held-out sound is normalised by its own
statistics, as a new recording is (or, for a voice hearing the video's loudness, by the training sound's: voice and
baselines alike).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from geoavatar.io.atomic import atomic_write_json, atomic_write_text
from geoavatar.sound.features import mfcc, power_frames
from geoavatar.voice.face import FaceProbe
from geoavatar.voice.inputs import SpeechStats, log_mel_torch, normalise, speech_stats, windows
from geoavatar.voice.model import SpokenFace, loudness_tag

REPORT_FORMAT = "geoavatar-eval-speech"
LAG_MS = 300.0
LINEAR_CONTEXT = 12  # feature frames each side: +-120 ms
RIDGE_GRID = (1e-1, 1.0, 10.0, 100.0, 1000.0)
FACE_KEYS = ("lip_vertex_error", "mouth_open_correlation", "lag_ms", "upper_face_dynamics")
PICTURE_KEYS = ("psnr", "lpips", "mouth_psnr")


def pearson(a: np.ndarray, b: np.ndarray) -> float | None:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) < 3 or a.std() < 1e-12 or b.std() < 1e-12:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def best_lag(predicted: np.ndarray, tracked: np.ndarray, fps: float, limit_ms: float = LAG_MS) -> tuple[float | None,
                                                                                                        float | None]:
    """(lag in ms, r at that lag): predicted[t + k] against tracked[t] for |k| frames within limit_ms."""
    best = (None, None)
    frames = int(limit_ms / 1000.0 * fps)
    for k in range(-frames, frames + 1):
        a = predicted[max(k, 0):len(predicted) + min(k, 0)]
        b = tracked[max(-k, 0):len(tracked) + min(-k, 0)]
        r = pearson(a, b)
        if r is not None and (best[1] is None or r > best[1]):
            best = (1000.0 * k / fps, r)
    return best


def lip_vertex_error(predicted: torch.Tensor, reference: torch.Tensor) -> float:
    """FaceFormer's LVE (m^2) of lip vertices [N, K, 3]: per frame the largest squared distance, mean over frames."""
    return float(((predicted - reference) ** 2).sum(-1).max(-1).values.mean())


def face_scores(probe: FaceProbe, predicted: SpokenFace, tracked: SpokenFace, fps: float) -> dict[str, float | None]:
    """FACE_KEYS of predicted against tracked faces [N]."""
    tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        lips_p = probe.lips(tensor(predicted.expr), tensor(predicted.jaw))
        lips_t = probe.lips(tensor(tracked.expr), tensor(tracked.jaw))
        lve = lip_vertex_error(lips_p, lips_t)
        open_p = probe.opening(tensor(predicted.expr), tensor(predicted.jaw)).numpy()
        open_t = probe.opening(tensor(tracked.expr), tensor(tracked.jaw)).numpy()
        neutral = probe.upper(torch.zeros(1, tracked.expr.shape[1]), torch.zeros(1, 3))
        dynamics = [float(((probe.upper(tensor(f.expr), tensor(f.jaw)) - neutral) ** 2).sum(-1).std(0).mean())
                    for f in (tracked, predicted)]
    lag, _ = best_lag(open_p, open_t, fps)
    return {"lip_vertex_error": lve, "mouth_open_correlation": pearson(open_p, open_t), "lag_ms": lag,
            "upper_face_dynamics": dynamics[0] - dynamics[1]}


# --- baselines -------------------------------------------------------------------------------------


def _stack(face: SpokenFace, expr_dims: int) -> np.ndarray:
    return np.concatenate([face.expr[:, :expr_dims], face.jaw], axis=1)


def _face(values: np.ndarray, expr_dims: int, expr_width: int) -> SpokenFace:
    expr = np.zeros((len(values), expr_width), np.float32)
    expr[:, :expr_dims] = values[:, :expr_dims]
    return SpokenFace(expr, values[:, expr_dims:].astype(np.float32))


def linear_features(mel: torch.Tensor, centres: np.ndarray) -> np.ndarray:
    """[N, (2C + 1) * (M + 13)]: log-mel and MFCC frames within +-LINEAR_CONTEXT of each centre, flattened."""
    frames = torch.cat([mel, torch.from_numpy(mfcc(mel.numpy()))], dim=1)
    picked = windows(frames, torch.from_numpy(centres), LINEAR_CONTEXT, LINEAR_CONTEXT)  # [N, M', W]
    return picked.reshape(len(centres), -1).numpy().astype(np.float64)


def ridge_fit(x: np.ndarray, y: np.ndarray, held: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(weights [X, Y], x mean, y mean, alpha): ridge regression, alpha chosen on the last `held` rows, then refitted
    on all."""
    def fit(xs, ys, alpha):
        mx, my = xs.mean(0), ys.mean(0)
        xc = xs - mx
        w = np.linalg.solve(xc.T @ xc + alpha * len(xs) * np.eye(xs.shape[1]), xc.T @ (ys - my))
        return w, mx, my

    best = None
    for alpha in RIDGE_GRID:
        w, mx, my = fit(x[:-held], y[:-held], alpha)
        error = float((((x[-held:] - mx) @ w + my - y[-held:]) ** 2).mean())
        if best is None or error < best[0]:
            best = (error, alpha)
    w, mx, my = fit(x, y, best[1])
    return w, mx, my, best[1]


@dataclass
class SpeechInputs:
    """The training and held-out frames of a run with their sound, as the baselines and the voice model hear them."""

    train_targets: np.ndarray  # [N, D] expression (expr_dims) and jaw of the training frames
    train_mel: torch.Tensor  # [F, M] normalised log-mel of the training sound (cut at the segment's start)
    train_centres: np.ndarray  # [N]
    test_mel: torch.Tensor  # [F', M] normalised log-mel of the held-out sound
    test_centres: np.ndarray  # [N']
    expr_dims: int
    expr_width: int
    test_level: float = 0.0  # the held-out sound's speech level against the training sound's (log10 units)


def baseline_faces(inputs: SpeechInputs, past: int, ahead: int) -> dict[str, SpokenFace]:
    """The three baselines' faces of the held-out frames (module docstring)."""
    y, dims, width = inputs.train_targets, inputs.expr_dims, inputs.expr_width
    count = len(inputs.test_centres)
    rest = y.mean(0).copy()
    rest[dims:] = 0.0
    faces = {"mean_face": _face(np.repeat(rest[None], count, 0), dims, width)}
    train_w = windows(inputs.train_mel, torch.from_numpy(inputs.train_centres), past, ahead).reshape(len(y), -1)
    test_w = windows(inputs.test_mel, torch.from_numpy(inputs.test_centres), past, ahead).reshape(count, -1)
    nearest = torch.cdist(test_w, train_w).argmin(1).numpy()
    faces["nearest"] = _face(y[nearest], dims, width)
    x_train = linear_features(inputs.train_mel, inputs.train_centres)
    w, mx, my, _ = ridge_fit(x_train, y, max(1, len(y) // 10))
    faces["linear"] = _face((linear_features(inputs.test_mel, inputs.test_centres) - mx) @ w + my, dims, width)
    return faces


def normalised_mel(sound, stats: SpeechStats | None = None) -> torch.Tensor:
    """[F, M] a sound's log-mel frames normalised by `stats` (None: its own speech statistics)."""
    mel = log_mel_torch(torch.from_numpy(power_frames(sound)))
    return normalise(mel, stats or speech_stats(mel))


# --- the report ------------------------------------------------------------------------------------


@dataclass
class SpeechResult:
    run_dir: Path
    label: str
    frames: int  # held-out frames scored
    fps: float
    scores: dict[str, dict[str, float | None]]  # "voice" / "tracked" / baselines -> metric -> value
    settings: dict = field(default_factory=dict)
    seconds: float = 0.0


def speech_dir(run_dir: str | Path, loudness: str = "own", copy: str | None = None) -> Path:
    """RUN/eval/speech; RUN/eval/speech@COPY against a copy COPY of the dataset (eval --data), and @video-loudness
    after it for a voice hearing the video's loudness, so no report overwrites another's."""
    name = "speech" + (f"@{copy}" if copy else "") + loudness_tag(loudness)
    return Path(run_dir) / "eval" / name


def _cell(value, key: str) -> str:
    if value is None:
        return "–"
    if key in ("lip_vertex_error", "upper_face_dynamics"):
        return f"{value:.2e}"
    if key == "lag_ms":
        return f"{value:+.0f}"
    return f"{value:.3f}" if key in ("mouth_open_correlation", "lpips") else f"{value:.2f}"


def speech_table(scores: dict[str, dict]) -> str:
    keys = FACE_KEYS + PICTURE_KEYS
    header = "| | LVE (m²) | mouth-open r | lag (ms) | FDD (m²) | PSNR | LPIPS | mouth PSNR |"
    lines = [header, "|" + "---|" * (len(keys) + 1)]
    for name, row in scores.items():
        lines.append(f"| {name} | " + " | ".join(_cell(row.get(k), k) for k in keys) + " |")
    return "\n".join(lines) + "\n"


def write_speech_report(result: SpeechResult, folder: Path) -> dict[str, Path]:
    folder = Path(folder)
    payload = {"format": REPORT_FORMAT, "version": 1, "run": str(result.run_dir), "label": result.label,
               "frames": result.frames, "fps": result.fps, "seconds": round(result.seconds, 1),
               **result.scores.get("voice", {}), "baselines": {k: v for k, v in result.scores.items()
                                                              if k not in ("voice", "tracked")},
               "tracked": result.scores.get("tracked", {}), "settings": result.settings,
               "units": {"lip_vertex_error": "m^2", "upper_face_dynamics": "m^2", "lag_ms": "ms"}}
    pictures = result.settings.get("picture_frames")
    reference = result.settings.get("face_scores_reference")  # said when not simply every frame's row
    reference = None if reference == "every held-out frame's row" else reference
    markdown = (f"# Speech-driven held-out frames: {result.label}\n\n{result.frames} held-out frames at "
                f"{result.fps:g} fps, driven by their own sound (never heard in training)"
                + (f"; PSNR, LPIPS and mouth PSNR over {pictures} of them, spread evenly" if pictures else "")
                + ".\n\n"
                + speech_table(result.scores)
                + "\nvoice: the voice model; tracked: the held-out frames' tracked parameters (the reference the face "
                  "scores compare with; its pictures are the avatar's best), from "
                + str(result.settings.get("test_params", "the dataset"))
                + (f"; the face scores against {reference}" if reference else "")
                + ". Baselines: mean_face, nearest, linear (geoavatar/eval/speech.py).\n")
    markdown_path = atomic_write_text(folder / "metrics.md", markdown)  # the json last: with it, the report is whole
    return {"json": atomic_write_json(folder / "metrics.json", payload), "markdown": markdown_path}


__all__ = ["FACE_KEYS", "PICTURE_KEYS", "SpeechInputs", "SpeechResult", "baseline_faces", "best_lag", "face_scores",
           "linear_features", "lip_vertex_error", "normalised_mel", "pearson", "ridge_fit", "speech_dir",
           "speech_table", "write_speech_report"]
