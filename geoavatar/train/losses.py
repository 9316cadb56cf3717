"""Training losses of GeoAvatar (paper Sec. 3.3) and GaussianAvatars' scale loss.

    L_rgb   = (1 - lambda) L1 + lambda (1 - SSIM)            lambda = 0.2, SSIM as 3DGS's loss
    L_p     = ReLU(r - tau_p)                                 tau by the face's set (rigid/flexible/mouth)
    L_angle = 1[r > tau_rigid] ReLU(phi - tau_phi)            tau_phi = 0.78 rad
    L_scale = |ReLU(exp(s_local) - 0.6)|                      GaussianAvatars (non-metric variant)
    L       = L_rgb + lambda_reg mean(L_p) + lambda_angle mean(L_angle) + lambda_scale mean(L_scale)

Means are over the Gaussians visible in the frame (GaussianAvatars' visibility filter) when a mask
is given. Why a weighted mean and not the paper's plain sum: see geoavatar/config.py.
Images are channel-last, [H, W, C] or [B, H, W, C], values in [0, 1] (the renderer's layout).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.avatar.aps import BASELINE, FLEXIBLE, MOUTH, RIGID
from geoavatar.avatar.binding import polar_coordinates
from geoavatar.config import LossConfig
from geoavatar.imaging.quality import ssim


# --- image terms ------------------------------------------------------------------------------


def rgb_loss(image: Tensor, target: Tensor, lambda_dssim: float = 0.2) -> tuple[Tensor, Tensor, Tensor]:
    """(L_rgb, L1, D-SSIM) with L_rgb = (1 - lambda) L1 + lambda (1 - SSIM)."""
    l1 = (image - target).abs().mean()
    dssim = 1.0 - ssim(image, target)
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * dssim, l1, dssim


# --- geometric regularisers -------------------------------------------------------------------


def set_thresholds(cfg: LossConfig, device=None) -> Tensor:
    """tau of each set id (RIGID, FLEXIBLE, MOUTH, BASELINE) -> [4]."""
    taus = torch.empty(4, device=device)
    taus[RIGID] = cfg.tau_rigid
    taus[FLEXIBLE] = cfg.tau_flexible
    taus[MOUTH] = cfg.tau_mouth_value
    taus[BASELINE] = cfg.tau_gaussianavatars
    return taus


def _masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    if mask is None:
        return values.mean() if values.numel() else values.sum()
    mask = mask.to(values.device)
    count = mask.sum()
    return (values * mask).sum() / count.clamp_min(1)


def position_loss(r: Tensor, tau: Tensor, mask: Tensor | None = None) -> Tensor:
    """mean ReLU(r - tau): r [N], tau [N] (per-Gaussian threshold), mask [N] bool or None."""
    return _masked_mean(F.relu(r - tau), mask)


def angle_loss(r: Tensor, phi: Tensor, tau_rigid: float, tau_angle: float, mask: Tensor | None = None) -> Tensor:
    """mean 1[r > tau_rigid] ReLU(phi - tau_angle): r, phi [N]."""
    return _masked_mean((r > tau_rigid).to(phi.dtype) * F.relu(phi - tau_angle), mask)


def scale_loss(log_scales: Tensor, threshold: float = 0.6, mask: Tensor | None = None) -> Tensor:
    """GaussianAvatars: mean |ReLU(exp(s) - threshold)| over Gaussians; log_scales [N, 3] (local)."""
    return _masked_mean(F.relu(torch.exp(log_scales) - threshold).norm(dim=-1), mask)


def regularization_losses(
    local_means: Tensor,  # [N, 3]
    log_scales: Tensor,  # [N, 3]
    binding: Tensor,  # [N]
    face_sets: Tensor,  # [F] set id per face (geoavatar.avatar.aps.face_set_ids)
    cfg: LossConfig,
    visible: Tensor | None = None,  # [N] bool; None: every Gaussian
) -> dict[str, Tensor]:
    """Weighted regularisers {"reg", "angle", "scale"} (already multiplied by their lambdas)."""
    mask = visible if cfg.visible_only else None
    r, phi = polar_coordinates(local_means, two_sided=cfg.angle_two_sided)
    tau = set_thresholds(cfg, local_means.device)[face_sets.to(local_means.device)[binding]]  # [N]
    out = {"reg": cfg.lambda_reg * position_loss(r, tau, mask)}
    if cfg.use_angle:
        out["angle"] = cfg.lambda_angle * angle_loss(r, phi, cfg.tau_rigid, cfg.tau_angle, mask)
    if cfg.lambda_scale:
        out["scale"] = cfg.lambda_scale * scale_loss(log_scales, cfg.threshold_scale, mask)
    return out


def avatar_loss(
    image: Tensor,  # [H, W, 3] or [B, H, W, 3] rendered
    target: Tensor,  # same shape, ground truth
    local_means: Tensor,  # [N, 3]
    log_scales: Tensor,  # [N, 3]
    binding: Tensor,  # [N]
    face_sets: Tensor,  # [F]
    cfg: LossConfig,
    visible: Tensor | None = None,  # [N] bool
) -> dict[str, Tensor]:
    """Every term by name ("l1", "dssim" unweighted for logging; "rgb", "reg", "angle", "scale") and "total"."""
    rgb, l1, dssim = rgb_loss(image, target, cfg.lambda_dssim)
    terms = {"rgb": rgb, **regularization_losses(local_means, log_scales, binding, face_sets, cfg, visible)}
    total = sum(terms.values())
    return {**terms, "l1": l1.detach(), "dssim": dssim.detach(), "total": total}
