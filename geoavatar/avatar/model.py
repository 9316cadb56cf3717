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
    f_expr     [N, 3K] only with expression blendshapes (avatar/expression.py): colour += E c, E = f_expr as
                       [3, K] and c [K] the frame's expression code (wrinkles, folds, shadows of an expression)
    means_expr [N, 3K] only with expression blendshapes: local mean += M c, M = means_expr as [3, K], in the
                       face-scale units of `means` (what the head model's expression modes do not reach)
Buffers: binding [N] (face index, int64), faces [F, 3].
"""

from __future__ import annotations

import math
import numpy as np
import torch
from torch import Tensor, nn

from geoavatar.avatar.binding import GlobalGaussians, face_frames, local_to_global, polar_coordinates

SH_C0 = 0.28209479177387814  # Y_0^0
GAUSSIAN_PARAM_NAMES = ("means", "quats", "scales", "f_dc", "opacities")
# present only when the avatar has them: f_normal with normal_shading, f_expr / means_expr with expression blendshapes
OPTIONAL_PARAM_NAMES = ("f_normal", "f_expr", "means_expr")


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
                 expression_dims: int = 0, expression_groups: Tensor | None = None, code_masks: Tensor | None = None):
        super().__init__()
        faces = torch.as_tensor(np.asarray(faces) if not isinstance(faces, Tensor) else faces, dtype=torch.long)
        if faces.dim() != 2 or faces.shape[1] != 3:
            raise ValueError(f"GaussianAvatar: faces must be [F, 3], got {tuple(faces.shape)}")
        self.register_buffer("faces", faces)  # [F, 3]
        init = initial_gaussian_params(faces.shape[0], init_opacity)
        if normal_shading:  # no shading at the start: the SH-0 colour alone
            init["f_normal"] = torch.zeros(faces.shape[0], 9)
        if expression_dims > 0:  # zero blendshapes at the start: every expression looks like the neutral avatar
            init["f_expr"] = torch.zeros(faces.shape[0], 3 * expression_dims)
            init["means_expr"] = torch.zeros(faces.shape[0], 3 * expression_dims)
        self.params = nn.ParameterDict({k: nn.Parameter(v) for k, v in init.items()})
        self.register_buffer("binding", torch.arange(faces.shape[0], dtype=torch.long))  # [N]
        # With blendshapes: each face's group [F] (0: the face's skin, 1: the rest) and which code entries drive each
        # group [2, K] (avatar/expression.code_masks; None: every entry drives every Gaussian)
        self.register_buffer("expression_groups", None if expression_groups is None
                             else torch.as_tensor(expression_groups, dtype=torch.long).reshape(-1))
        self.register_buffer("code_masks", None if code_masks is None else torch.as_tensor(code_masks).float())

    @classmethod
    def for_model(cls, head, model) -> "GaussianAvatar":
        """The avatar a `config.ModelConfig` describes, bound to `head`'s faces (one Gaussian per face)."""
        from geoavatar.avatar.expression import code_masks, expression_code_dims, expression_groups

        mode = model.expression_blendshapes
        if mode == "off":
            return cls(head.faces.cpu(), model.init_opacity, model.normal_shading)
        dims = expression_code_dims(head.num_expr)
        return cls(head.faces.cpu(), model.init_opacity, model.normal_shading, dims, expression_groups(head),
                   code_masks(mode, dims))

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

        code [K]: the frame's expression code (avatar/expression.py), used by the expression blendshapes when the
        avatar has them (None: the neutral code, no blendshape); one frame at a time (vertices [V, 3])."""
        frames = face_frames(vertices, self.faces)
        p = self.params
        local_means, colour_offset = p["means"], None
        if code is not None and "f_expr" in p:
            local_means = p["means"] + self.grouped_blendshape(p["means_expr"], code)  # [N, 3]
            colour_offset = self.grouped_blendshape(p["f_expr"], code)  # [N, 3]
        means, quats, scales = local_to_global(local_means, p["quats"], p["scales"], self.binding, frames)
        if "f_normal" in p:
            # The face normal in world axes (detached: shading must not pull the geometry or the tracking).
            normal = frames.rotation[..., self.binding, :, 1].detach()  # [(B,) N, 3]
            shading = (p["f_normal"].view(-1, 3, 3) * normal[..., None, :]).sum(-1)  # [(B,) N, 3]
            colors = SH_C0 * p["f_dc"] + 0.5 + shading
        else:
            colors = SH_C0 * p["f_dc"] + 0.5
        colors = (colors if colour_offset is None else colors + colour_offset).clamp_min(0.0)
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
    def expression_dims(self) -> int:
        """K, the length of the expression code the blendshapes take (0: the avatar has none)."""
        return int(self.params["f_expr"].shape[1]) // 3 if "f_expr" in self.params else 0

    def grouped_blendshape(self, basis: Tensor, code: Tensor) -> Tensor:
        """[N, 3]: each Gaussian's blendshape driven by the code entries its face's group takes (code_masks)."""
        if self.code_masks is None:
            return self.blendshape(basis, code)
        group = self.expression_groups[self.binding][:, None]  # [N, 1]
        face, rest = (self.blendshape(basis, code * mask) for mask in self.code_masks)  # [N, 3] each
        return torch.where(group == 0, face, rest)

    @staticmethod
    def blendshape(basis: Tensor, code: Tensor) -> Tensor:
        """basis [N, 3K], code [K] -> [N, 3]: sum_k code_k basis[:, :, k]."""
        if code.dim() != 1 or basis.shape[1] != 3 * code.shape[0]:
            raise ValueError(f"GaussianAvatar: the expression code must be [{basis.shape[1] // 3}] (one frame), got "
                             f"{tuple(code.shape)}")
        return basis.view(-1, 3, code.shape[0]) @ code.to(basis.dtype)

    def polar(self, two_sided: bool = False) -> tuple[Tensor, Tensor]:
        """r [N], phi [N] of the local means (see binding.polar_coordinates)."""
        return polar_coordinates(self.params["means"], two_sided=two_sided)

    # --- checkpoints: the number of Gaussians changes during training ---------------------------
    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Resize the parameters to the checkpoint's number of Gaussians, then load as usual."""
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
        "f_expr": lr.features,
        "means_expr": lr.position * scene_extent,  # decays with "means" (the trainer sets both)
    }
    return [{"params": [params[name]], "lr": rates[name], "name": name} for name in param_names(params)]


def position_lr(step: int, lr, scene_extent: float) -> float:
    """3DGS's log-linear position learning-rate decay (GaussianAvatars' values; its delay is off)."""
    t = min(max(step / max(lr.position_decay_steps, 1), 0.0), 1.0)
    start, end = lr.position * scene_extent, lr.position_final * scene_extent
    if start <= 0.0 or end <= 0.0:
        return 0.0
    return float(math.exp(math.log(start) * (1 - t) + math.log(end) * t))

