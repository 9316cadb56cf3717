"""One way to pose and render an avatar, shared by the trainer, eval and every app.

    posed = pose_avatar(avatar, head, params, T, deformer)                  # PosedAvatar(gaussians, vertices)
    frame = render_avatar(avatar, head, params, camera, T, deformer, background)
    frame.result.rgb                                                       # [H, W, 3]; also .gaussians, .vertices

params: HeadParams of one frame (per-frame keys [1, ...]); T: the mouth deformer's time input
(`frame_timestep` gives the rule; None = T = 0); camera: render.camera.Camera. The head is posed
once per frame, and its vertices come back with the image (eval's mouth mask needs them).
"""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor

from geoavatar.avatar.binding import GlobalGaussians
from geoavatar.avatar.deform import MouthDeformer, posed_head
from geoavatar.avatar.hair_motion import head_pose_code
from geoavatar.avatar.model import GaussianAvatar
from geoavatar.head.base import HeadModel
from geoavatar.head.params import HeadParams
from geoavatar.render.camera import Camera
from geoavatar.render.rasterize import RasterizeResult, rasterize


class PosedAvatar(NamedTuple):
    gaussians: GlobalGaussians  # in world space, ready for rasterize
    vertices: Tensor  # [V, 3] the posed head (with the mouth deformation)


class AvatarRender(NamedTuple):
    result: RasterizeResult  # rgb [H, W, 3] on the background, alpha, means2d (densification), ...
    gaussians: GlobalGaussians
    vertices: Tensor  # [V, 3]


def pose_avatar(
    avatar: GaussianAvatar,
    head: HeadModel,
    params: HeadParams,  # one frame: per-frame keys [1, ...]
    timestep: int | None = None,  # T of the mouth deformer; None = T = 0 (see frame_timestep)
    deformer: MouthDeformer | None = None,
) -> PosedAvatar:
    """Head posed by `params` (with the part-wise mouth offsets), then the avatar's local -> global (with the frame's
    head pose code when the avatar's hair follows the head's turn)."""
    vertices = posed_head(head, params, deformer, timestep).vertices[0]  # [V, 3]
    code = head_pose_code(params) if avatar.follows_head else None  # [6]
    return PosedAvatar(avatar(vertices, code), vertices)


def rasterize_gaussians(
    gaussians: GlobalGaussians,
    camera: Camera,  # moved to the Gaussians' device when elsewhere
    background: Tensor | None = None,  # [3]; None = black
    backend: str = "auto",
    check_values: bool = True,  # rasterize's value checks (one device sync)
) -> RasterizeResult:
    device = gaussians.means.device
    camera = camera.to(device)
    background = None if background is None else background.to(device)
    return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
                     camera.viewmat, camera.K, camera.width, camera.height, background, backend=backend,
                     check_values=check_values)


def render_avatar(
    avatar: GaussianAvatar,
    head: HeadModel,
    params: HeadParams,  # one frame: per-frame keys [1, ...]
    camera: Camera,
    timestep: int | None = None,  # T of the mouth deformer; None = T = 0
    deformer: MouthDeformer | None = None,
    background: Tensor | None = None,  # [3]; None = black
    backend: str = "auto",
    check_values: bool = True,
) -> AvatarRender:
    """Pose the head, place the Gaussians, rasterize; differentiable (the trainer's step uses it)."""
    posed = pose_avatar(avatar, head, params, timestep, deformer)
    result = rasterize_gaussians(posed.gaussians, camera, background, backend, check_values)
    return AvatarRender(result, posed.gaussians, posed.vertices)


__all__ = ["AvatarRender", "PosedAvatar", "pose_avatar", "rasterize_gaussians", "render_avatar"]
