"""Expression transfer that stays inside what the avatar learned: the driver's expression mapped by the statistics of
both sequences, or projected onto the expressions the avatar was trained on.

    learned = transfer_statistics(RunFrames(run), driver_values)        # once per driver
    out.update(statistics_transfer(driver_values, learned))             # 'statistics': expr [T, E], jaw, eyes
    out.update(subspace_projection(relative_values, learned))           # 'subspace': the relative result, projected

animation/transfer.py's driven_params is the one function that turns a driver's parameters into the avatar's; it calls
these for the modes "statistics" and "subspace" (TRANSFER_MODES). The expression keys are expr, jaw_pose and
eyes_pose (EXPRESSION_KEYS; jaw and eyes as axis-angle numbers, fine for the small angles of a face); the head's
rotation, the neck and the translation follow the driver's change from its neutral frame in both modes, as
--relative does.

statistics   Each coefficient standardised by the driver's own mean and spread over its sequence and mapped to
             the avatar's training-set mean and spread:
                 x = mean_avatar + std_avatar * (x_driver - mean_driver) / std_driver.
             A driver who opens the mouth twice as wide as the avatar ever did opens it as wide as the avatar
             did; a coefficient the avatar never moved stays at its training mean. The driver's spread is shrunk
             toward the avatar's with PRIOR_FRAMES frames' weight,
                 std_driver^2 <- (n std_driver^2 + PRIOR_FRAMES std_avatar^2) / (n + PRIOR_FRAMES),
             so that a short sequence (drive's first second) or a coefficient the driver barely moves is not blown
             up to the avatar's whole range.
subspace     Relative transfer, then expr projected onto the principal subspace of the avatar's training expressions
             (centred on their mean, the leading directions holding SUBSPACE_VARIANCE of the variance) with each
             principal coordinate clamped to the range the training frames cover, and jaw and eyes clamped per
             component to their training range: the advice of 3D Gaussian Blendshapes' author (their issue #12) for
             expressions beyond the training set. The avatar is never asked for an expression its training frames
             did not span. (Projecting the statistics result instead lost expression similarity: docs/
             cross_reenactment.md.)

Jaw and eyes per mode: absolute, the driver's rotations; relative, the driver's change from its neutral composed
onto the avatar's neutral (rotation matrices); statistics, the driver's axis-angle numbers standardised and mapped
to the avatar's training statistics per component; subspace, as relative, then clamped to the avatar's training
range (a mouth never opens wider, eyes never turn further, than in some training frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Sequence, get_args

import torch
from torch import Tensor

from geoavatar.errors import OptionError

if TYPE_CHECKING:
    from geoavatar.train.run_frames import RunFrames

TransferMode = Literal["absolute", "relative", "statistics", "subspace"]
TRANSFER_MODES: tuple[str, ...] = get_args(TransferMode)
DEFAULT_TRANSFER: TransferMode = "relative"  # no mode beat it across #30's two tables (docs/cross_reenactment.md)
EXPRESSION_KEYS = ("expr", "jaw_pose", "eyes_pose")
PRIOR_FRAMES = 25  # the avatar's spread counts as this many driver frames (one second at 25 fps)
SUBSPACE_VARIANCE = 0.99  # share of the training expressions' variance the kept directions hold
TINY = 1e-8  # a spread below this is no spread


@dataclass(frozen=True)
class ExpressionStatistics:
    """Per-coefficient mean and spread of a sequence's expression keys, and its range."""

    mean: dict[str, Tensor]  # key -> [D_key]
    std: dict[str, Tensor]  # key -> [D_key] (population)
    low: dict[str, Tensor]  # key -> [D_key] minimum over the frames
    high: dict[str, Tensor]  # key -> [D_key] maximum
    frames: int

    def to(self, device: torch.device) -> ExpressionStatistics:
        """The same statistics with every tensor on `device` (a live driver's are fitted on CPU)."""
        def moved(part: dict[str, Tensor]) -> dict[str, Tensor]:
            return {key: value.to(device) for key, value in part.items()}

        return ExpressionStatistics(moved(self.mean), moved(self.std), moved(self.low), moved(self.high), self.frames)


@dataclass(frozen=True)
class ExpressionSubspace:
    """The principal subspace of the avatar's training expressions (expr only) and the range covered along it."""

    basis: Tensor  # [E, K] orthonormal columns
    low: Tensor  # [K] smallest training coordinate along each direction
    high: Tensor  # [K]


@dataclass(frozen=True)
class TransferStatistics:
    """What statistics / subspace transfer need: the avatar's training expressions and the driver's statistics."""

    avatar: ExpressionStatistics
    subspace: ExpressionSubspace
    driver: ExpressionStatistics


def transfer_mode(mode: str | bool) -> TransferMode:
    """A TransferMode from a mode name, or from the old `relative` flag (True: relative, False: absolute)."""
    if isinstance(mode, bool):
        return "relative" if mode else "absolute"
    if mode not in TRANSFER_MODES:
        raise OptionError(f"--transfer must be one of {', '.join(TRANSFER_MODES)}, got {mode!r}")
    return mode  # type: ignore[return-value]


def resolve_transfer(transfer: str | None, relative: bool) -> TransferMode:
    """The mode of a command's --transfer and --relative options (--relative is --transfer relative)."""
    if relative and transfer not in (None, "relative"):
        raise OptionError(f"--relative means --transfer relative; it cannot go with --transfer {transfer}")
    if relative:
        return "relative"
    return transfer_mode(transfer) if transfer is not None else DEFAULT_TRANSFER


def _pad(value: Tensor, width: int) -> Tensor:
    """Zero-pad the last dimension to `width` (expression coefficients of models with fewer modes)."""
    return torch.nn.functional.pad(value, (0, width - value.shape[-1])) if value.shape[-1] < width else value


def expression_statistics(values: dict[str, Tensor], rows: Sequence[int] | None = None) -> ExpressionStatistics:
    """Statistics of EXPRESSION_KEYS over the rows `rows` (default: all) of per-frame values [T, ...]."""
    picked = {key: values[key] if rows is None else values[key][torch.as_tensor(list(rows), dtype=torch.long,
                                                                                device=values[key].device)]
              for key in EXPRESSION_KEYS}
    count = int(picked["expr"].shape[0])
    if count == 0:
        raise ValueError("expression_statistics: no frames")
    stats = {name: {} for name in ("mean", "std", "low", "high")}
    for key, value in picked.items():
        value = value.double()  # [N, D]
        stats["mean"][key], stats["std"][key] = value.mean(0), value.std(0, unbiased=False)
        stats["low"][key], stats["high"][key] = value.min(0).values, value.max(0).values
    return ExpressionStatistics(**stats, frames=count)


def expression_subspace(expr: Tensor, mean: Tensor, variance: float = SUBSPACE_VARIANCE) -> ExpressionSubspace:
    """Principal subspace of training expressions expr [N, E] about `mean` [E] holding `variance` of their variance."""
    centred = expr.double() - mean  # [N, E]
    _, singular, vh = torch.linalg.svd(centred, full_matrices=False)  # vh [min(N, E), E]
    energy = singular.square()
    if float(energy.sum()) <= TINY:  # the avatar never changed its expression: the subspace is its mean
        empty = centred.new_zeros(0)
        return ExpressionSubspace(centred.new_zeros(expr.shape[1], 0), empty, empty)
    share = torch.cumsum(energy, 0) / energy.sum()
    keep = int(torch.searchsorted(share, torch.tensor(variance, dtype=share.dtype, device=share.device)).item()) + 1
    basis = vh[:min(keep, vh.shape[0])].T  # [E, K]
    coordinates = centred @ basis  # [N, K]
    return ExpressionSubspace(basis, coordinates.min(0).values, coordinates.max(0).values)


def avatar_expressions(frames: "RunFrames") -> tuple[ExpressionStatistics, ExpressionSubspace]:
    """The statistics and the expression subspace of a run's training frames (all its frames when it lists none),
    with the parameters it trained with (refined ones where training refined them)."""
    values = frames.values.to_npz()
    train = set(frames.run.info.timesteps.get("train") or frames.timesteps)
    rows = [i for i, t in enumerate(frames.timesteps) if t in train]
    statistics = expression_statistics(values, rows)
    index = torch.as_tensor(rows, dtype=torch.long, device=values["expr"].device)
    return statistics, expression_subspace(values["expr"][index], statistics.mean["expr"])


def transfer_statistics(frames: "RunFrames", driver_values: dict[str, Tensor]) -> TransferStatistics:
    """The avatar's statistics and subspace (avatar_expressions) and the driver's statistics over all its frames."""
    return TransferStatistics(*avatar_expressions(frames), expression_statistics(driver_values))


def _mapped(key: str, driver: Tensor, learned: TransferStatistics) -> Tensor:
    """One key's driver values [T, D] standardised by the driver's statistics, mapped to the avatar's: [T, D']."""
    avatar, source = learned.avatar, learned.driver
    width = max(driver.shape[-1], avatar.mean[key].shape[-1])
    mean_a, std_a = _pad(avatar.mean[key], width), _pad(avatar.std[key], width)
    mean_d, std_d = _pad(source.mean[key], width), _pad(source.std[key], width)
    n = source.frames
    std_d = ((n * std_d.square() + PRIOR_FRAMES * std_a.square()) / (n + PRIOR_FRAMES)).sqrt()
    z = (_pad(driver.double(), width) - mean_d) / std_d.clamp_min(TINY)  # [T, D]
    z = torch.where(std_d > TINY, z, torch.zeros_like(z))
    return mean_a + std_a * z


def _projected(expr: Tensor, learned: TransferStatistics) -> Tensor:
    """expr [T, E] projected onto the avatar's training subspace, its coordinates clamped to the training range."""
    space = learned.subspace
    mean = _pad(learned.avatar.mean["expr"], expr.shape[-1])
    basis = torch.nn.functional.pad(space.basis, (0, 0, 0, expr.shape[-1] - space.basis.shape[0]))  # [E, K]
    coordinates = (expr - mean) @ basis  # [T, K]
    coordinates = torch.maximum(torch.minimum(coordinates, space.high), space.low)
    return mean + coordinates @ basis.T


def _clamped(key: str, value: Tensor, avatar: ExpressionStatistics) -> Tensor:
    return torch.maximum(torch.minimum(value, _pad(avatar.high[key], value.shape[-1])),
                         _pad(avatar.low[key], value.shape[-1]))


def statistics_transfer(driver: dict[str, Tensor], learned: TransferStatistics) -> dict[str, Tensor]:
    """EXPRESSION_KEYS [T, ...] of the driver's values [T, ...] mapped to the avatar's statistics ('statistics')."""
    return {key: _mapped(key, driver[key], learned).to(driver[key].dtype) for key in EXPRESSION_KEYS}


def subspace_projection(values: dict[str, Tensor], learned: TransferStatistics) -> dict[str, Tensor]:
    """EXPRESSION_KEYS [T, ...] of the avatar's values [T, ...] (the relative result) kept inside its training
    expressions: expr projected onto their subspace and clamped, jaw and eyes clamped ('subspace')."""
    dtype = values["expr"].dtype
    out = {"expr": _projected(values["expr"].double(), learned)}
    out.update({key: _clamped(key, values[key].double(), learned.avatar) for key in ("jaw_pose", "eyes_pose")})
    return {key: value.to(dtype) for key, value in out.items()}


__all__ = ["DEFAULT_TRANSFER", "EXPRESSION_KEYS", "ExpressionStatistics", "ExpressionSubspace", "PRIOR_FRAMES",
           "SUBSPACE_VARIANCE", "TRANSFER_MODES", "TransferMode", "TransferStatistics", "avatar_expressions",
           "expression_statistics", "expression_subspace", "resolve_transfer", "statistics_transfer",
           "subspace_projection", "transfer_mode",
           "transfer_statistics"]
