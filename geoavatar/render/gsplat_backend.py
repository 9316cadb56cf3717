"""gsplat backend: CUDA only. gsplat's first kernel call JIT-builds its CUDA extension, which fails
without a GPU, so nothing here is imported or called unless the tensors are on a CUDA device."""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from geoavatar.render.torch_backend import EPS2D, FAR_PLANE, NEAR_PLANE


@functools.lru_cache(maxsize=1)
def gsplat_available() -> bool:
    """True when CUDA is available and gsplat imports (importing it does not build anything)."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a broken install (gsplat imports `packaging` undeclared)
        return False
    return True


def rasterize_gsplat(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    viewmats: Tensor,  # [C, 4, 4]
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    backgrounds: Tensor,  # [C, 3]
    batched: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Same outputs as torch_backend.rasterize_torch, from gsplat.rasterization (classic mode, unpacked)."""
    if means.device.type != "cuda":
        raise ValueError(f"backend 'gsplat' needs CUDA tensors; means is on {means.device}")
    if means.dtype != torch.float32:
        raise ValueError(f"backend 'gsplat' needs float32 tensors; means is {means.dtype}")
    if not gsplat_available():
        raise RuntimeError("backend 'gsplat' requested but gsplat cannot be imported (pip install gsplat==1.5.3 packaging)")
    from gsplat import rasterization

    rgb, alpha, meta = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane=NEAR_PLANE, far_plane=FAR_PLANE, eps2d=EPS2D, radius_clip=0.0,
        packed=False,  # so means2d is [C, N, 2], one row per input Gaussian
        backgrounds=backgrounds, rasterize_mode="classic", absgrad=False,
    )
    means2d = meta["means2d"]  # [C, N, 2]
    if means2d.requires_grad:
        means2d.retain_grad()
        if not batched:
            means2d = _gradient_mirror(means2d, 0)
    radii = meta["radii"].to(torch.int32)  # [C, N, 2]
    visible = (radii > 0).all(-1)
    return rgb, alpha, means2d, radii, visible, meta["depths"].detach()


def _gradient_mirror(batch: Tensor, index: int) -> Tensor:
    """A [N, 2] leaf equal to batch[index] whose .grad receives batch.grad[index] on every backward.

    gsplat consumes its own [C, N, 2] means2d internally, so a slice taken afterwards would not be on
    the gradient path; a hook copies the slice of the gradient instead.
    """
    mirror = batch.detach()[index].clone().requires_grad_(True)

    def copy_gradient(grad: Tensor) -> None:
        part = grad[index].detach()
        mirror.grad = part.clone() if mirror.grad is None else mirror.grad + part

    batch.register_hook(copy_gradient)
    return mirror
