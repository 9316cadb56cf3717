"""Gaussians bound to triangles: face frames, local -> global, polar coordinates of local means.

The frame of a face (GaussianAvatars' `compute_face_orientation`, kept exactly so that local
parameters mean the same as in GaussianAvatars):

    a0 = normalize(v1 - v0)                  first edge
    a1 = normalize(a0 x (v2 - v0))           face normal (outward for counter-clockwise faces)
    a2 = -normalize(a1 x a0) = a0 x a1       in-plane, completes a right-handed frame
    R  = [a0 | a1 | a2]   (columns)          local x -> a0, local y -> normal, local z -> a2
    C  = (v0 + v1 + v2) / 3
    k  = (|v1 - v0| + |a2 . (v2 - v0)|) / 2  "face scaling": mean of base length and height

Local -> global:  mu_g = k R mu + C,  s_g = k exp(s),  q_g = q_face (x) normalize(q).
The rotation is composed as rotation matrices compose (R_g = R_face R_local). GaussianAvatars'
code multiplies in the other order (q_local (x) q_face); with identity initial rotations both start
the same, but they are different parametrisations of the learned rotations.

Polar coordinates (paper Sec. 3): r = |mu|; phi = angle between mu and the face normal. The paper
calls the normal "the z-axis"; in this frame the normal is local axis 1 (y), so phi = angle(mu, +e_y)
in [0, pi]. We measure to the *positive* normal: Fig. 5's purpose is keeping a far Gaussian above
its own triangle (inside the cone over it), and a Gaussian far *below* its face sits inside the
head, nearer to other triangles; `two_sided=True` measures to the normal line instead.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from geoavatar.avatar import fused
from geoavatar.avatar.fused import place_gaussians
from geoavatar.geometry import matrix_to_quaternion

_EPS = 1e-12


class FaceFrames(NamedTuple):
    """Per-face local frames of one posed mesh (or a batch of them)."""

    rotation: Tensor  # [..., F, 3, 3] columns a0, a1 (normal), a2
    centre: Tensor  # [..., F, 3]
    scale: Tensor  # [..., F]

    @property
    def quaternion(self) -> Tensor:
        """[..., F, 4] (w, x, y, z)."""
        return matrix_to_quaternion(self.rotation)


def _normalize(x: Tensor) -> Tensor:
    return x / x.square().sum(-1, keepdim=True).clamp_min(_EPS).sqrt()


def face_frames(vertices: Tensor, faces: Tensor) -> FaceFrames:
    """Local frame of every face.

    vertices: [..., V, 3] posed vertices; faces: [F, 3] vertex ids -> FaceFrames with [..., F, ...].
    """
    if vertices.shape[-1] != 3:
        raise ValueError(f"face_frames: vertices must be [..., V, 3], got {tuple(vertices.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"face_frames: faces must be [F, 3], got {tuple(faces.shape)}")
    faces = faces.to(device=vertices.device, dtype=torch.long)
    v0 = vertices[..., faces[:, 0], :]  # [..., F, 3]
    v1 = vertices[..., faces[:, 1], :]
    v2 = vertices[..., faces[:, 2], :]
    edge0 = v1 - v0
    edge2 = v2 - v0
    a0 = _normalize(edge0)
    a1 = _normalize(torch.linalg.cross(a0, edge2, dim=-1))
    a2 = -_normalize(torch.linalg.cross(a1, a0, dim=-1))
    rotation = torch.stack([a0, a1, a2], dim=-1)  # [..., F, 3, 3]
    centre = (v0 + v1 + v2) / 3.0
    base = edge0.square().sum(-1).clamp_min(_EPS).sqrt()
    height = (a2 * edge2).sum(-1).abs()
    return FaceFrames(rotation, centre, (base + height) / 2.0)


class GlobalGaussians(NamedTuple):
    """Gaussians in head/world space, ready for `rasterize` (gsplat conventions)."""

    means: Tensor  # [..., N, 3]
    quats: Tensor  # [..., N, 4] unit (w, x, y, z)
    scales: Tensor  # [..., N, 3] standard deviations (not log)
    opacities: Tensor  # [N] in (0, 1)
    colors: Tensor  # [N, 3] RGB from the SH degree-0 coefficient
    frames: FaceFrames  # the face frames they were placed with (face scale needed by densification)


def local_to_global(
    means: Tensor,  # [N, 3] local means, in face-scale units
    quats: Tensor,  # [N, 4] local rotations (w, x, y, z), any norm
    log_scales: Tensor,  # [N, 3] local log standard deviations
    binding: Tensor,  # [N] face index of each Gaussian
    frames: FaceFrames,  # [..., F, ...]
) -> tuple[Tensor, Tensor, Tensor]:
    """mu_g = k R mu + C, q_g = q_face (x) normalize(q), s_g = k exp(s): -> [..., N, 3], [..., N, 4], [..., N, 3].

    One autograd Function with a hand-written backward (fused.place_gaussians)."""
    return place_gaussians(frames.rotation, frames.centre, frames.scale, frames.quaternion, means, quats, log_scales,
                           binding)


def polar_coordinates(local_means: Tensor, two_sided: bool = False) -> tuple[Tensor, Tensor]:
    """r = |mu| and phi = angle between mu and the face normal (local axis 1), gradient-safe at 0.

    local_means: [N, 3] -> r [N], phi [N] in [0, pi] ([0, pi/2] when two_sided).
    """
    return fused.polar_coordinates(local_means, two_sided)
