"""Part-wise mouth deformation (paper Sec. 3.2): Phi_upper and Phi_lower.

    Delta v_part = Phi_part(psi, Theta, gamma(T))      one 3D offset per part and frame

psi: expression coefficients (padded/truncated to `expr_dim`, 100 as FLAME); Theta: neck 3 + jaw 3 +
eyes 6 = 12 numbers (axis-angle); gamma(T): [sin(2^l pi t), cos(2^l pi t)] for l < L with
t = T / num_frames in [0, 1), so the same L frequencies resolve any sequence length. T = 0 when
animating from new parameters (`timestep=None`), as the paper does at inference.

Where the offset is applied: to the *rest-pose* vertices of the part, before linear blend
skinning, through HeadModel's per-vertex offset input. The mouth parts are skinned rigidly (upper
part to the neck joint, lower part to the jaw, no correctives, no joint-regressor weight: see
geoavatar.head.mouth), so after LBS every vertex of a part still moves by one common offset, now
rotated with its joint. Hence a learned correction ("lower teeth 2 mm further back") means the same
whatever the head and jaw rotation, which an offset added to posed world-space vertices would not.
It is the place GaussianAvatars' FLAME adds its per-frame `dynamic_offset`, which GeoAvatar's code
base inherits.

Each MLP: Linear-ReLU x hidden_layers, then Linear(., 3) initialised to zero (training starts from
the undeformed mouth); the output is in units of `offset_unit` metres (centimetres by default).
Adam moves each last-layer weight by about the learning rate per step whatever the gradient's size,
so the offset can change by ~lr x (sum of hidden activations) cm per step; LearningRates.mouth_deform
(1e-5) keeps that sub-millimetre over a run (1e-4 drifted 5 mm where there was nothing to correct).
"""

from __future__ import annotations

import math
from typing import Container, Literal, Mapping

import numpy as np
import torch
from torch import Tensor, nn

from geoavatar.config import MouthDeformConfig
from geoavatar.head.base import HeadModel, HeadOutput
from geoavatar.head.params import HeadParams, as_head_params

POSE_DIM = 12  # neck 3 + jaw 3 + eyes 6
PART_NAMES = ("upper", "lower")


def positional_encoding(t: Tensor, frequencies: int) -> Tensor:
    """gamma(t): t [B] (normalised time) -> [B, 2 * frequencies] = sin(2^l pi t), cos(2^l pi t)."""
    scales = (2.0 ** torch.arange(frequencies, dtype=t.dtype, device=t.device)) * math.pi  # [L]
    angles = t[:, None] * scales  # [B, L]
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def pose_vector(neck_pose: Tensor, jaw_pose: Tensor, eyes_pose: Tensor) -> Tensor:
    """Theta [B, 12] = neck [B,3], jaw [B,3], eyes [B,6]."""
    return torch.cat([neck_pose, jaw_pose, eyes_pose], dim=-1)


def _mlp(in_dim: int, width: int, layers: int) -> nn.Sequential:
    modules: list[nn.Module] = []
    dim = in_dim
    for _ in range(layers):
        modules += [nn.Linear(dim, width), nn.ReLU()]
        dim = width
    last = nn.Linear(dim, 3)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    modules.append(last)
    return nn.Sequential(*modules)


class MouthDeformer(nn.Module):
    """Phi_upper, Phi_lower and the vertex ids of the two mouth parts."""

    def __init__(
        self,
        num_vertices: int,
        upper_vertices: np.ndarray | Tensor,  # [Vu] ids of upper teeth + palate
        lower_vertices: np.ndarray | Tensor,  # [Vl] ids of lower teeth + floor
        num_frames: int,
        cfg: MouthDeformConfig = MouthDeformConfig(),
    ):
        super().__init__()
        if num_frames < 1:
            raise ValueError(f"MouthDeformer: num_frames must be >= 1, got {num_frames}")
        upper = torch.as_tensor(np.asarray(upper_vertices), dtype=torch.long).reshape(-1)
        lower = torch.as_tensor(np.asarray(lower_vertices), dtype=torch.long).reshape(-1)
        for name, ids in (("upper", upper), ("lower", lower)):
            if ids.numel() == 0 or int(ids.min()) < 0 or int(ids.max()) >= num_vertices:
                raise ValueError(f"MouthDeformer: mouth_{name} vertex ids are empty or outside [0, {num_vertices})")
        if bool(torch.isin(upper, lower).any()):
            raise ValueError("MouthDeformer: mouth_upper and mouth_lower share vertices")
        self.cfg = cfg
        self.num_vertices = int(num_vertices)
        self.num_frames = int(num_frames)
        self.register_buffer("upper_vertices", upper, persistent=False)
        self.register_buffer("lower_vertices", lower, persistent=False)
        in_dim = cfg.expr_dim + POSE_DIM + 2 * cfg.frequencies
        self.phi = nn.ModuleDict({name: _mlp(in_dim, cfg.hidden_width, cfg.hidden_layers) for name in PART_NAMES})

    @classmethod
    def for_head(cls, head: HeadModel, num_frames: int, cfg: MouthDeformConfig = MouthDeformConfig()) -> "MouthDeformer":
        groups = head.vertex_groups
        missing = [g for g in ("mouth_upper", "mouth_lower") if g not in groups]
        if missing:
            raise ValueError(f"head model '{head.name}' has no vertex group(s) {missing}: add a mouth structure "
                             "(geoavatar.head.mouth) or disable model.mouth_deform")
        return cls(head.num_vertices, groups["mouth_upper"], groups["mouth_lower"], num_frames, cfg)

    def features(self, expr: Tensor, pose: Tensor, timestep: Tensor | int | None) -> Tensor:
        """Network input [B, expr_dim + 12 + 2L] from expr [B, E'], pose [B, 12], timestep [B] | int | None."""
        if pose.shape[-1] != POSE_DIM:
            raise ValueError(f"MouthDeformer: pose must be [B, {POSE_DIM}] (neck, jaw, eyes), got {tuple(pose.shape)}")
        batch = pose.shape[0]
        e = self.cfg.expr_dim
        expr = expr[..., :e]
        if expr.shape[-1] < e:
            expr = torch.cat([expr, expr.new_zeros(*expr.shape[:-1], e - expr.shape[-1])], dim=-1)
        if timestep is None:
            t = pose.new_zeros(batch)  # inference / novel animation: T = 0
        else:
            t = torch.as_tensor(timestep, dtype=pose.dtype, device=pose.device).reshape(-1).expand(batch)
            t = t / self.num_frames
        return torch.cat([expr.to(pose.dtype), pose, positional_encoding(t, self.cfg.frequencies)], dim=-1)

    def part_offsets(self, expr: Tensor, pose: Tensor, timestep: Tensor | int | None = None) -> Tensor:
        """[B, 2, 3] offsets in metres, (upper, lower)."""
        x = self.features(expr, pose, timestep)
        return torch.stack([self.phi[name](x) for name in PART_NAMES], dim=1) * self.cfg.offset_unit

    def forward(self, expr: Tensor, pose: Tensor, timestep: Tensor | int | None = None) -> Tensor:
        """Per-vertex rest-pose offsets [B, V, 3]: the part offset on its vertices, zero elsewhere."""
        parts = self.part_offsets(expr, pose, timestep)  # [B, 2, 3]
        batch = parts.shape[0]
        offsets = parts.new_zeros(batch, self.num_vertices, 3)
        offsets = offsets.index_copy(1, self.upper_vertices, parts[:, 0:1].expand(batch, len(self.upper_vertices), 3))
        offsets = offsets.index_copy(1, self.lower_vertices, parts[:, 1:2].expand(batch, len(self.lower_vertices), 3))
        return offsets


TimestepMode = Literal["auto", "zero", "frame"]


def frame_timestep(timestep: int, trained: Container[int], mode: TimestepMode = "auto") -> int | None:
    """The T rule: the deformer's time input for rendering `timestep` of a run.

    auto: a training timestep (in `trained`) uses its own T, the code gamma(T) the run learned for it,
    which reproduces what training saw; any other frame (test frames, a driver's frames, edited
    parameters) uses None, i.e. T = 0, the paper's inference setting, since gamma(T) was never
    trained there. zero: always None; frame: always the frame's own T."""
    if mode == "zero" or (mode == "auto" and timestep not in trained):
        return None
    if mode not in ("auto", "frame"):
        raise ValueError(f"timestep mode must be auto, zero or frame, got {mode!r}")
    return int(timestep)


def posed_head(
    head: HeadModel,
    params: HeadParams | Mapping[str, Tensor],  # batched [B, ...] (shape [S] or [B, S]); a dict in the npz layout
    deformer: MouthDeformer | None = None,
    timestep: Tensor | int | None = None,  # frame index T; None = inference (T = 0)
) -> HeadOutput:
    """The head model posed by `params`, with the part-wise mouth deformation when `deformer` is given."""
    params = as_head_params(params)
    static = params.static_offset
    if deformer is not None:
        pose = pose_vector(params.neck_pose, params.jaw_pose, params.eyes_pose)
        mouth = deformer(params.expr, pose, timestep)  # [B, V, 3]
        if static is not None:
            if static.dim() == 2:
                static = static[None]
            pad = head.num_vertices - static.shape[-2]
            if pad < 0:
                raise ValueError(f"static_offset has {static.shape[-2]} vertices, head model has {head.num_vertices}")
            static = torch.cat([static, static.new_zeros(*static.shape[:-2], pad, 3)], dim=-2) if pad else static
            mouth = mouth + static.to(mouth)
        static = mouth
    return head.forward_params(params.replace(static_offset=static))
