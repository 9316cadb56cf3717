"""Train / val / test splits over the timesteps (frames) of one monocular video.

Protocol (INSTA, followed by SplattingAvatar, FlashAvatar and the GeoAvatar paper): the LAST
`test_frames` = 350 frames of the video are the test set; training uses the frames before them.
The split is by timestep, so with several cameras every view of a test timestep is a test frame.

Rules, in order:

1. `test_frames=None` (the default) and the dataset ships explicit `transforms_{train,val,test}.json`
   (VHAP, GaussianAvatars, our writer): honour those files. VHAP's own export puts the last 30 % of
   timesteps in its test file. Pass `--test-frames N` to re-split with the rule below instead.
2. Otherwise hold out the last `test_frames` timesteps (350 when None). A video too short for that
   (test frames would be more than half of it, i.e. fewer than 2 x test_frames frames) holds out its
   last 25 % (`short_video_fraction`, rounded up, at least 1) instead and says so with
   `warnings.warn` (a `ShortVideoWarning`; pytest can catch it, the CLI prints it once).
   `test_frames=0` means no test set: every frame trains.
3. Validation: the frames of a non-empty `transforms_val.json` when rule 1 applies, else
   `val_frames` timesteps spread evenly over the TRAINING timesteps. Validation frames are training
   frames (as in VHAP's monocular export, whose val file shares the training timesteps): they serve
   progress images during training, never metrics. Test frames never enter train or val.

Training and test timesteps are always disjoint; explicit files that overlap raise DatasetError.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np

from geoavatar.data.errors import DatasetError
from geoavatar.errors import OptionError

SplitName = Literal["train", "val", "test", "all"]
SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test", "all")

# INSTA protocol: the last 350 frames of each video are the test set.
DEFAULT_TEST_FRAMES = 350


class ShortVideoWarning(UserWarning):
    """The video is too short to hold out `test_frames` frames; a fraction was held out instead."""


@dataclass
class SplitConfig:
    """How frames are divided into train / val / test."""

    test_frames: int | None = None
    """Hold out the last N frames as the test set (INSTA protocol: 350). None: use the dataset's own
    transforms_{train,val,test}.json when it has them, else 350."""
    val_frames: int = 4
    """Training frames, spread evenly, that serve as the validation set (progress images)."""
    short_video_fraction: float = 0.25
    """Videos with fewer than 2 x test_frames frames hold out this fraction of their end instead."""


@dataclass(frozen=True)
class Split:
    """Timesteps of each split, sorted ascending."""

    train: tuple[int, ...]
    val: tuple[int, ...]
    test: tuple[int, ...]
    source: str  # "files" (explicit transforms_*.json) or "rule" (last-N protocol)

    def timesteps(self, name: str) -> tuple[int, ...]:
        if name == "all":
            return tuple(sorted(set(self.train) | set(self.test)))
        if name not in ("train", "val", "test"):
            raise ValueError(f"unknown split '{name}'; choose one of {', '.join(SPLIT_NAMES)}")
        return getattr(self, name)


@dataclass(frozen=True)
class ExplicitSplit:
    """The timesteps listed by a dataset's own transforms_{train,val,test}.json."""

    train: tuple[int, ...]
    val: tuple[int, ...]
    test: tuple[int, ...]


def split_timesteps(
    timesteps: Sequence[int],
    config: SplitConfig | None = None,
    explicit: ExplicitSplit | None = None,
    source: str = "dataset",
) -> Split:
    """Divide `timesteps` (any order, unique) into train / val / test following the module's rules.

    `source` names the dataset in warnings and errors.
    """
    config = config or SplitConfig()
    ordered = sorted(set(int(t) for t in timesteps))
    if len(ordered) != len(timesteps):
        raise DatasetError(f"{source}: timesteps are not unique")
    if config.val_frames < 0:
        raise ValueError(f"--val-frames must be >= 0, got {config.val_frames}")
    if not 0.0 < config.short_video_fraction < 1.0:
        raise ValueError(f"short_video_fraction must be in (0, 1), got {config.short_video_fraction}")

    if config.test_frames is None and explicit is not None:
        return _from_explicit(ordered, explicit, config, source)

    test_frames = DEFAULT_TEST_FRAMES if config.test_frames is None else config.test_frames
    if test_frames < 0:
        raise ValueError(f"--test-frames must be >= 0, got {test_frames}")
    count = len(ordered)
    if test_frames > 0 and count < 2:
        raise DatasetError(f"{source}: {count} frame(s) cannot be split into training and test frames")
    if 2 * test_frames > count:
        held_out = min(count - 1, max(1, math.ceil(count * config.short_video_fraction)))
        warnings.warn(
            f"{source}: {count} frames are too few to hold out the last {test_frames} as the test set "
            f"(INSTA protocol); holding out the last {held_out} frames "
            f"({config.short_video_fraction:.0%}) instead. Pass --test-frames to choose.",
            ShortVideoWarning,
            stacklevel=2,
        )
        test_frames = held_out
    cut = count - test_frames
    train, test = tuple(ordered[:cut]), tuple(ordered[cut:])
    return Split(train=train, val=_spread(train, config.val_frames), test=test, source="rule")


def _from_explicit(ordered: list[int], explicit: ExplicitSplit, config: SplitConfig, source: str) -> Split:
    train, test = tuple(sorted(set(explicit.train))), tuple(sorted(set(explicit.test)))
    leaked = sorted(set(train) & set(test))
    if leaked:
        raise DatasetError(
            f"{source}: transforms_train.json and transforms_test.json share {len(leaked)} timestep(s) "
            f"(first: {leaked[0]}); training frames must not leak into the test split. "
            f"Pass --test-frames N to re-split by the last-N rule."
        )
    val_leak = sorted(set(explicit.val) & set(test))
    if val_leak:
        raise DatasetError(
            f"{source}: transforms_val.json and transforms_test.json share timestep {val_leak[0]}; "
            f"pass --test-frames N to re-split by the last-N rule."
        )
    known = set(ordered)
    unknown = sorted((set(train) | set(test) | set(explicit.val)) - known)
    if unknown:
        raise DatasetError(f"{source}: the split files name timestep {unknown[0]}, which has no frame")
    val = tuple(sorted(set(explicit.val))) or _spread(train, config.val_frames)
    return Split(train=train, val=val, test=test, source="files")


def _spread(timesteps: tuple[int, ...], count: int) -> tuple[int, ...]:
    """`count` timesteps spread evenly over `timesteps` (first and last included), fewer if short."""
    if count <= 0 or not timesteps:
        return ()
    if count >= len(timesteps):
        return timesteps
    if count == 1:
        return (timesteps[len(timesteps) // 2],)
    picks = sorted({round(i * (len(timesteps) - 1) / (count - 1)) for i in range(count)})
    return tuple(timesteps[i] for i in picks)


def evenly_spaced(count: int, limit: int | None) -> list[int]:
    """`limit` indices spread evenly over range(count) (all of them when limit is None or >= count):
    the frames of a split that `--max-frames` keeps (eval and the rendering commands)."""
    if limit is not None and limit <= 0:
        raise OptionError(f"--max-frames must be positive, got {limit}")
    if limit is None or limit >= count:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, limit)})


__all__ = [
    "evenly_spaced",
    "DEFAULT_TEST_FRAMES", "SPLIT_NAMES", "ExplicitSplit", "ShortVideoWarning", "Split", "SplitConfig",
    "split_timesteps",
]
