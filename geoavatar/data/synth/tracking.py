"""Realistic tracker error added to the ground-truth parameters of a synthetic video.

A monocular face tracker (VHAP, metrical-tracker) is never exact: the head pose wobbles a little
from frame to frame and drifts slowly, the expression and jaw coefficients are biased and noisy,
and the identity fit is slightly off. GeoAvatar's frame-conditioned mouth deformation (the frame
index T in Φ(ψ, Θ, γ(T))) exists to absorb exactly this, so the synthetic data carries it: the
written `flame_param/` = ground truth + error; `flame_param_gt/` holds the exact ground truth.

Each error has a temporally correlated part (white noise through a Gaussian filter with the
time constant `correlation_s`, unit variance, then scaled) and a white per-frame part.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class TrackingNoise:
    """Tracker error model; the defaults are the size of errors of a good monocular tracker."""

    enabled: bool = True
    rotation_deg: float = 1.0  # slow head-rotation error (std, degrees, on each axis)
    rotation_jitter_deg: float = 0.3  # per-frame head-rotation jitter (std, degrees)
    translation_mm: float = 2.0  # slow head-translation error (std, mm, on each axis; depth gets 3x)
    translation_jitter_mm: float = 0.5  # per-frame translation jitter (std, mm)
    expression_sigma: float = 0.12  # slow error on every expression coefficient (std, model units)
    expression_jitter_sigma: float = 0.04  # per-frame expression error (std)
    jaw_rad: float = 0.03  # slow jaw-opening error (std, radians), biased towards under-opening
    jaw_jitter_rad: float = 0.01  # per-frame jaw error (std, radians)
    eyes_rad: float = 0.03  # gaze error (std, radians)
    shape_sigma: float = 0.1  # constant identity-fit error on the shape coefficients used (std)
    correlation_s: float = 0.5  # time constant of the slow parts (seconds)

    def to_dict(self) -> dict:
        return asdict(self)


def _correlated(rng: np.random.Generator, shape: tuple[int, ...], sigma_frames: float) -> np.ndarray:
    """Unit-variance noise [N, ...] correlated along axis 0 by a Gaussian of `sigma_frames` frames."""
    white = rng.standard_normal(shape)
    if shape[0] < 2 or sigma_frames <= 0.0:
        return white
    smooth = gaussian_filter1d(white, sigma=sigma_frames, axis=0, mode="reflect")
    radius = int(4.0 * sigma_frames + 0.5)
    g = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_frames) ** 2)
    g = g / g.sum()
    return smooth / math.sqrt(float((g * g).sum()))  # the filter's gain on white noise


def _perturb_rotation(rotvec: np.ndarray, error: np.ndarray) -> np.ndarray:
    """Compose an axis-angle error [N, 3] with rotations [N, 3] (error applied in the world frame)."""
    return (Rotation.from_rotvec(error) * Rotation.from_rotvec(rotvec)).as_rotvec()


def apply_tracking_noise(
    params: dict[str, np.ndarray],  # ground truth in the FLAME npz layout, per-frame arrays [N, ...]
    noise: TrackingNoise,
    fps: float,
    seed: int,
    num_expr_used: int,  # expression modes the head model has (error goes on these)
    num_shape_used: int,  # identity modes the head model has
) -> dict[str, np.ndarray]:
    """The parameters a tracker would have written: ground truth + error (a new dict; input untouched).

    Per-frame keys: rotation [N,3], neck_pose [N,3], jaw_pose [N,3], eyes_pose [N,6],
    translation [N,3], expr [N,E]; shape [S] is shared by all frames.
    """
    out = {k: np.array(v, copy=True) for k, v in params.items()}
    if not noise.enabled:
        return out
    rng = np.random.default_rng([seed, 0x7A4C])
    n = out["rotation"].shape[0]
    corr = noise.correlation_s * fps
    deg = math.pi / 180.0

    rot_err = deg * (noise.rotation_deg * _correlated(rng, (n, 3), corr)
                     + noise.rotation_jitter_deg * rng.standard_normal((n, 3)))
    out["rotation"] = _perturb_rotation(out["rotation"], rot_err).astype(np.float32)
    # The tracker also splits the head rotation between the neck and the root a little differently.
    neck_err = deg * 0.5 * noise.rotation_deg * _correlated(rng, (n, 3), corr)
    out["neck_pose"] = _perturb_rotation(out["neck_pose"], neck_err).astype(np.float32)

    trans_scale = np.array([1.0, 1.0, 3.0])  # monocular depth is the least certain
    trans_err = 1e-3 * trans_scale * (noise.translation_mm * _correlated(rng, (n, 3), corr)
                                      + noise.translation_jitter_mm * rng.standard_normal((n, 3)))
    out["translation"] = (out["translation"] + trans_err).astype(np.float32)

    e = min(num_expr_used, out["expr"].shape[1])
    expr_err = (noise.expression_sigma * _correlated(rng, (n, e), corr)
                + noise.expression_jitter_sigma * rng.standard_normal((n, e)))
    out["expr"][:, :e] = out["expr"][:, :e] + expr_err

    # Trackers tend to under-open the jaw (the inner lips are hard to see): a negative bias when open.
    jaw_open = out["jaw_pose"][:, 0]
    jaw_err = (noise.jaw_rad * _correlated(rng, (n,), corr) - 0.15 * jaw_open
               + noise.jaw_jitter_rad * rng.standard_normal(n))
    out["jaw_pose"][:, 0] = np.clip(jaw_open + jaw_err, 0.0, None)

    out["eyes_pose"] = out["eyes_pose"] + noise.eyes_rad * _correlated(rng, (n, 6), corr)

    s = min(num_shape_used, out["shape"].shape[-1])
    out["shape"][..., :s] = out["shape"][..., :s] + noise.shape_sigma * rng.standard_normal(s)
    return {k: v.astype(np.float32) for k, v in out.items()}


__all__ = ["TrackingNoise", "apply_tracking_noise"]
