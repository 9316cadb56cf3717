"""A driver's parameters become the avatar's: driven_params, the one function every driving command goes through
(reenact, export --format web --driver and eval --driver through sources/driver.py; drive frame by frame through
sources/live.py).

Parameters of every driver frame (FLAME npz layout; what is taken from whom), by transfer mode (--transfer):

    shape, static_offset        the avatar's (its identity, from the run)
    expr, jaw, eyes, neck,      absolute: the driver's values
      rotation                  relative (--relative): the avatar's neutral + the driver's change from its neutral
                                  expr = expr_avatar_neutral + (expr_driver(t) - expr_driver_neutral)
                                  R    = R_driver(t) R_driver_neutral^T R_avatar_neutral   (each joint,
                                         and the global rotation: rotation matrices, not axis-angles)
                                statistics (animation/expression_transfer.py): expr, jaw and eyes standardised by the
                                  driver's statistics and mapped to the avatar's training-set statistics; neck and
                                  rotation as relative
                                subspace: relative, then expr projected onto the expressions the avatar was trained
                                  on and clamped to their range, jaw and eyes clamped to their training range
    translation                 the avatar's neutral translation + the driver's displacement from its
                                neutral frame (tracked translations depend on each video's camera, so
                                only the motion carries over); with --camera driver the driver's own

"Neutral" is a frame of each sequence (reference_frame): `first`, `mean` (the mean over the sequence's frames, the
avatar's training frames; the mean of axis-angles for rotations, fine for the small angles of a talking head), or a
timestep number. The driver must be tracked with the same head model as the avatar; a model with fewer modes uses the
leading ones (zero-padded).
"""

from __future__ import annotations

import torch
from torch import Tensor

from geoavatar.animation.expression_transfer import (TransferMode, TransferStatistics, statistics_transfer,
                                                     subspace_projection, transfer_mode, transfer_statistics)
from geoavatar.data.subject import Subject
from geoavatar.errors import OptionError
from geoavatar.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from geoavatar.head.params import SUBJECT_KEYS
from geoavatar.train.checkpoint import LoadedRun
from geoavatar.train.run_frames import RunFrames

ROTATION_KEYS = ("rotation", "neck_pose", "jaw_pose", "eyes_pose")  # axis-angle, 3 numbers per joint
TRANSFERRED_KEYS = ("expr", *ROTATION_KEYS, "translation")


def reference_frame(values: dict[str, Tensor], timesteps: list[int], spec: str, mean_over: list[int] | None = None,
                    what: str = "--driver-neutral") -> dict[str, Tensor]:
    """The neutral frame of a sequence: per-frame keys [1, ...] of row `spec` ('first', 'mean', a timestep).

    values: per-timestep keys [T, ...]; mean_over: the timesteps averaged by 'mean' (default: all)."""
    if spec == "first":
        rows = [0]
    elif spec == "mean":
        wanted = set(mean_over if mean_over else timesteps)
        rows = [i for i, t in enumerate(timesteps) if t in wanted]
    else:
        try:
            timestep = int(spec)
        except ValueError:
            raise OptionError(f"{what} must be 'first', 'mean' or a timestep number, got {spec!r}") from None
        if timestep not in timesteps:
            raise OptionError(f"{what} {timestep}: not a timestep of the sequence ({timesteps[0]}..{timesteps[-1]})")
        rows = [timesteps.index(timestep)]
    index = torch.as_tensor(rows, dtype=torch.long, device=values["expr"].device)
    return {key: values[key].index_select(0, index).mean(dim=0, keepdim=True) for key in TRANSFERRED_KEYS}


def _match_width(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """Zero-pad the last dimension of the narrower of a, b (expression coefficients of different lengths)."""
    width = max(a.shape[-1], b.shape[-1])
    pad = lambda x: torch.nn.functional.pad(x, (0, width - x.shape[-1]))  # noqa: E731
    return pad(a), pad(b)


def _compose_relative(driver: Tensor, driver_ref: Tensor, avatar_ref: Tensor) -> Tensor:
    """Axis-angles [T, 3k]: R_driver R_driver_ref^T R_avatar_ref per joint (k joints of 3 numbers)."""
    count = driver.shape[0]
    d = axis_angle_to_matrix(driver.reshape(count, -1, 3))  # [T, k, 3, 3]
    d0 = axis_angle_to_matrix(driver_ref.reshape(1, -1, 3))  # [1, k, 3, 3]
    a0 = axis_angle_to_matrix(avatar_ref.reshape(1, -1, 3))
    return matrix_to_axis_angle(d @ d0.transpose(-1, -2) @ a0).reshape(count, -1)


def driven_params(
    identity: dict[str, Tensor],  # shape [S], static_offset [1, V, 3] (optional): the avatar's
    avatar_ref: dict[str, Tensor],  # the avatar's neutral frame, per-frame keys [1, ...]
    driver: dict[str, Tensor],  # the driver's per-timestep keys [T, ...]
    driver_ref: dict[str, Tensor],  # the driver's neutral frame [1, ...]
    mode: TransferMode | bool = "absolute",  # a bool is the old `relative` flag
    driver_translation: bool = False,  # keep the driver's absolute translation (--camera driver)
    learned: TransferStatistics | None = None,  # for 'statistics' / 'subspace': transfer_statistics(...)
) -> dict[str, Tensor]:
    """Per-frame parameters [T, ...] of the avatar driven by `driver` in transfer `mode` (rules in the module
    docstring and in animation/expression_transfer.py)."""
    mode = transfer_mode(mode)
    if mode in ("statistics", "subspace") and learned is None:
        raise ValueError(f"driven_params: transfer {mode!r} needs the statistics "
                         "(expression_transfer.transfer_statistics)")
    out: dict[str, Tensor] = {}
    driver_expr, ref_expr = _match_width(driver["expr"], driver_ref["expr"])
    if mode == "absolute":
        out["expr"] = driver["expr"].clone()
        for key in ROTATION_KEYS:
            out[key] = driver[key].clone()
    else:
        avatar_expr, delta = _match_width(avatar_ref["expr"], driver_expr - ref_expr)
        out["expr"] = avatar_expr + delta  # [T, E]
        # every joint in one composition (per joint the same arithmetic; one call, not four: drive poses per frame)
        stacked = [torch.cat([values[key] for key in ROTATION_KEYS], -1) for values in (driver, driver_ref, avatar_ref)]
        composed = _compose_relative(*stacked)  # [T, 15]
        widths = [driver[key].shape[-1] for key in ROTATION_KEYS]
        out.update((key, value.contiguous()) for key, value in zip(ROTATION_KEYS, torch.split(composed, widths, dim=-1)))
    if mode == "statistics":
        out.update(statistics_transfer(driver, learned))  # expr, jaw, eyes from the two sequences' statistics
    elif mode == "subspace":
        out.update(subspace_projection(out, learned))  # the relative result kept inside the training expressions
    if driver_translation:
        out["translation"] = driver["translation"].clone()
    else:
        out["translation"] = avatar_ref["translation"] + (driver["translation"] - driver_ref["translation"])
    out.update({key: value for key, value in identity.items() if key in SUBJECT_KEYS})
    return out


def subject_params(run: LoadedRun, frames: RunFrames, subject: Subject, mode: TransferMode | bool = "absolute",
                   driver_neutral: str = "first", avatar_neutral: str = "first",
                   driver_translation: bool = False) -> dict[str, Tensor]:
    """driven_params for every timestep of an opened driver, with the neutral frames of the module docstring and,
    for statistics / subspace transfer, the two sequences' statistics."""
    driver_values = {k: v.to(frames.device) for k, v in subject.params.items()}
    driver_ref = reference_frame(driver_values, list(subject.timesteps), driver_neutral, what="--driver-neutral")
    avatar_ref = reference_frame(frames.values.to_npz(), frames.timesteps, avatar_neutral,
                                 mean_over=run.info.timesteps.get("train"), what="--avatar-neutral")
    learned = transfer_statistics(frames, driver_values) if transfer_mode(mode) in ("statistics", "subspace") else None
    return driven_params(frames.identity(), avatar_ref, driver_values, driver_ref, mode, driver_translation, learned)


__all__ = ["ROTATION_KEYS", "TRANSFERRED_KEYS", "driven_params", "reference_frame", "subject_params"]
