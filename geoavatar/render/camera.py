"""Pinhole cameras in the project's convention, and conversions from the conventions of the field.

Our `viewmat` is world-to-camera [4, 4] with OpenCV axes (+x right, +y down, +z forward, as gsplat);
`K` [3, 3] is the pinhole intrinsics in pixels, with pixel centres at +0.5 (the pixel (i, j) covers
[i, i+1) x [j, j+1) and its centre is (i + 0.5, j + 0.5)).

VHAP / GaussianAvatars / NeRF `transforms_*.json` store "transform_matrix" as camera-to-world with
OpenGL axes (+x right, +y up, +z backward); `opengl_c2w_to_viewmat` and `viewmat_to_opengl_c2w`
convert between the two.

Every function works on torch tensors with optional leading batch dimensions and follows the
device/dtype of its inputs.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, Sequence

import torch
from torch import Tensor

# Flipping y and z turns OpenGL camera axes into OpenCV ones (and back: it is its own inverse).
_GL_TO_CV_DIAG = (1.0, -1.0, -1.0, 1.0)


class Camera(NamedTuple):
    """One pinhole camera and the image it takes: what rasterize needs besides the Gaussians."""

    viewmat: Tensor  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor  # [3, 3] pixels, pixel centres at +0.5
    width: int
    height: int

    def to(self, device: torch.device | str) -> "Camera":
        return Camera(self.viewmat.to(device), self.K.to(device), self.width, self.height)

    def resized(self, longer_side: int) -> "Camera":
        """The same camera for an image whose longer side is `longer_side` pixels (K scaled)."""
        scale = longer_side / max(self.width, self.height)
        width, height = max(1, round(self.width * scale)), max(1, round(self.height * scale))
        return Camera(self.viewmat, scale_intrinsics(self.K, width / self.width, height / self.height), width, height)


def scale_intrinsics(K: Tensor, sx: float, sy: float | None = None) -> Tensor:
    """K [..., 3, 3] for the image resized by (sx, sy) (sy = sx when not given): rows 0 and 1 scaled, so pixel
    centres at +0.5 keep their meaning."""
    factors = torch.tensor([sx, sx if sy is None else sy, 1.0], dtype=K.dtype, device=K.device)
    return K * factors[:, None]


def _as_tensor(x: Tensor | Sequence[float], like: Tensor | None = None) -> Tensor:
    if isinstance(x, Tensor):
        return x if like is None else x.to(device=like.device, dtype=like.dtype)
    if like is not None:
        return torch.as_tensor(x, dtype=like.dtype, device=like.device)
    return torch.as_tensor(x, dtype=torch.float32)


def look_at(
    eye: Tensor | Sequence[float],  # [..., 3] camera centre in world coordinates
    target: Tensor | Sequence[float],  # [..., 3] point the camera looks at
    up: Tensor | Sequence[float] = (0.0, 1.0, 0.0),  # [..., 3] world direction that appears upward
) -> Tensor:
    """World-to-camera matrix [..., 4, 4] (OpenCV axes) of a camera at `eye` looking at `target`.

    The image's up direction is the projection of `up` (so +y of the camera is "down" in the world).
    Raises ValueError when eye == target or `up` is parallel to the viewing direction.
    """
    eye = _as_tensor(eye)
    target = _as_tensor(target, eye)
    up = _as_tensor(up, eye)
    forward = target - eye  # [..., 3] camera +z
    if bool((forward.norm(dim=-1) < 1e-12).any()):
        raise ValueError("look_at: eye and target coincide")
    forward = forward / forward.norm(dim=-1, keepdim=True)
    right = torch.linalg.cross(forward, up.expand_as(forward))  # [..., 3] camera +x
    if bool((right.norm(dim=-1) < 1e-9).any()):
        raise ValueError("look_at: 'up' is parallel to the viewing direction; pass another up vector")
    right = right / right.norm(dim=-1, keepdim=True)
    down = torch.linalg.cross(forward, right)  # [..., 3] camera +y (right x down = forward)
    rot = torch.stack([right, down, forward], dim=-2)  # [..., 3, 3] rows = camera axes in world
    trans = -(rot @ eye[..., None])[..., 0]  # [..., 3]
    viewmat = torch.zeros(*rot.shape[:-2], 4, 4, dtype=eye.dtype, device=eye.device)
    viewmat[..., :3, :3] = rot
    viewmat[..., :3, 3] = trans
    viewmat[..., 3, 3] = 1.0
    return viewmat


def intrinsics_from_fov(
    fov_deg: float,
    width: int,
    height: int,
    axis: Literal["x", "y"] = "x",
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Pinhole K [3, 3] with square pixels and the principal point at the image centre.

    fov_deg is the full field of view across the image width (axis="x", as NeRF/VHAP's
    camera_angle_x) or height (axis="y").
    """
    if not 0.0 < fov_deg < 180.0:
        raise ValueError(f"intrinsics_from_fov: fov_deg must be in (0, 180), got {fov_deg}")
    if width <= 0 or height <= 0:
        raise ValueError(f"intrinsics_from_fov: width and height must be positive, got {width}x{height}")
    focal = focal_length(math.radians(fov_deg), width if axis == "x" else height)
    return torch.tensor(
        [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]], dtype=dtype, device=device
    )


def centred_intrinsics(K: Tensor, width: int, height: int) -> Tensor:
    """K [3, 3] with its principal point moved to the image centre (width / 2, height / 2), focal lengths kept.

    A camera aimed at a point (look_at, orbit_viewmat) shows that point at the principal point; `prepare`'s
    face crops leave it anywhere (even outside the image), so views aimed at the head use this K."""
    out = K.clone()
    out[..., 0, 2] = width / 2.0
    out[..., 1, 2] = height / 2.0
    return out


def focal_length(fov: float, extent: float) -> float:
    """Focal length in pixels that shows a full field of view of `fov` radians across `extent` pixels."""
    return 0.5 * extent / math.tan(0.5 * fov)


def field_of_view(focal: float, extent: float) -> float:
    """Full field of view in radians across `extent` pixels at focal length `focal` (pixels): NeRF/VHAP's
    camera_angle_x with the image width."""
    return 2.0 * math.atan(0.5 * extent / focal)


def fov_from_intrinsics(K: Tensor, width: int, height: int, axis: Literal["x", "y"] = "x") -> float:
    """Inverse of intrinsics_from_fov: full field of view in degrees across width (x) or height (y)."""
    focal = float(K[..., 0, 0] if axis == "x" else K[..., 1, 1])
    return math.degrees(field_of_view(focal, width if axis == "x" else height))


def world_to_camera(points: Tensor, viewmat: Tensor) -> Tensor:
    """points [..., N, 3] (world) -> [..., N, 3] camera coordinates (OpenCV axes); viewmat [..., 4, 4]."""
    viewmat = viewmat.to(points.dtype)
    return points @ viewmat[..., :3, :3].transpose(-1, -2) + viewmat[..., None, :3, 3]


def project(
    points: Tensor,  # [..., N, 3] world coordinates
    viewmat: Tensor,  # [..., 4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [..., 3, 3]
) -> tuple[Tensor, Tensor]:
    """Perspective projection: pixels [..., N, 2] (x, y; centres at +0.5) and camera depth z [..., N].

    Points behind the camera (z <= 0) get non-finite or mirrored pixels; check `depth > 0`.
    """
    cam = world_to_camera(points, viewmat)  # [..., N, 3]
    depth = cam[..., 2]
    K = K.to(points.dtype)
    uvw = cam @ K.transpose(-1, -2)  # [..., N, 3]
    pixels = uvw[..., :2] / uvw[..., 2:3]
    return pixels, depth


def _gl_cv_flip(like: Tensor) -> Tensor:
    return torch.diag(torch.tensor(_GL_TO_CV_DIAG, dtype=like.dtype, device=like.device))


def opengl_c2w_to_viewmat(c2w_gl: Tensor) -> Tensor:
    """Camera-to-world with OpenGL axes [..., 4, 4] (VHAP "transform_matrix") -> our viewmat [..., 4, 4].

    A [..., 3, 4] matrix is accepted and completed with the row (0, 0, 0, 1).
    """
    c2w_gl = _homogeneous(c2w_gl, "c2w_gl")
    c2w_cv = c2w_gl @ _gl_cv_flip(c2w_gl)  # flip the camera's y and z axes
    return rigid_inverse(c2w_cv)


def viewmat_to_opengl_c2w(viewmat: Tensor) -> Tensor:
    """Our viewmat (world-to-camera, OpenCV axes) [..., 4, 4] -> camera-to-world with OpenGL axes."""
    viewmat = _homogeneous(viewmat, "viewmat")
    return rigid_inverse(viewmat) @ _gl_cv_flip(viewmat)


def rigid_inverse(matrix: Tensor) -> Tensor:
    """Inverse of a rigid transform [..., 4, 4] (rotation + translation) without a general inverse."""
    rot = matrix[..., :3, :3]
    trans = matrix[..., :3, 3:4]
    out = torch.zeros_like(matrix)
    out[..., :3, :3] = rot.transpose(-1, -2)
    out[..., :3, 3:4] = -rot.transpose(-1, -2) @ trans
    out[..., 3, 3] = 1.0
    return out


def orbit_viewmat(
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    centre: Tensor,  # [3] the point the camera turns about (and then looks at)
    yaw_deg: float,
    pitch_deg: float = 0.0,
) -> Tensor:
    """The camera turned about `centre` by yaw (about its own up axis) then pitch (about its right
    axis), at its distance to `centre`, aimed at `centre`: [4, 4]. Positive yaw moves the camera
    toward its right; positive pitch moves it up. `geoavatar orbit` and the novel views of
    `geoavatar synth` place their cameras with it."""
    from geoavatar.geometry import axis_angle_to_matrix

    c2w = rigid_inverse(viewmat.to(centre))  # [4, 4] columns: camera axes in world, then the camera centre
    right, up = c2w[:3, 0], -c2w[:3, 1]  # OpenCV: +y is down in the image
    offset = c2w[:3, 3] - centre  # [3]
    if float(offset.norm()) < 1e-9:
        raise ValueError("orbit_viewmat: the camera sits at the centre it turns about")
    turn = axis_angle_to_matrix(up * math.radians(yaw_deg)) @ axis_angle_to_matrix(right * math.radians(-pitch_deg))
    return look_at(centre + turn @ offset, centre, turn @ up)


def orbit_cameras(base: "Camera", centre: Tensor, angles: list[tuple[float, float]]) -> list["Camera"]:
    """Cameras turned about `centre` [3] by (yaw, pitch) degrees and aimed at it, at base's distance and focal
    lengths, `centre` in the middle of the image (orbit_viewmat: positive yaw toward the camera's right, positive
    pitch up; centred_intrinsics), on centre's device and dtype. `geoavatar orbit`, eval's side views and the
    warped view's turned camera (train/warped_view.py) place their cameras with it."""
    viewmat = base.viewmat.to(centre)
    K = centred_intrinsics(base.K.to(centre), base.width, base.height)
    return [Camera(orbit_viewmat(viewmat, centre, yaw, pitch), K, base.width, base.height) for yaw, pitch in angles]


def _homogeneous(matrix: Tensor, name: str) -> Tensor:
    if matrix.shape[-2:] == (4, 4):
        return matrix
    if matrix.shape[-2:] == (3, 4):
        bottom = torch.zeros(*matrix.shape[:-2], 1, 4, dtype=matrix.dtype, device=matrix.device)
        bottom[..., 0, 3] = 1.0
        return torch.cat([matrix, bottom], dim=-2)
    raise ValueError(f"{name} must be [..., 4, 4] or [..., 3, 4], got shape {tuple(matrix.shape)}")


__all__ = [
    "Camera", "look_at", "intrinsics_from_fov", "centred_intrinsics", "field_of_view", "focal_length",
    "fov_from_intrinsics", "world_to_camera", "project",
    "opengl_c2w_to_viewmat", "viewmat_to_opengl_c2w", "rigid_inverse", "scale_intrinsics",
    "orbit_viewmat", "orbit_cameras",
]
