"""Native CPU backend ("cpu") of rasterize(): projection and rasterize-to-pixels in C++.

The split is gsplat's: a projection step (EWA, Jacobian clamp, 0.3 px dilation, opacity-aware radii,
near plane: the rules and operation order of torch_backend.project_gaussians, with a hand-written
backward to means/quats/scales), then the per-pixel work (tile binning, per-tile depth order,
front-to-back compositing with the 1/255, 0.999 and T <= 1e-4 rules, and the back-to-front
backward). Both run in csrc/rasterize_cpu.cpp on OpenMP threads (torch.get_num_threads() of them,
dynamic over tiles). Projection is native because in PyTorch its many small ops cost as much as the
kernel itself (measured: 44 ms of 119 ms forward+backward at 256²/50k on one thread); when viewmat or
K need gradients, the differentiable torch projection is used instead. means2d.grad (densification)
is the gradient the kernel returns for the screen-space means. For float32 inputs forward and backward
composite a Gaussian over several pixels of a row per step (GCC/Clang vector types, one source compiled
for AVX-512, AVX2 and the baseline ISA, "vector": NEON on ARM; picked at run time, see SIMD_ENV and
simd_path()); float64 inputs take the per-pixel loop.

The extension is built on first use and cached by geoavatar.native (g++ and ninja; under a minute on our
machines); without a compiler, or when the build fails, `load_extension()` warns once and returns None, and
rasterize(backend="auto") then uses the torch backend.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType
from typing import Optional

import torch
from torch import Tensor

from geoavatar import native
from geoavatar.native import ExtensionSpec
from geoavatar.render.torch_backend import Projection, project_gaussians, render_cameras

# 32: with the AVX-512 kernel's 4 x 4 blocks the pixel work does not depend on the tile size, larger tiles
# cut the (tile, Gaussian) entries and their per-entry costs (100k Gaussians at 256 px: 204k -> 146k
# entries, fwd + bwd -8 % at 1 thread, also at 512 px); tiles go to the threads largest first, which keeps
# the 64 tiles of a 256 px image balanced over 2 threads (rasterize_cpu.cpp, tiles_by_work).
DEFAULT_TILE_SIZE = 32
# Selects the float32 compositing path: "auto" (the fastest this CPU runs), "avx512", "avx2", "vector"
# (lanes of a row per step, float32 state; "vector" is the build's baseline ISA: NEON on aarch64, SSE2 on
# x86-64, where it is selectable for testing) or "scalar" (the per-pixel loop with libm's exp and double
# state, the kernel before the SIMD paths; float64 inputs always use it).
SIMD_ENV = "GEOAVATAR_CPU_SIMD"

_EXTENSION = ExtensionSpec(
    name="rasterize_cpu", source=Path(__file__).with_name("csrc") / "rasterize_cpu.cpp",
    what="the native CPU rasterizer (backend 'cpu')", instead="rendering on CPU uses the slower PyTorch backend")
_state = native.new_state()


def load_extension(verbose: bool = False) -> Optional[ModuleType]:
    """The compiled kernel module (built on first use, then loaded from the cache), or None with one
    warning when it cannot be built. Safe to call from several threads; later calls are free."""
    return native.load_extension(_EXTENSION, _state, verbose)


def cpu_backend_available() -> bool:
    """True when the native kernel is built and loaded (builds it on the first call)."""
    return load_extension() is not None


def simd_path() -> str:
    """The float32 compositing path in use: $GEOAVATAR_CPU_SIMD when set (and not "auto"), else the
    fastest one this CPU runs ("avx512", "avx2", "vector" or "scalar")."""
    ext = load_extension()
    if ext is None:
        raise RuntimeError(f"rasterize: backend 'cpu' is unavailable: {cpu_backend_error()}")
    paths = ext.simd_paths()
    requested = os.environ.get(SIMD_ENV, "auto").strip().lower() or "auto"
    if requested == "auto":
        return paths[0]
    if requested not in paths:
        raise ValueError(f"{SIMD_ENV}={requested!r}: this CPU runs {', '.join(paths)} (or auto)")
    return requested


def cpu_backend_error() -> Optional[str]:
    """Why the native kernel is unavailable (None when it loaded or was not tried yet)."""
    return _state["error"]


class _RasterizeToPixels(torch.autograd.Function):
    """Native tile compositing of projected Gaussians with a native backward."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, background, radii, depths, width, height, tile_size):
        ext = load_extension()
        args = [t.detach().contiguous() for t in (means2d, conics, opacities, colors, background)]
        radii, depths = radii.contiguous(), depths.detach().contiguous()
        simd = simd_path()
        rgb, alpha, *state = ext.forward(*args, radii, depths, width, height, tile_size, simd)
        # state: tile offsets, ids, last, t_final, splat records, entry slots, firsts (see forward in csrc)
        ctx.save_for_backward(*args, *state)
        ctx.geometry = (width, height, tile_size, simd)
        return rgb, alpha

    @staticmethod
    def backward(ctx, grad_rgb, grad_alpha):
        means2d, conics, opacities, colors, background, offsets, ids, last, t_final, splats, slots, firsts = (
            ctx.saved_tensors)
        width, height, tile_size, simd = ctx.geometry
        dtype = means2d.dtype
        grad_rgb = grad_rgb.to(dtype).contiguous()  # [H, W, 3]
        grad_alpha = grad_alpha.to(dtype).contiguous()  # [H, W, 1]
        g_means2d, g_conics, g_opacities, g_colors = load_extension().backward(
            means2d, conics, opacities, colors, background, splats, offsets, ids, slots, firsts, last, t_final,
            grad_rgb, grad_alpha, width, height, tile_size, simd,
        )
        g_background = (t_final.to(dtype)[..., None] * grad_rgb).sum((0, 1))  # [3]
        return g_means2d, g_conics, g_opacities, g_colors, g_background, None, None, None, None, None


class _ProjectGaussians(torch.autograd.Function):
    """Native projection of one camera; backward to means, quats and scales (not viewmat or K)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height):
        ext = load_extension()
        args = [t.detach().contiguous() for t in (means, quats, scales, opacities, viewmat, K)]
        means2d, conics, depths, radii, visible = ext.project(*args, width, height)
        ctx.save_for_backward(args[0], args[1], args[2], args[4], args[5], visible)
        ctx.size = (width, height)
        ctx.mark_non_differentiable(depths, radii, visible)
        return means2d, conics, depths, radii, visible

    @staticmethod
    def backward(ctx, g_means2d, g_conics, _g_depths, _g_radii, _g_visible):
        means, quats, scales, viewmat, K, visible = ctx.saved_tensors
        dtype = means.dtype
        g_means2d = torch.zeros_like(means[:, :2]) if g_means2d is None else g_means2d.to(dtype).contiguous()
        g_conics = torch.zeros_like(means) if g_conics is None else g_conics.to(dtype).contiguous()
        g_means, g_quats, g_scales = load_extension().project_backward(
            means, quats, scales, viewmat, K, visible, g_means2d, g_conics, *ctx.size
        )
        return g_means, g_quats, g_scales, None, None, None, None, None


def project_gaussians_cpu(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
) -> Projection:
    """torch_backend.project_gaussians in C++ (same outputs); the torch one when viewmat/K need grads."""
    if viewmat.requires_grad or K.requires_grad:
        return project_gaussians(means, quats, scales, opacities, viewmat, K, width, height)
    means2d, conics, depths, radii, visible = _ProjectGaussians.apply(means, quats, scales, opacities, viewmat, K,
                                                                      width, height)
    return Projection(means2d, conics, depths, radii, visible)


def rasterize_to_pixels_cpu(
    means2d: Tensor,  # [N, 2] pixels
    conics: Tensor,  # [N, 3] (a, b, c) of the inverse 2D covariance
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3]
    background: Tensor,  # [3]
    radii: Tensor,  # [N, 2] int32; 0 = culled
    depths: Tensor,  # [N]
    width: int,
    height: int,
    tile_size: int = DEFAULT_TILE_SIZE,
) -> tuple[Tensor, Tensor]:
    """rgb [H, W, 3] (background composited) and alpha [H, W, 1], differentiable in the first five."""
    if load_extension() is None:
        raise RuntimeError(f"rasterize: backend 'cpu' is unavailable: {cpu_backend_error()}")
    tensors = (means2d, conics, opacities, colors, background, depths)
    if any(t.device.type != "cpu" for t in tensors):
        raise ValueError("rasterize: backend 'cpu' needs CPU tensors; use backend 'torch' or 'auto' on other devices")
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size <= 0:
        raise ValueError(f"rasterize_to_pixels_cpu: tile_size must be a positive int, got {tile_size!r}")
    return _RasterizeToPixels.apply(means2d, conics, opacities, colors, background, radii.to(torch.int32), depths,
                                    width, height, tile_size)


def rasterize_cpu(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3] linear
    opacities: Tensor,  # [N] in [0, 1]
    colors: Tensor,  # [N, 3]
    viewmats: Tensor,  # [C, 4, 4] world-to-camera, OpenCV axes
    Ks: Tensor,  # [C, 3, 3]
    width: int,
    height: int,
    backgrounds: Tensor,  # [C, 3]
    batched: bool = True,
    tile_size: int = DEFAULT_TILE_SIZE,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Same contract as torch_backend.rasterize_torch: rgb [C,H,W,3], alpha [C,H,W,1], means2d [C,N,2]
    (a graph node whose .grad is d loss / d means2d; [N, 2] when batched=False), radii [C,N,2] int32,
    visible [C,N] bool, depths [C,N]. tile_size changes speed only, never results."""
    if means.device.type != "cpu":
        raise ValueError(f"rasterize: backend 'cpu' needs CPU tensors, got {means.device}; use backend 'torch' or 'auto'")
    if load_extension() is None:
        raise RuntimeError(f"rasterize: backend 'cpu' is unavailable: {cpu_backend_error()}")
    projections = [
        project_gaussians_cpu(means, quats, scales, opacities, viewmats[c], Ks[c], width, height)
        for c in range(viewmats.shape[0])
    ]

    def composite_camera(c: int, means2d: Tensor, proj: Projection) -> tuple[Tensor, Tensor]:
        return rasterize_to_pixels_cpu(means2d, proj.conics, opacities, colors, backgrounds[c],
                                       proj.radii, proj.depths, width, height, tile_size)

    return render_cameras(projections, composite_camera, batched)
