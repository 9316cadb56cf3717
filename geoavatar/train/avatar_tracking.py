"""Tracking against a trained avatar: fit frames' head parameters with the avatar as the appearance model.

    config = AvatarTrackingConfig()                        # 30 Adam steps per frame, every per-frame key
    fitted = track_frames(avatar, head, deformer, frames, config)
    fitted.params                                          # HeadParams [N] (shape / static_offset of the inits)
    fitted.loss_before, fitted.loss_after                  # [N] L1 per frame (NaN: an empty mask, not fitted)

`frames` yields AvatarFrame(params [1, ...], camera, target [H, W, 3], mask [H, W, 1], background [3]).

Why: the trainer refines the parameters of the frames it trains on (train/frame_params.py, GaussianAvatars'
tracking fine-tuning); every other frame (the held-out ones, a new clip of the same person) keeps the
parameters of the photometric tracker, whose appearance model (a per-face albedo under SH lighting,
prep/photometric.py) is far cruder than the avatar, and whose small frame-to-frame error the avatar does
not share: the avatar has absorbed the offset common to the training frames. This fit gives those frames
what training gives its own: parameters in which the avatar explains the image (analysis by synthesis with
the person's own avatar). The avatar and the mouth deformer are frozen; only the frame's rotation,
translation, neck, jaw, eyes and expression move (each frame alone: no temporal term, so nothing of one
frame leaks into another), from its tracked value, by Adam on the training loss's L1 over the image
composited on the background, as training scores it (render.composite_target). T = 0, the inference rule.
A frame with an empty mask (prepare's lost-face frames) is left as tracked.

Measured on generated subject 0 (BENCHMARKS.md, photometric tracking, section 9).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np
import torch
from torch import Tensor

from geoavatar.avatar import render_avatar
from geoavatar.avatar.deform import MouthDeformer
from geoavatar.avatar.model import GaussianAvatar
from geoavatar.head.base import HeadModel
from geoavatar.head.params import FRAME_KEYS, HeadParams
from geoavatar.render.camera import Camera
from geoavatar.render.composite import composite_target


@dataclass
class AvatarTrackingConfig:
    """Per-frame Adam steps and rates (units: rad, m, expression coefficients). On generated subject 0, 30 steps come
    within 0.1 dB of 60, rates 2x higher are no better, and the expression adds 0.24 dB over the pose keys alone
    (BENCHMARKS.md, photometric tracking, section 9)."""

    steps: int = 30
    keys: tuple[str, ...] = FRAME_KEYS  # the per-frame parameters that move
    # start each frame from its tracked value plus the correction the previous frame of the sequence got, when that
    # start renders closer to the image than the tracked value: neighbouring frames share most of their tracker error
    carry: bool = False
    rates: dict[str, float] = field(default_factory=lambda: {
        "rotation": 1e-3, "translation": 2e-4, "neck_pose": 1e-3, "jaw_pose": 1e-3, "eyes_pose": 1e-3, "expr": 1e-2})

    def __post_init__(self):
        unknown = [key for key in self.keys if key not in FRAME_KEYS]
        if unknown or self.steps < 0:
            raise ValueError(f"avatar tracking: keys must be among {', '.join(FRAME_KEYS)} and steps >= 0, got "
                             f"{', '.join(unknown) or self.keys}, {self.steps}")


class AvatarFrame(NamedTuple):
    params: HeadParams  # one frame, per-frame keys [1, ...]: the starting point
    camera: Camera
    image: Tensor  # [H, W, 3] in [0, 1], as stored (not composited)
    mask: Tensor  # [H, W, 1] in [0, 1]
    background: Tensor  # [3]


@dataclass
class AvatarTrackingResult:
    params: HeadParams  # [N] fitted (detached), rows in the order of the frames
    loss_before: np.ndarray  # [N] L1 with the starting parameters (NaN: empty mask, not fitted)
    loss_after: np.ndarray  # [N]


def frozen(module: torch.nn.Module | None) -> None:
    """No gradient for `module`'s parameters (the avatar and the deformer stay as trained)."""
    if module is not None:
        for parameter in module.parameters():
            parameter.requires_grad_(False)


def image_loss(avatar: GaussianAvatar, head: HeadModel, deformer: MouthDeformer | None, params: HeadParams,
               frame: AvatarFrame, target: Tensor) -> Tensor:
    """L1 between the avatar's render of `params` (T = 0, on the frame's background) and `target` [H, W, 3]."""
    rgb = render_avatar(avatar, head, params, frame.camera, None, deformer, frame.background).result.rgb  # [H, W, 3]
    return (rgb - target).abs().mean()


def carried_start(avatar: GaussianAvatar, head: HeadModel, deformer: MouthDeformer | None, frame: AvatarFrame,
                  correction: dict[str, Tensor]) -> tuple[AvatarFrame, float]:
    """(`frame` starting from its tracked parameters plus `correction` (key -> [1, ...], the previous frame's fitted
    minus tracked) when that renders closer to its image, else `frame` as it is; the tracked parameters' L1)."""
    target = composite_target(frame.image, frame.mask, frame.background)  # [H, W, 3]
    carried = frame.params.replace(**{key: getattr(frame.params, key) + value for key, value in correction.items()})
    with torch.no_grad():
        tracked = float(image_loss(avatar, head, deformer, frame.params, frame, target))
        better = float(image_loss(avatar, head, deformer, carried, frame, target)) < tracked
    return (frame._replace(params=carried.detach()) if better else frame), tracked


def track_frame(avatar: GaussianAvatar, head: HeadModel, deformer: MouthDeformer | None, frame: AvatarFrame,
                config: AvatarTrackingConfig) -> tuple[HeadParams, float, float]:
    """One frame's fitted parameters [1, ...] and its L1 before and after (NaN, NaN: empty mask, unchanged).
    `before` is the L1 of `frame.params`, the start."""
    if not bool(frame.mask.sum() > 0):
        return frame.params.detach(), math.nan, math.nan
    frozen(avatar)  # gradients for the frame's parameters only
    frozen(deformer)
    target = composite_target(frame.image, frame.mask, frame.background)  # [H, W, 3]
    values = {key: getattr(frame.params, key).detach().clone().float().requires_grad_(True) for key in config.keys}
    optimizer = torch.optim.Adam([{"params": [values[key]], "lr": config.rates[key]} for key in config.keys])
    before = None  # the first step's loss: its parameters are the start
    for _ in range(config.steps):
        loss = image_loss(avatar, head, deformer, frame.params.replace(**values), frame, target)
        before = float(loss.detach()) if before is None else before
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    if before is None:  # no step
        with torch.no_grad():
            before = float(image_loss(avatar, head, deformer, frame.params, frame, target))
    fitted = frame.params.replace(**{key: value.detach() for key, value in values.items()}).detach()
    with torch.no_grad():
        after = float(image_loss(avatar, head, deformer, fitted, frame, target))
    if after > before:  # Adam overshot (a frame already at its optimum): keep the start
        return frame.params.detach(), before, before
    return fitted, before, after


def track_frames(avatar: GaussianAvatar, head: HeadModel, deformer: MouthDeformer | None, frames: Iterable[AvatarFrame],
                 config: AvatarTrackingConfig = AvatarTrackingConfig(),
                 progress: Callable[[int], None] | None = None) -> AvatarTrackingResult:
    """Fit every frame alone (see the module docstring), in order: with `config.carry`, each from the previous
    frame's correction when it helps; `progress(1)` after each frame. The L1 before is the tracked parameters'."""
    fitted, before, after = [], [], []
    correction = None  # key -> [1, ...]: the previous fitted frame's fitted minus tracked
    with torch.enable_grad():
        for frame in frames:
            start, tracked_loss = frame, None
            if config.carry and correction is not None and bool(frame.mask.sum() > 0):
                start, tracked_loss = carried_start(avatar, head, deformer, frame, correction)
            params, loss_before, loss_after = track_frame(avatar, head, deformer, start, config)
            if tracked_loss is not None:  # report against the tracked start, as without carry
                loss_before = tracked_loss
            if not math.isnan(loss_after):
                correction = {key: (getattr(params, key) - getattr(frame.params, key)).detach() for key in config.keys}
            fitted.append(params)
            before.append(loss_before)
            after.append(loss_after)
            if progress is not None:
                progress(1)
    if not fitted:
        raise ValueError("avatar tracking: no frames")
    stacked = {key: torch.cat([getattr(p, key) for p in fitted]) for key in FRAME_KEYS}  # [N, ...]
    return AvatarTrackingResult(fitted[0].replace(**stacked), np.asarray(before), np.asarray(after))


def dataset_frames(dataset, indices: Iterable[int], device: torch.device | str) -> Iterator[AvatarFrame]:
    """AvatarFrames of a HeadAvatarDataset's items `indices` on `device`, decoded one at a time."""
    from geoavatar.data.dataset import item_camera, item_to

    for index in indices:
        item = item_to(dataset[index], device)
        yield AvatarFrame(HeadParams.from_npz(item["params"]), item_camera(item), item["image"], item["mask"],
                          item["background"])


__all__ = ["AvatarFrame", "AvatarTrackingConfig", "AvatarTrackingResult", "carried_start", "dataset_frames", "frozen",
           "image_loss", "track_frame", "track_frames"]
