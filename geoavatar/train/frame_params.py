"""Per-frame head-model parameters, optionally refined during training (GaussianAvatars' tracking
fine-tuning: expression, pose and translation of every timestep are learnable tensors).

    frames = FrameParams(subject.params, refine=True)
    params = frames(row)            # HeadParams: per-frame keys [1, ...], shape [S]

Only the rows of training frames ever receive a gradient (the trainer only renders training frames),
so test frames keep their tracked values: Adam leaves a parameter row whose gradient has always been
zero exactly where it is (both moments stay 0). Rows that did get gradients keep drifting a little on
their momentum when other frames are drawn, as in GaussianAvatars where the same dense tensors are
optimised.
"""

from __future__ import annotations

from typing import Mapping

from torch import Tensor, nn

from geoavatar.head.params import HeadParams

# Refined per-timestep keys, grouped by the learning rate they take (config.LearningRates.tracking_*).
REFINED_KEYS: dict[str, tuple[str, ...]] = {
    "expr": ("expr",),
    "pose": ("rotation", "neck_pose", "jaw_pose", "eyes_pose"),
    "translation": ("translation",),
}


class FrameParams(nn.Module):
    """The per-timestep parameters of one subject, [T, ...] per key (row i = subject.timesteps[i])."""

    def __init__(self, params: Mapping[str, Tensor], refine: bool = True):
        super().__init__()
        missing = [k for group in REFINED_KEYS.values() for k in group if k not in params] + (
            [] if "shape" in params else ["shape"]
        )
        if missing:
            raise ValueError(f"FrameParams: the subject's parameters lack {', '.join(missing)}")
        self.refine = bool(refine)
        rows = int(params["expr"].shape[0])
        self.values = nn.ParameterDict()
        for group in REFINED_KEYS.values():
            for key in group:
                value = params[key].detach().float().clone()
                if value.shape[0] != rows:
                    raise ValueError(f"FrameParams: '{key}' has {value.shape[0]} rows, 'expr' has {rows}")
                self.values[key] = nn.Parameter(value, requires_grad=self.refine)  # [T, n]
        self.register_buffer("shape", params["shape"].detach().float().clone())  # [S]
        static = params.get("static_offset")
        self.register_buffer("static_offset", None if static is None else static.detach().float().clone())

    @property
    def num_rows(self) -> int:
        return int(self.values["expr"].shape[0])

    def forward(self, row: int) -> HeadParams:
        """Parameters of one timestep: per-frame keys [1, ...], shape [S], static_offset [1, V, 3] or None."""
        if not 0 <= row < self.num_rows:
            raise IndexError(f"FrameParams: row {row} outside [0, {self.num_rows})")
        return HeadParams(shape=self.shape, static_offset=self.static_offset,
                          **{key: value[row : row + 1] for key, value in self.values.items()})

    def as_dict(self) -> dict[str, Tensor]:
        """Every key as a detached tensor, per-frame keys [T, ...] (FrameParams(as_dict()) rebuilds it)."""
        out = {key: value.detach().clone() for key, value in self.values.items()}
        out["shape"] = self.shape.clone()
        if self.static_offset is not None:
            out["static_offset"] = self.static_offset.clone()
        return out

    def param_groups(self, lr) -> list[dict]:
        """Adam groups (expr / pose / translation) with GaussianAvatars' tracking learning rates."""
        rates = {"expr": lr.tracking_expr, "pose": lr.tracking_pose, "translation": lr.tracking_translation}
        return [
            {"params": [self.values[k] for k in keys], "lr": rates[group], "name": f"tracking_{group}"}
            for group, keys in REFINED_KEYS.items()
        ]


__all__ = ["FrameParams", "REFINED_KEYS"]
