"""GaussianAvatar: the learned Gaussian parameters, their face binding, and forward(vertices).

The module holds only parameters and the binding; densification lives in `densify.py`, APS in
`aps.py`, the mouth MLPs in `deform.py`, the losses in `geoavatar.train.losses`.

Parameters (a ParameterDict `params`, every entry [N, ...], names as in the standard 3DGS PLY):
    means      [N, 3]  local mean, in units of the face scale k
    quats      [N, 4]  local rotation (w, x, y, z), normalised when used
    scales     [N, 3]  local log standard deviation
    f_dc       [N, 3]  SH degree-0 coefficient of the colour (RGB = 0.5 + C0 * f_dc)
    opacities  [N]     opacity logit
    f_normal   [N, 9]  only with normal_shading: colour += F n, F = f_normal as [3, 3] (RGB x xyz) and n the
                       world direction of the Gaussian's face normal (diffuse shading by lights fixed to the
                       world, i.e. to a fixed dataset camera while the head turns)
    f_pose     [N, 18] only with hair_follows_head (avatar/hair_motion.py): colour += C c, C = f_pose as [3, 6]
                       and c [6] the frame's head pose code (head rotation, neck), for Gaussians off the face
    means_pose [N, 18] only with hair_follows_head: local mean += M c, M = means_pose as [3, 6], in the
                       face-scale units of `means` (long hair swinging with the head's turn)
Buffers: binding [N] (face index, int64), faces [F, 3]; with hair_follows_head moving [F] bool (the faces
whose Gaussians take the pose code) and pose_range [2, 6] (the training frames' smallest and largest code, to which
every code is clamped: M and C were fitted inside that box, and beyond it the linear offsets would carry the hair
off the head; absent in runs trained before it, whose codes are used as they are).
"""

from __future__ import annotations

import math
import numpy as np
import torch
from torch import Tensor, nn

from geoavatar.avatar.binding import GlobalGaussians, face_frames, local_to_global, polar_coordinates
from geoavatar.avatar.hair_motion import POSE_CODE_DIM

SH_C0 = 0.28209479177387814  # Y_0^0
GAUSSIAN_PARAM_NAMES = ("means", "quats", "scales", "f_dc", "opacities")
# present only when the avatar has them: f_normal with normal_shading, f_pose / means_pose with hair_follows_head
OPTIONAL_PARAM_NAMES = ("f_normal", "f_pose", "means_pose")


def param_names(params) -> tuple[str, ...]:
    """The Gaussian parameters `params` holds, in a fixed order (GAUSSIAN_PARAM_NAMES, then optional ones)."""
    return GAUSSIAN_PARAM_NAMES + tuple(name for name in OPTIONAL_PARAM_NAMES if name in params)


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(f_dc: Tensor) -> Tensor:
    return (SH_C0 * f_dc + 0.5).clamp_min(0.0)  # as 3DGS/gsplat: no upper clamp before blending


def initial_gaussian_params(num_faces: int, init_opacity: float = 0.1, device=None) -> dict[str, Tensor]:
    """One Gaussian per face: local mean 0, log-scale 0, identity rotation, grey, opacity `init_opacity`."""
    if num_faces < 1:
        raise ValueError(f"initial_gaussian_params: the head model has no faces (num_faces={num_faces})")
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"initial_gaussian_params: init_opacity must lie in (0, 1), got {init_opacity}")
    quats = torch.zeros(num_faces, 4, device=device)
    quats[:, 0] = 1.0
    return {
        "means": torch.zeros(num_faces, 3, device=device),
        "quats": quats,
        "scales": torch.zeros(num_faces, 3, device=device),
        "f_dc": torch.zeros(num_faces, 3, device=device),
        "opacities": torch.full((num_faces,), math.log(init_opacity / (1.0 - init_opacity)), device=device),
    }


class GaussianAvatar(nn.Module):
    """Gaussians rigged to the faces of a head model."""

    def __init__(self, faces: Tensor | np.ndarray, init_opacity: float = 0.1, normal_shading: bool = False,
                 moving: Tensor | None = None):
        super().__init__()
        faces = torch.as_tensor(np.asarray(faces) if not isinstance(faces, Tensor) else faces, dtype=torch.long)
        if faces.dim() != 2 or faces.shape[1] != 3:
            raise ValueError(f"GaussianAvatar: faces must be [F, 3], got {tuple(faces.shape)}")
        self.register_buffer("faces", faces)  # [F, 3]
        init = initial_gaussian_params(faces.shape[0], init_opacity)
        if normal_shading:  # no shading at the start: the SH-0 colour alone
            init["f_normal"] = torch.zeros(faces.shape[0], 9)
        if moving is not None:  # zero at the start: every head pose shows the same hair
            init["f_pose"] = torch.zeros(faces.shape[0], 3 * POSE_CODE_DIM)
            init["means_pose"] = torch.zeros(faces.shape[0], 3 * POSE_CODE_DIM)
        self.params = nn.ParameterDict({k: nn.Parameter(v) for k, v in init.items()})
        self.register_buffer("binding", torch.arange(faces.shape[0], dtype=torch.long))  # [N]
        # [F] bool: the faces whose Gaussians follow the head's turn (avatar/hair_motion.moving_faces); None: none
        self.register_buffer("moving", None if moving is None else torch.as_tensor(moving, dtype=torch.bool).reshape(-1))
        self.register_buffer("pose_range", None)  # [2, 6] set by set_pose_range (training); None: codes unclamped

    @classmethod
    def for_model(cls, head, model) -> "GaussianAvatar":
        """The avatar a `config.ModelConfig` describes, bound to `head`'s faces (one Gaussian per face)."""
        from geoavatar.avatar.hair_motion import moving_faces

        moving = moving_faces(head) if model.hair_follows_head else None
        return cls(head.faces.cpu(), model.init_opacity, model.normal_shading, moving)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.binding.shape[0])

    def gaussians_per_face(self) -> Tensor:
        """[F] number of Gaussians bound to each face."""
        return torch.bincount(self.binding, minlength=self.num_faces)

    def forward(self, vertices: Tensor, code: Tensor | None = None) -> GlobalGaussians:
        """vertices [V, 3] or [B, V, 3] posed head vertices -> Gaussians in the same space ([N,...] or [B,N,...]).

        code [6]: the frame's head pose code (avatar/hair_motion.head_pose_code), which moves the Gaussians off the
        face when the avatar follows the head's turn (None: the code 0, the hair as learned at the rest pose); one
        frame at a time (vertices [V, 3])."""
        frames = face_frames(vertices, self.faces)
        p = self.params
        local_means = p["means"]
        colors = SH_C0 * p["f_dc"] + 0.5  # [N, 3], clamped once every term is in (3DGS: no upper clamp)
        if code is not None and self.follows_head:
            mean_offset, colour_offset = self.pose_offsets(code)  # [N, 3] each
            local_means, colors = local_means + mean_offset, colors + colour_offset
        means, quats, scales = local_to_global(local_means, p["quats"], p["scales"], self.binding, frames)
        if "f_normal" in p:
            # The face normal in world axes (detached: shading must not pull the geometry or the tracking).
            # The face normals gathered once per Gaussian, then one batched 3x3 product: half the time of a broadcast
            # multiply and sum over [N, 3, 3] (~4 ms a step at 66k Gaussians on one core).
            normal = frames.rotation[..., 1].detach().contiguous().index_select(-2, self.binding)  # [(B,) N, 3]
            colors = colors + torch.matmul(p["f_normal"].view(-1, 3, 3), normal[..., None])[..., 0]  # [(B,) N, 3]
        colors = colors.clamp_min(0.0)
        return GlobalGaussians(
            means=means,
            quats=quats,
            scales=scales,
            opacities=torch.sigmoid(p["opacities"]),
            colors=colors,
            frames=frames,
        )

    @property
    def normal_shading(self) -> bool:
        return "f_normal" in self.params

    @property
    def follows_head(self) -> bool:
        """Whether the Gaussians off the face move with the head pose code (model.hair_follows_head)."""
        return "f_pose" in self.params

    def set_pose_range(self, codes: Tensor) -> None:
        """Keep the smallest and largest of the training frames' head pose codes [M, 6] (pose_range)."""
        codes = codes.detach().reshape(-1, POSE_CODE_DIM).to(self.binding.device, torch.float32)  # [M, 6]
        self.pose_range = torch.stack([codes.min(0).values, codes.max(0).values])  # [2, 6]

    def clamp_pose_code(self, code: Tensor) -> Tensor:
        """code [6] clamped to the training frames' range (pose_range); unchanged when the run has none."""
        if self.pose_range is None:
            return code
        low, high = self.pose_range.to(code)
        return torch.minimum(torch.maximum(code, low), high)

    def pose_offsets(self, code: Tensor) -> tuple[Tensor, Tensor]:
        """code [6] -> the local mean and colour offsets [N, 3] each: sum_k code_k basis[:, :, k] of means_pose and
        f_pose for the moving faces' Gaussians, 0 elsewhere, the code clamped to pose_range."""
        if code.shape != (POSE_CODE_DIM,):
            raise ValueError(f"GaussianAvatar: the head pose code must be [{POSE_CODE_DIM}] (one frame), got "
                             f"{tuple(code.shape)}")
        code = self.clamp_pose_code(code)
        moving = self.moving[self.binding][:, None]  # [N, 1]
        return tuple(self.params[name].view(-1, 3, POSE_CODE_DIM) @ code.to(self.params[name].dtype) * moving
                     for name in ("means_pose", "f_pose"))

    def polar(self, two_sided: bool = False) -> tuple[Tensor, Tensor]:
        """r [N], phi [N] of the local means (see binding.polar_coordinates)."""
        return polar_coordinates(self.params["means"], two_sided=two_sided)

    # --- checkpoints: the number of Gaussians changes during training ---------------------------
    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Resize the parameters to the checkpoint's number of Gaussians, then load as usual (a run trained before
        pose_range loads without it)."""
        has_range = "pose_range" in state_dict
        self.pose_range = torch.empty(2, POSE_CODE_DIM, device=self.binding.device) if has_range else None
        key = "binding"
        if key in state_dict:
            n = int(state_dict[key].shape[0])
            device = self.binding.device
            for name in param_names(self.params):
                saved = state_dict.get(f"params.{name}")
                if saved is None:
                    continue
                if saved.shape[1:] != self.params[name].shape[1:] or saved.shape[0] != n:
                    raise ValueError(
                        f"avatar checkpoint: 'params.{name}' has shape {tuple(saved.shape)}, expected "
                        f"[{n}, {', '.join(map(str, self.params[name].shape[1:]))}]"
                    )
                self.params[name] = nn.Parameter(torch.empty_like(saved, device=device))
            self.binding = torch.empty(n, dtype=torch.long, device=device)
            binding = state_dict[key]
            if n and (int(binding.min()) < 0 or int(binding.max()) >= self.num_faces):
                raise ValueError(f"avatar checkpoint: 'binding' refers to faces outside [0, {self.num_faces})")
        return super().load_state_dict(state_dict, strict=strict, assign=assign)


def gaussian_param_groups(params: dict[str, Tensor] | nn.ParameterDict, lr, scene_extent: float) -> list[dict]:
    """Adam parameter groups for the Gaussian parameters (one tensor per group, named), as GaussianAvatars.

    lr: a `geoavatar.config.LearningRates`. The position learning rate is scaled by the scene extent.
    """
    rates = {
        "means": lr.position * scene_extent,
        "quats": lr.rotation,
        "scales": lr.scaling,
        "f_dc": lr.features,
        "opacities": lr.opacity,
        "f_normal": lr.features,
        "f_pose": lr.features,
        "means_pose": lr.position * scene_extent,  # decays with "means" (the trainer sets both)
    }
    return [{"params": [params[name]], "lr": rates[name], "name": name} for name in param_names(params)]


def position_lr(step: int, lr, scene_extent: float) -> float:
    """3DGS's log-linear position learning-rate decay (GaussianAvatars' values; its delay is off)."""
    t = min(max(step / max(lr.position_decay_steps, 1), 0.0), 1.0)
    start, end = lr.position * scene_extent, lr.position_final * scene_extent
    if start <= 0.0 or end <= 0.0:
        return 0.0
    return float(math.exp(math.log(start) * (1 - t) + math.log(end) * t))

