"""Rotation and small geometry helpers shared by every layer (torch, batched, differentiable)."""

from __future__ import annotations

import torch
from torch import Tensor


def axis_angle_to_matrix(axis_angle: Tensor) -> Tensor:
    """Rodrigues' formula, safe and differentiable at zero angle.

    axis_angle: [..., 3] -> rotation matrices [..., 3, 3]
    """
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True)  # [..., 1]
    small = theta2 < 1e-8
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    # sin(t)/t and (1-cos(t))/t^2 with their Taylor series near zero.
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2_safe)
    x, y, z = axis_angle.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*axis_angle.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_quaternion(matrix: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] -> unit quaternions [..., 4] (w, x, y, z), w >= 0."""
    # The nine entries by one unbind: its backward is one stack, where 9 selects would each add a
    # zero-filled [..., 3, 3] gradient.
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = matrix.flatten(-2).unbind(-1)
    # Four candidate magnitudes; pick the best-conditioned per element (Shepperd's method).
    q_abs = torch.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], dim=-1
    ).clamp_min(1e-12).sqrt()  # [..., 4] = 2*|w|, 2*|x|, 2*|y|, 2*|z|
    q0, q1, q2, q3 = q_abs.unbind(-1)
    candidates = torch.stack(
        [
            torch.stack([q0 ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, q1 ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, q2 ** 2, m21 + m12], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q3 ** 2], -1),
        ],
        dim=-2,
    ) / (2.0 * q_abs[..., :, None])  # [..., 4, 4]
    best = q_abs.argmax(dim=-1)  # [...]
    quat = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    quat = torch.nn.functional.normalize(quat, dim=-1)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quaternion_multiply(a: Tensor, b: Tensor, dim: int = -1) -> Tensor:
    """Hamilton product a ⊗ b of quaternions [..., 4] (w, x, y, z); `dim`: the component axis
    (0 for component-major [4, ...] tensors, whose components are contiguous)."""
    aw, ax, ay, az = a.unbind(dim)
    bw, bx, by, bz = b.unbind(dim)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=dim,
    )


def quaternion_to_matrix(quat: Tensor) -> Tensor:
    """Quaternions [..., 4] (w, x, y, z; normalised here) -> rotation matrices [..., 3, 3]."""
    w, x, y, z = torch.nn.functional.normalize(quat, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quat.shape[:-1], 3, 3)


def matrix_to_axis_angle(matrix: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] -> axis-angle [..., 3] with angle in [0, pi] (via the quaternion)."""
    quat = matrix_to_quaternion(matrix)  # [..., 4], w >= 0
    w, xyz = quat[..., :1], quat[..., 1:]
    sin_half = xyz.norm(dim=-1, keepdim=True)  # [..., 1]
    angle = 2.0 * torch.atan2(sin_half, w)
    # angle / sin(angle/2) -> 2 / w as the angle -> 0 (w -> 1).
    small = sin_half < 1e-6
    factor = torch.where(small, 2.0 / w.clamp_min(1e-6), angle / torch.where(small, torch.ones_like(sin_half), sin_half))
    return xyz * factor


def rotation_6d_to_matrix(d6: Tensor) -> Tensor:
    """6D rotations [..., 6] -> matrices [..., 3, 3], PyTorch3D's convention (used by metrical-tracker).

    The 6 numbers are the first two ROWS of the matrix (Zhou et al. 2019 write columns; PyTorch3D,
    and so metrical-tracker's `.frame` files, store rows). Gram-Schmidt makes them orthonormal; the
    third row is their cross product.
    """
    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = torch.nn.functional.normalize(a1, dim=-1)
    b2 = torch.nn.functional.normalize(a2 - (b1 * a2).sum(-1, keepdim=True) * b1, dim=-1)
    b3 = torch.linalg.cross(b1, b2)
    return torch.stack([b1, b2, b3], dim=-2)


def camera_centre(viewmat: Tensor) -> Tensor:
    """[..., 3] world position of the camera of each world-to-camera `viewmat` [..., 4, 4]: C = -R^T t."""
    rot, trans = viewmat[..., :3, :3], viewmat[..., :3, 3:]
    return -(rot.transpose(-1, -2) @ trans).squeeze(-1)
