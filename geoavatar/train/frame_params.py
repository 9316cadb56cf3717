"""Per-frame head-model parameters, optionally refined during training (as GaussianAvatars' tracking
fine-tuning: expression, pose and translation of every timestep are learnable tensors), by RowAdam.

    frames = FrameParams(subject.params, refine=True)
    params = frames(row)            # HeadParams: per-frame keys [1, ...], shape [S]
    optimizer = RowAdam(frames.param_groups(config.lr), lr=0.0)

Only the rows of training frames ever receive a gradient (the trainer only renders training frames),
so test frames keep their tracked values. RowAdam (ours, issue #27) moves a row only on the steps that
drew its frame, one Adam step per visit; GaussianAvatars' torch Adam over the dense table kept moving
every row on its momentum between visits, which is why its rates had to be tiny.
"""

from __future__ import annotations

from typing import Mapping

import torch
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
        """Optimiser groups (expr / pose / translation) with the tracking learning rates (config.LearningRates)."""
        rates = {"expr": lr.tracking_expr, "pose": lr.tracking_pose, "translation": lr.tracking_translation}
        return [
            {"params": [self.values[k] for k in keys], "lr": rates[group], "name": f"tracking_{group}"}
            for group, keys in REFINED_KEYS.items()
        ]


class RowAdam(torch.optim.Optimizer):
    """Adam over the rows of [T, n] tensors, each row with its own moments and step count, updated only on the
    steps whose gradient reaches it (a row of zeros is no visit): training's refinement of the per-frame
    parameters (ours, issue #27).

    Why not torch's Adam over the table (GaussianAvatars): the trainer draws one frame per step, so a frame's row
    gets a gradient once every ~T steps and zeros in between. Dense Adam keeps moving a row on its stale momentum
    for the ~10 steps after each visit and divides by a second moment averaged over the zeros, so a visit moves a
    row by ~30x the learning rate along one noisy gradient: GaussianAvatars' tiny rates (1e-5 rad) keep that
    harmless and the refinement inert (0.09 mm over a run), and rates large enough to matter make it a random walk
    (d3: training frames 22.6 dB, held-out 15.8, docs/REJECTED.md). Here a visit is one Adam step of that row alone
    (the first moves it by exactly the learning rate), so the rates mean "per visit", as in the per-frame fit against
    the avatar (train/avatar_tracking.py, whose rates they are), and a row that was not drawn stays where it is.
    Given a torch Adam state it starts fresh per-row moments (a run trained with torch's Adam resumes with torch's
    Adam, train/state.tracking_optimizer)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for param in group["params"]:
                if param.grad is None:
                    continue
                grad = param.grad.reshape(param.shape[0], -1)  # [T, n]
                rows = grad.ne(0).any(dim=1).nonzero().squeeze(1)  # [R] visited rows
                if rows.numel() == 0:
                    continue
                state = self.state[param]
                if "row_steps" not in state:  # first visit, or a torch Adam state of an older run
                    state["exp_avg"] = torch.zeros_like(grad)  # [T, n]
                    state["exp_avg_sq"] = torch.zeros_like(grad)  # [T, n]
                    state["row_steps"] = torch.zeros(param.shape[0], dtype=grad.dtype, device=grad.device)  # [T]
                g = grad[rows]  # [R, n]
                steps = state["row_steps"][rows] + 1  # [R]
                state["row_steps"][rows] = steps
                m = state["exp_avg"][rows].mul_(beta1).add_(g, alpha=1 - beta1)
                v = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(g, g, value=1 - beta2)
                state["exp_avg"][rows], state["exp_avg_sq"][rows] = m, v
                m_hat = m / (1 - beta1 ** steps)[:, None]
                v_hat = v / (1 - beta2 ** steps)[:, None]
                update = group["lr"] * m_hat / (v_hat.sqrt() + group["eps"])  # [R, n]
                param.view(param.shape[0], -1)[rows] -= update
        return None


__all__ = ["FrameParams", "REFINED_KEYS", "RowAdam"]
