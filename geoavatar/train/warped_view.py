"""The training frame seen from a turned camera, warped through the posed head mesh (TrainConfig.warped_view, #18).

A monocular video films a turning head from one camera, so a surface point's view direction and its world normal
change together: the avatar can explain a pose-dependent brightness by its shading *or* by how its layers composite
from that one direction, and only the first is right from any other camera. A second camera breaks the tie (on the
generated subject 0, 80 extra yaw +-30 frames lifted the held-out yaw +-30 views from 28.3 / 28.6 to 34.1 / 35.0 dB).
One camera can borrow it from the mesh: a point of the posed head that the training camera sees has, for a
Lambertian surface under room-fixed lights, the same colour from a camera turned about the head. So

    pseudo target(p) = image(project_source(X(p)))     X(p): the mesh point a turned-camera pixel p sees
    loss             = mean over valid p of |render_turned(p) - pseudo target(p)|

valid: the mesh face at p belongs to the skin parts the head model fits (not hair, which lies above the scalp, nor
the mouth interior), the same point is the visible surface from the training camera (depth test against its
z-buffer), the training mask covers it there, and the training camera sees it at most `max_angle` off its normal
(grazing pixels would be stretched over many turned-view pixels). The target carries no gradient; the turned render
does, and through the posed Gaussians it reaches what the training camera's loss reaches: the Gaussians and, via the
posed vertices, the per-frame tracking refinement and the mouth deformer (BENCHMARKS.md's figures were measured so).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.avatar.binding import GlobalGaussians
from geoavatar.avatar.render import rasterize_gaussians
from geoavatar.config import WarpedViewConfig
from geoavatar.geometry import camera_centre
from geoavatar.head.regions import skull_centre
from geoavatar.render.camera import Camera, orbit_cameras, world_to_camera
from geoavatar.render.mesh import behind_surface, interpolate, rasterize_mesh
from geoavatar.train.randomness import turned_angles


class WarpedView(NamedTuple):
    colour: Tensor  # [h, w, 3] the training image's colour of the surface point each turned-camera pixel sees
    valid: Tensor  # [h, w] bool: pixels whose colour the warp can give (see the module docstring)


@torch.no_grad()
def warp_to_camera(
    image: Tensor,  # [H, W, 3] the training frame
    mask: Tensor,  # [H, W] foreground mask of the training frame, in [0, 1]
    vertices: Tensor,  # [V, 3] posed head in world space
    faces: Tensor,  # [F, 3]
    normals: Tensor,  # [F, 3] outward unit face normals (the avatar's face frames, binding.FaceFrames axis 1)
    usable_faces: Tensor,  # [F] bool: faces whose surface is the subject's (skin parts)
    source: Camera,  # the training camera
    target: Camera,  # the turned camera
    depth_tolerance: float,  # metres: how far the point may lie behind the source's z-buffer and still be seen
    max_angle: float,  # degrees between the face normal and the source's line of sight
) -> WarpedView:
    """The training image resampled into `target` through the mesh (bilinear), and where it is valid."""
    vertices = vertices.detach()
    faces = faces.to(vertices.device)
    seen_t = rasterize_mesh(world_to_camera(vertices, target.viewmat.to(vertices)), faces, target.K.to(vertices),
                            target.width, target.height)
    face_id = seen_t.face_id.clamp_min(0)  # [h, w]
    points = interpolate(seen_t, vertices, faces)  # [h, w, 3] world point each target pixel sees
    src_view, src_K = source.viewmat.to(vertices), source.K.to(vertices)
    in_source = world_to_camera(points.reshape(-1, 3), src_view)  # [h*w, 3]
    z = in_source[:, 2].clamp_min(1e-6)
    uv = (in_source @ src_K.T)[:, :2] / z[:, None]  # [h*w, 2] source pixels (centres at +0.5)
    seen_s = rasterize_mesh(world_to_camera(vertices, src_view), faces, src_K, source.width, source.height)
    inside = ((in_source[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < source.width)
              & (uv[:, 1] >= 0) & (uv[:, 1] < source.height))
    visible = inside & ~behind_surface(in_source, seen_s.depth, src_K, depth_tolerance)  # [h*w] not hidden there
    normal = normals.detach().to(vertices)[face_id].reshape(-1, 3)  # [h*w, 3]
    to_camera = F.normalize(camera_centre(src_view) - points.reshape(-1, 3), dim=-1)
    facing = (normal * to_camera).sum(-1) >= math.cos(math.radians(max_angle))
    grid = torch.stack([uv[:, 0] / source.width, uv[:, 1] / source.height], -1) * 2.0 - 1.0  # align_corners=False
    sampled = F.grid_sample(torch.cat([image, mask[..., None]], -1).permute(2, 0, 1)[None].to(vertices),
                            grid.view(1, target.height, target.width, 2), mode="bilinear", padding_mode="border",
                            align_corners=False)[0].permute(1, 2, 0)  # [h, w, 4]
    valid = (seen_t.mask & usable_faces.to(vertices.device)[face_id]
             & (visible & facing).view(target.height, target.width) & (sampled[..., 3] > 0.99))
    return WarpedView(sampled[..., :3], valid)


def warped_view_loss(render: Tensor, warped: WarpedView) -> Tensor:
    """Mean L1 over the valid pixels of `render` [h, w, 3] against the warped colour (0 when none is valid)."""
    weight = warped.valid.to(render.dtype)[..., None]  # [h, w, 1]
    return ((render - warped.colour).abs() * weight).sum() / (3.0 * weight.sum()).clamp_min(1.0)


def turned_view_term(
    gaussians: GlobalGaussians,  # the posed avatar (differentiable)
    vertices: Tensor,  # [V, 3] posed head (the trainer's frame.vertices)
    head,  # HeadModel: faces, and the skull centre the camera turns about
    usable_faces: Tensor,  # [F] bool
    item: dict,  # the training item: image [H, W, 3], mask [H, W, 1]
    camera: Camera,  # the training camera
    background: Tensor,  # [3] the step's background (the turned render is composited on it)
    config: WarpedViewConfig,
    seed: int,
    step: int,
    backend: str = "auto",
) -> Tensor:
    """config.weight x warped_view_loss at `step`'s turned camera: the training camera turned about the posed head's
    centre by a seeded random yaw / pitch and aimed at it with the principal point mid-image, as `geoavatar orbit`
    and eval's side views turn it."""
    yaw, pitch = turned_angles(config.turned_yaw, config.turned_pitch, seed, step)
    view = orbit_cameras(camera, skull_centre(vertices.detach(), head), [(yaw, pitch)])[0]
    normals = gaussians.frames.rotation[..., :, 1]  # [F, 3]
    warped = warp_to_camera(item["image"], item["mask"][..., 0], vertices, head.faces, normals, usable_faces, camera,
                            view, config.depth_tolerance, config.max_angle)
    render = rasterize_gaussians(gaussians, view, background, backend, check_values=False).rgb
    return config.weight * warped_view_loss(render, warped)


__all__ = ["WarpedView", "turned_view_term", "warp_to_camera", "warped_view_loss"]
