"""Render the ground-truth actor with the mesh rasterizer: perspective, z-buffer, per-pixel
procedural colour, supersampled anti-aliasing; the mask is the supersampled coverage.

Not the Gaussian renderer under test: the images are made by a different renderer than the one the
avatar is trained with, as a real camera would be.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.data.synth.actor import Actor
from geoavatar.data.synth.appearance import MATERIAL_INDEX, Appearance
from geoavatar.render.camera import focal_length, intrinsics_from_fov, look_at, orbit_viewmat, scale_intrinsics, world_to_camera
from geoavatar.render.mesh import box_downsample, face_normals, rasterize_mesh, vertex_normals

_MOUTH_MATERIALS = [MATERIAL_INDEX[m] for m in ("teeth", "gums", "tongue")]


@dataclass
class Camera:
    viewmat: Tensor  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor  # [3, 3] pixels
    width: int
    height: int


def frontal_camera(actor: Actor, size: int, fov_deg: float = 30.0, fill: float = 0.6) -> Camera:
    """A fixed webcam-like camera in front of the actor's neutral head, the head filling `fill` of the height.

    The head's extent (crown with hair to chin) is measured on the neutral actor; the camera looks
    horizontally at the middle of that extent from +z.
    """
    with torch.no_grad():
        rest = actor.model.forward_params(_neutral(actor)).vertices[0].numpy()  # [V, 3]
    head_parts = rest[actor.part_of_vertex >= 0]
    chin_y = float(rest[np.asarray(actor.head.lip_ring_lower), 1].mean()) - 0.06
    top_y = float(head_parts[:, 1].max())
    centre_y = 0.5 * (top_y + chin_y)
    extent = top_y - chin_y
    visible = extent / fill
    distance = focal_length(math.radians(fov_deg), visible)  # where `visible` metres span the field of view
    eye = (0.0, centre_y, distance)  # the head model's origin is near the middle of the skull
    viewmat = look_at(torch.tensor(eye, dtype=torch.float64), torch.tensor((0.0, centre_y, 0.0), dtype=torch.float64))
    K = intrinsics_from_fov(fov_deg, size, size, axis="y", dtype=torch.float64)
    return Camera(viewmat=viewmat.float(), K=K.float(), width=size, height=size)


def orbit_camera(camera: Camera, yaw_deg: float, pitch_deg: float, centre: Tensor) -> Camera:
    """The same camera turned about `centre` [3] (render.camera.orbit_viewmat), aimed at it."""
    viewmat = orbit_viewmat(camera.viewmat.double(), centre.double(), yaw_deg, pitch_deg)
    return Camera(viewmat=viewmat.float(), K=camera.K, width=camera.width, height=camera.height)


def _neutral(actor: Actor) -> dict[str, Tensor]:
    params = actor.model.zero_params(1)
    params["shape"] = torch.from_numpy(actor.shape)
    return params


class ActorRenderer:
    """Renders frames of one actor over a plain background: holds the per-vertex attributes."""

    def __init__(self, actor: Actor, camera: Camera, background: tuple[float, float, float], ssaa: int = 2):
        if ssaa < 1:
            raise ValueError(f"ssaa must be >= 1, got {ssaa}")
        self.actor = actor
        self.camera = camera
        self.ssaa = ssaa
        self.appearance = Appearance(actor.subject, actor.landmarks)
        self.faces = torch.from_numpy(actor.faces).long()  # [F, 3]
        canonical = torch.from_numpy(actor.canonical)  # [V, 3]
        materials = torch.from_numpy(actor.materials)  # [V, M]
        edge = torch.from_numpy(actor.shell_edge)[:, None]  # [V, 1]
        self.vertex_attrs = torch.cat([canonical, materials, edge], dim=1)  # [V, 3 + M + 1]
        self.cavity = torch.from_numpy(actor.cavity_faces)  # [F]
        teeth = [np.asarray(actor.head.vertex_groups[g]) for g in ("teeth_upper", "teeth_lower")
                 if g in actor.head.vertex_groups]
        # Inside the mouth, light falls off behind the front of the teeth (or the lips without teeth).
        self.mouth_z = float(actor.canonical[np.concatenate(teeth), 2].max()) if teeth \
            else float(actor.landmarks.mouth_centre[2])
        self.background = torch.tensor(background, dtype=torch.float32)  # [3]
        self.K_hi = scale_intrinsics(camera.K, ssaa)

    @torch.no_grad()
    def render(self, vertices: Tensor, camera: Camera | None = None, lights_on_camera: bool = False
               ) -> tuple[Tensor, Tensor]:
        """vertices [V, 3] world -> image [H, W, 3] in [0, 1] (over the background) and mask [H, W] in [0, 1].

        The lights (appearance.LIGHTING, given in camera axes) are fixed to the room, i.e. to the dataset
        camera `self.camera`: another camera (a novel view) sees the actor lit as the dataset camera's
        frames light it, as a second camera of a capture rig would. With `lights_on_camera` they move with
        `camera` instead (a lamp on the camera; the contact sheet's side views).
        """
        camera = camera or self.camera
        s = self.ssaa
        width, height = camera.width * s, camera.height * s
        K_hi = self.K_hi if camera is self.camera else scale_intrinsics(camera.K, s)
        verts_cam = world_to_camera(vertices.float(), camera.viewmat)  # [V, 3]
        frags = rasterize_mesh(verts_cam, self.faces, K_hi, width, height)
        covered = frags.face_id.reshape(-1) >= 0  # [h*w]
        pix = torch.nonzero(covered).squeeze(1)  # [P]
        fid = frags.face_id.reshape(-1)[pix]  # [P]
        bary = frags.bary.reshape(-1, 3)[pix]  # [P, 3]
        corners = self.faces[fid]  # [P, 3]

        def lerp(attrs: Tensor) -> Tensor:  # [V, C] -> [P, C]
            return (attrs[corners] * bary[:, :, None]).sum(1)

        attrs = lerp(self.vertex_attrs)
        canonical, weights, edge = attrs[:, :3], attrs[:, 3:-1], attrs[:, -1]
        normals = lerp(vertex_normals(verts_cam, self.faces))  # [P, 3]
        position = lerp(verts_cam)  # [P, 3]
        view_dirs = F.normalize(-position, dim=-1)
        geometric = face_normals(verts_cam, self.faces)[fid]  # [P, 3]
        back_facing = ((geometric * view_dirs).sum(-1) < 0) & self.cavity[fid]
        if camera is not self.camera and not lights_on_camera:  # shade in the room's (dataset camera's) axes
            turn = (self.camera.viewmat[:3, :3].double() @ camera.viewmat[:3, :3].double().T).float()  # [3, 3]
            normals, view_dirs = normals @ turn.T, view_dirs @ turn.T
        # Ambient occlusion inside the mouth: darker the further behind the front teeth.
        depth_in = (self.mouth_z - canonical[:, 2]).clamp_min(0.0)  # [P] metres
        mouth_weight = weights[:, _MOUTH_MATERIALS].sum(-1).clamp(0, 1)
        inside = torch.where(back_facing, torch.ones_like(mouth_weight), mouth_weight)
        occlusion = 1.0 - inside * 0.75 * (1.0 - torch.exp(-depth_in / 0.015))
        colour = self.appearance.shade_samples(canonical, weights, edge, normals, view_dirs, back_facing, occlusion)

        image_hi = self.background.expand(height * width, 3).clone()
        image_hi[pix] = colour
        image = box_downsample(image_hi.view(height, width, 3), s)
        mask = box_downsample(covered.view(height, width).float(), s)
        return image, mask


__all__ = ["Camera", "ActorRenderer", "frontal_camera", "orbit_camera"]
