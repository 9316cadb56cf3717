"""HeadParams: the parameters that pose a head model, typed, in the FLAME npz layout of VHAP /
GaussianAvatars (the layout datasets and checkpoints store).

    params = HeadParams.from_npz(subject.params)     # a batch: per-frame keys [T, ...]
    one = params.frame(i)                            # frame i: per-frame keys [1, ...], shape and
                                                     # static_offset unchanged (they belong to the subject)
    head.forward_params(one.to(device)).vertices     # [1, V, 3]
    npz = one.to_npz()                               # back to the dict layout

Per-frame keys: expr [B, E], rotation / neck_pose / jaw_pose / translation [B, 3], eyes_pose [B, 6]
(axis-angle; eyes: left then right). Subject keys, the same for every frame: shape [S] and
static_offset [1, V, 3] or None. A model with fewer modes uses the leading entries.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Mapping

import torch
from torch import Tensor

FRAME_KEYS: tuple[str, ...] = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
SUBJECT_KEYS: tuple[str, ...] = ("shape", "static_offset")  # the same for every frame of a subject


@dataclass(frozen=True)
class HeadParams:
    """One frame ([1, ...]) or a batch ([B, ...]) of head parameters; see the module docstring."""

    shape: Tensor  # [S]
    expr: Tensor  # [B, E]
    rotation: Tensor  # [B, 3]
    neck_pose: Tensor  # [B, 3]
    jaw_pose: Tensor  # [B, 3]
    eyes_pose: Tensor  # [B, 6]
    translation: Tensor  # [B, 3]
    static_offset: Tensor | None = None  # [1, V, 3]

    @classmethod
    def from_npz(cls, params: Mapping[str, Tensor]) -> "HeadParams":
        """From a dict in the npz layout (extra keys such as dynamic_offset or eyelids are left out)."""
        missing = [key for key in (*FRAME_KEYS, "shape") if key not in params]
        if missing:
            raise KeyError(f"head parameters lack {', '.join(missing)} (have: {', '.join(sorted(params))})")
        return cls(**{key: params[key] for key in (*FRAME_KEYS, "shape")}, static_offset=params.get("static_offset"))

    def to_npz(self) -> dict[str, Tensor]:
        """The dict layout (static_offset only when present)."""
        out = {field.name: getattr(self, field.name) for field in fields(self)}
        if out["static_offset"] is None:
            del out["static_offset"]
        return out

    @property
    def batch(self) -> int:
        return int(self.rotation.shape[0])

    @property
    def device(self) -> torch.device:
        return self.rotation.device

    def frame(self, index: int) -> "HeadParams":
        """Frame `index` of a batch as a batch of one: per-frame keys [1, ...]; shape and static_offset kept."""
        if not -self.batch <= index < self.batch:
            raise IndexError(f"HeadParams: frame {index} outside a batch of {self.batch}")
        return self.rows(slice(index, index + 1) if index != -1 else slice(-1, None))

    def rows(self, index: "Tensor | slice") -> "HeadParams":
        """The frames `index` selects (a slice, or a tensor of row ids [K]) as a batch; shape and static_offset kept."""
        return replace(self, **{key: getattr(self, key)[index] for key in FRAME_KEYS})

    def to(self, device: torch.device | str) -> "HeadParams":
        return self.map(lambda value: value.to(device))

    def detach(self) -> "HeadParams":
        return self.map(Tensor.detach)

    def map(self, function) -> "HeadParams":
        """`function` applied to every tensor (static_offset None stays None)."""
        return HeadParams(**{field.name: None if getattr(self, field.name) is None else function(getattr(self, field.name))
                             for field in fields(self)})

    def replace(self, **changes: Tensor | None) -> "HeadParams":
        return replace(self, **changes)


def npz_frame(params: Mapping[str, Tensor], index: int) -> dict[str, Tensor]:
    """Frame `index` of a dict in the npz layout, extras included (dynamic_offset, eyelids: per-frame):
    every key [T, ...] -> [1, ...] except the subject keys, kept whole (HeadParams.frame's rule)."""
    row = slice(index, index + 1) if index != -1 else slice(-1, None)
    return {key: (value if key in SUBJECT_KEYS else value[row]) for key, value in params.items()}


def as_head_params(params: "HeadParams | Mapping[str, Tensor]") -> HeadParams:
    """`params` as HeadParams: the typed value unchanged, a dict in the npz layout converted."""
    return params if isinstance(params, HeadParams) else HeadParams.from_npz(params)


__all__ = ["FRAME_KEYS", "HeadParams", "SUBJECT_KEYS", "as_head_params", "npz_frame"]
