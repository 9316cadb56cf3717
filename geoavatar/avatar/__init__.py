"""AVATAR layer: Gaussians bound to head-model faces, local <-> global, densify/prune with binding
inheritance, the Adaptive Pre-allocation Stage, and the part-wise mouth deformation MLPs.

    frames = face_frames(vertices, faces)                       # R [F,3,3], C [F,3], k [F]
    means, quats, scales = local_to_global(mu, q, s, binding, frames)
    avatar = GaussianAvatar(head.faces); gaussians = avatar(vertices)   # GlobalGaussians
    deformer = MouthDeformer.for_head(head, num_frames); out = posed_head(head, params, deformer, T)
    frame = render_avatar(avatar, head, params, camera, T, deformer, background)  # AvatarRender
"""

from geoavatar.avatar.aps import APSState, assign_parts, face_set_ids, part_distances
from geoavatar.avatar.binding import FaceFrames, GlobalGaussians, face_frames, local_to_global, polar_coordinates
from geoavatar.avatar.deform import (MouthDeformer, TimestepMode, frame_timestep, positional_encoding, pose_vector,
                                    posed_head)
from geoavatar.avatar.model import GAUSSIAN_PARAM_NAMES, GaussianAvatar, gaussian_param_groups, position_lr
from geoavatar.avatar.render import AvatarRender, PosedAvatar, pose_avatar, rasterize_gaussians, render_avatar

__all__ = [
    "APSState", "assign_parts", "face_set_ids", "part_distances",
    "FaceFrames", "GlobalGaussians", "face_frames", "local_to_global", "polar_coordinates",
    "MouthDeformer", "TimestepMode", "frame_timestep", "positional_encoding", "pose_vector", "posed_head",
    "AvatarRender", "PosedAvatar", "pose_avatar", "rasterize_gaussians", "render_avatar",
    "GAUSSIAN_PARAM_NAMES", "GaussianAvatar", "gaussian_param_groups", "position_lr",
]
