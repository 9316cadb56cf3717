"""Adaptive density control for Gaussians bound to faces (clone, split, prune, opacity reset).

gsplat "strategy" style: plain functions acting on a dict of parameters (`params`, every entry
[N, ...], e.g. `GaussianAvatar.params`), the Adam optimizer(s) holding them, the binding [N] and a
statistics dict `state` {grad2d [N], count [N], max_radii [N]}. Every function keeps the three in
step: new Gaussians get zero Adam moments, removed ones lose theirs.

Binding rules (GaussianAvatars): children inherit their parent's face; pruning never removes the
last Gaussian of a face (of the Gaussians a face would lose entirely, the most opaque one stays).

Where we differ from GaussianAvatars' code, on purpose:
- split samples the children in the parent's *local* frame around the parent's local mean:
  mu_child = mu + R(q) (exp(s) * eps), eps ~ N(0, I). GaussianAvatars draws the offset with the
  *global* scale and drops the parent's local mean (children land around the face centre).
- the last Gaussian of a face that would be pruned entirely is chosen by opacity (GaussianAvatars
  keeps all of them in that case).

The densification decision uses world-space sizes (k * exp(s), with the face scale k of the last
rendered frame) against `percent_dense * scene_extent`, and the mean screen-space gradient norm in
NDC units (the renderer's pixel-space means2d gradient times width/2, height/2, as gsplat does to
match 3DGS's threshold 2e-4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, MutableMapping, NamedTuple, Optional, Union

import torch
from torch import Tensor, nn

from geoavatar.avatar.model import GAUSSIAN_PARAM_NAMES, param_names
from geoavatar.config import DensifyConfig
from geoavatar.geometry import quaternion_to_matrix

Params = MutableMapping[str, Tensor]
Optimizers = Optional[Union[torch.optim.Optimizer, Iterable[torch.optim.Optimizer]]]
STATE_KEYS = ("grad2d", "count", "max_radii")


def _optimizers(optimizers: Optimizers) -> list[torch.optim.Optimizer]:
    if optimizers is None:
        return []
    if isinstance(optimizers, torch.optim.Optimizer):
        return [optimizers]
    return list(optimizers)


def new_state(num_gaussians: int, device=None) -> dict[str, Tensor]:
    """Empty densification statistics for `num_gaussians` Gaussians."""
    return {key: torch.zeros(num_gaussians, device=device) for key in STATE_KEYS}


def scene_extent(camera_centres: Tensor, minimum: float = 1.0) -> float:
    """3DGS/GaussianAvatars scene extent: 1.1 x the largest camera distance from the cameras' mean.

    camera_centres: [C, 3]. A monocular video has one camera (extent 0), hence the floor `minimum`.
    """
    centres = camera_centres.reshape(-1, 3)
    spread = (centres - centres.mean(0)).norm(dim=-1).max() if centres.shape[0] else torch.tensor(0.0)
    return max(1.1 * float(spread), float(minimum))


# --- optimizer surgery ------------------------------------------------------------------------


@torch.no_grad()
def _replace_param(
    params: Params,
    optimizers: list[torch.optim.Optimizer],
    name: str,
    new_value: Tensor,
    edit_state: Callable[[Tensor], Tensor],
) -> None:
    """Swap params[name] for a new Parameter holding `new_value`; edit its Adam moments the same way."""
    old = params[name]
    new = nn.Parameter(new_value, requires_grad=old.requires_grad)
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            for i, p in enumerate(group["params"]):
                if p is not old:
                    continue
                group["params"][i] = new
                state = optimizer.state.pop(old, None)
                if state is not None:
                    for key, value in state.items():
                        # exp_avg, exp_avg_sq (and max_exp_avg_sq) are shaped like the parameter; 'step' is not
                        if torch.is_tensor(value) and value.shape == old.shape:
                            state[key] = edit_state(value)
                    optimizer.state[new] = state
    params[name] = new


def _num(params: Params) -> int:
    return int(params[GAUSSIAN_PARAM_NAMES[0]].shape[0])


def _check(params: Params, binding: Tensor, state: dict[str, Tensor] | None) -> None:
    n = int(binding.shape[0])
    for name in param_names(params):
        if name not in params:
            raise KeyError(f"densify: parameter '{name}' missing (have {sorted(params)})")
        if params[name].shape[0] != n:
            raise ValueError(f"densify: params['{name}'] has {params[name].shape[0]} rows, binding has {n}")
    for key, value in (state or {}).items():
        if value.shape[0] != n:
            raise ValueError(f"densify: state['{key}'] has {value.shape[0]} rows, binding has {n}")


def append_gaussians(
    params: Params,
    optimizers: Optimizers,
    binding: Tensor,
    new_values: dict[str, Tensor],
    new_binding: Tensor,
    state: dict[str, Tensor] | None = None,
) -> Tensor:
    """Append Gaussians (zero Adam moments, zero statistics). Returns the new binding [N + M]."""
    opts = _optimizers(optimizers)
    for name in param_names(params):
        extra = new_values[name].to(params[name])
        _replace_param(
            params, opts, name, torch.cat([params[name].detach(), extra]),
            lambda moment, extra=extra: torch.cat([moment, torch.zeros_like(extra)]),
        )
    if state is not None:
        for key in list(state):
            state[key] = torch.cat([state[key], state[key].new_zeros(new_binding.shape[0])])
    return torch.cat([binding, new_binding.to(binding)])


def keep_gaussians(
    params: Params, optimizers: Optimizers, binding: Tensor, keep: Tensor, state: dict[str, Tensor] | None = None
) -> Tensor:
    """Keep the Gaussians where keep [N] is True (parameters, Adam moments, statistics). Returns binding."""
    opts = _optimizers(optimizers)
    for name in param_names(params):
        _replace_param(params, opts, name, params[name].detach()[keep], lambda moment: moment[keep])
    if state is not None:
        for key in list(state):
            state[key] = state[key][keep]
    return binding[keep]


# --- the operations ---------------------------------------------------------------------------


@torch.no_grad()
def clone_gaussians(
    params: Params, optimizers: Optimizers, binding: Tensor, mask: Tensor, state: dict[str, Tensor] | None = None
) -> Tensor:
    """Duplicate the Gaussians in mask [N] (same local parameters, same face). Returns binding [N + M]."""
    _check(params, binding, state)
    new = {name: params[name].detach()[mask] for name in param_names(params)}
    return append_gaussians(params, optimizers, binding, new, binding[mask], state)


@torch.no_grad()
def split_gaussians(
    params: Params,
    optimizers: Optimizers,
    binding: Tensor,
    mask: Tensor,
    state: dict[str, Tensor] | None = None,
    children: int = 2,
    shrink: float = 0.8,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Replace each Gaussian in mask [N] by `children` smaller ones sampled inside it (local frame).

    Children: mu + R(q) (exp(s) * eps), log-scale s - log(shrink * children), the parent's
    rotation, colour, opacity and face. Returns the binding [N - M + children * M].
    """
    _check(params, binding, state)
    n = _num(params)
    parent_means = params["means"].detach()[mask]  # [M, 3]
    parent_scales = params["scales"].detach()[mask]  # [M, 3]
    rot = quaternion_to_matrix(params["quats"].detach()[mask])  # [M, 3, 3]
    eps = torch.randn(
        (children, *parent_means.shape), generator=generator, device=parent_means.device, dtype=parent_means.dtype
    )  # [children, M, 3]
    offsets = (rot[None] @ (torch.exp(parent_scales)[None] * eps)[..., None]).squeeze(-1)
    new = {
        "means": (parent_means[None] + offsets).reshape(-1, 3),
        "scales": (parent_scales - math.log(shrink * children)).repeat(children, 1),
    }
    for name in (n for n in param_names(params) if n not in ("means", "scales")):
        value = params[name].detach()[mask]
        new[name] = value.repeat(children, *([1] * (value.dim() - 1)))
    binding = append_gaussians(params, optimizers, binding, new, binding[mask].repeat(children), state)
    keep = torch.ones(binding.shape[0], dtype=torch.bool, device=binding.device)
    keep[:n] = ~mask
    return keep_gaussians(params, optimizers, binding, keep, state)


def protect_last_of_each_face(prune: Tensor, binding: Tensor, num_faces: int, score: Tensor) -> Tensor:
    """prune [N] with, for every face that would lose all its Gaussians, its best-`score` Gaussian spared."""
    kept_per_face = torch.bincount(binding[~prune], minlength=num_faces)  # [F]
    orphaned = kept_per_face[binding] == 0  # [N] Gaussians of faces that would end up empty
    if not bool(orphaned.any()):
        return prune
    candidates = torch.nonzero(orphaned).squeeze(-1)  # [M]
    # Sort candidates by face, best score first inside each face; the first of each face survives.
    order = torch.argsort(score[candidates], descending=True, stable=True)
    candidates = candidates[order]
    candidates = candidates[torch.argsort(binding[candidates], stable=True)]
    faces = binding[candidates]
    first = torch.ones_like(faces, dtype=torch.bool)
    first[1:] = faces[1:] != faces[:-1]
    result = prune.clone()
    result[candidates[first]] = False
    return result


@torch.no_grad()
def prune_gaussians(
    params: Params,
    optimizers: Optimizers,
    binding: Tensor,
    mask: Tensor,
    num_faces: int,
    state: dict[str, Tensor] | None = None,
) -> Tensor:
    """Remove the Gaussians in mask [N], except the last one of any face. Returns the binding."""
    _check(params, binding, state)
    mask = protect_last_of_each_face(mask, binding, num_faces, params["opacities"].detach())
    return keep_gaussians(params, optimizers, binding, ~mask, state)


@torch.no_grad()
def reset_opacity(params: Params, optimizers: Optimizers, max_opacity: float = 0.01) -> None:
    """Clamp every opacity to at most `max_opacity` and zero its Adam moments (3DGS)."""
    logit_max = math.log(max_opacity / (1.0 - max_opacity))
    new = params["opacities"].detach().clamp_max(logit_max)
    _replace_param(params, _optimizers(optimizers), "opacities", new, torch.zeros_like)


# --- statistics and the schedule --------------------------------------------------------------


@torch.no_grad()
def accumulate_stats(
    state: dict[str, Tensor],
    means2d_grad: Tensor,  # [N, 2] or [C, N, 2] gradient of the loss w.r.t. the projected means, in pixels
    visible: Tensor,  # [N] or [C, N] bool (e.g. radii > 0)
    width: int,
    height: int,
    radii: Tensor | None = None,  # [N], [N, 2], [C, N] or [C, N, 2] screen radii in pixels
) -> None:
    """Add this step's screen-space gradient norms (NDC units, as 3DGS) and max radii to `state`."""
    grad = means2d_grad.detach().reshape(-1, means2d_grad.shape[-2], 2).clone()  # [C, N, 2]
    vis = visible.reshape(-1, visible.shape[-1])  # [C, N]
    if grad.shape[:2] != vis.shape:
        raise ValueError(f"accumulate_stats: means2d_grad {tuple(means2d_grad.shape)} and visible "
                         f"{tuple(visible.shape)} disagree")
    if state["grad2d"].shape[0] != vis.shape[1]:
        raise ValueError(f"accumulate_stats: state holds {state['grad2d'].shape[0]} Gaussians, gradients {vis.shape[1]}")
    grad[..., 0] *= width / 2.0
    grad[..., 1] *= height / 2.0
    norms = grad.norm(dim=-1) * vis  # [C, N]
    state["grad2d"] += norms.sum(0).to(state["grad2d"])
    state["count"] += vis.sum(0).to(state["count"])
    if radii is not None:
        r = radii.detach()
        if r.shape[-1] == 2 and r.dim() >= 2 and r.shape[-2] == vis.shape[1]:
            r = r.amax(-1)  # gsplat >= 1.5 gives per-axis radii
        r = (r.reshape(-1, vis.shape[1]).to(state["max_radii"]) * vis).amax(0)
        state["max_radii"] = torch.maximum(state["max_radii"], r)


@torch.no_grad()
def densify_and_prune(
    params: Params,
    optimizers: Optimizers,
    binding: Tensor,
    state: dict[str, Tensor],
    cfg: DensifyConfig,
    step: int,
    face_scale: Tensor,  # [F] face scales k of the last rendered frame
    extent: float,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, dict[str, int]]:
    """Clone small / split large Gaussians with a high mean gradient, then prune. Returns (binding, counts)."""
    _check(params, binding, state)
    num_faces = int(face_scale.shape[-1])
    grads = state["grad2d"] / state["count"].clamp_min(1)
    high = grads >= cfg.grad_threshold
    world_size = (torch.exp(params["scales"].detach()) * face_scale.reshape(-1)[binding, None]).amax(-1)
    small = world_size <= cfg.percent_dense * extent
    clone_mask, split_mask = high & small, high & ~small
    n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())

    binding = clone_gaussians(params, optimizers, binding, clone_mask, state)
    split_mask = torch.cat([split_mask, split_mask.new_zeros(n_clone)])
    binding = split_gaussians(
        params, optimizers, binding, split_mask, state, cfg.split_children, cfg.split_shrink, generator
    )

    prune = torch.sigmoid(params["opacities"].detach()) < cfg.prune_opacity
    if step > cfg.reset_opacity_every:
        world_size = (torch.exp(params["scales"].detach()) * face_scale.reshape(-1)[binding, None]).amax(-1)
        prune |= state["max_radii"] > cfg.max_screen_size
        prune |= world_size > cfg.max_world_size * extent
    before = int(binding.shape[0])
    binding = prune_gaussians(params, optimizers, binding, prune, num_faces, state)
    for key in state:
        state[key].zero_()
    return binding, {"cloned": n_clone, "split": n_split, "pruned": before - int(binding.shape[0]),
                     "total": int(binding.shape[0])}


class DensifyInfo(NamedTuple):
    """What one rendered step tells densification (gsplat's `info`)."""

    binding: Tensor  # [N] face of each Gaussian
    face_scale: Tensor  # [F] face scales k of the rendered frame
    means2d_grad: Tensor | None = None  # [N, 2] pixels; None: no statistics this step
    visible: Tensor | None = None  # [N] bool
    radii: Tensor | None = None  # [N] or [N, 2] pixels
    width: int = 0
    height: int = 0


@dataclass
class DensifyStrategy:
    """GaussianAvatars' schedule as a gsplat-style strategy: what is fixed for a run (the schedule and thresholds,
    the scene extent, the generator of split samples) is the strategy; `step_post_backward(params, optimizers,
    state, step, info)` acts on one step."""

    config: DensifyConfig
    extent: float
    generator: torch.Generator | None = None

    @torch.no_grad()
    def step_post_backward(
        self, params: Params, optimizers: Optimizers, state: dict[str, Tensor], step: int, info: DensifyInfo,
    ) -> tuple[Tensor, dict[str, int] | None]:
        """One step's work (after backward; the trainer runs it after the optimizer step, see train/trainer.py).

        Accumulates statistics while step < stop; densifies+prunes when start < step < stop and
        step % every == 0; resets opacities when step % reset_opacity_every == 0 (while densifying).
        Returns the (possibly new) binding and the densification counts when it densified, else None.
        """
        cfg, binding = self.config, info.binding
        if step >= cfg.stop:
            return binding, None
        report = None
        if info.means2d_grad is not None and info.visible is not None:
            accumulate_stats(state, info.means2d_grad, info.visible, info.width, info.height, info.radii)
        if step > cfg.start and step % cfg.every == 0:
            binding, report = densify_and_prune(params, optimizers, binding, state, cfg, step, info.face_scale,
                                                self.extent, self.generator)
        if step % cfg.reset_opacity_every == 0:
            reset_opacity(params, optimizers, cfg.reset_opacity_value)
        return binding, report
