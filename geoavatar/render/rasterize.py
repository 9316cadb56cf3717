"""rasterize(): differentiable 3D Gaussian splatting behind one API, backends "torch", "cpu" and "gsplat".

All backends follow gsplat 1.5.3's conventions (see torch_backend's docstring); the torch backend
runs anywhere (CPU or CUDA tensors), "cpu" is the native C++/OpenMP kernel for CPU tensors (built on
first use, cpu_backend.py), gsplat runs only on CUDA. Inputs are validated here, once, so every
backend gets the same clear errors (gsplat itself asserts shapes only). The value checks (NaN/Inf,
ranges) cost one device sync; `check_values=False` skips them for loops that sample them.

A batch of cameras is supported: pass viewmat [C, 4, 4] and K [C, 3, 3] (and background [3] or
[C, 3]); every output then gains a leading C dimension.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

import torch
from torch import Tensor

from geoavatar.render.cpu_backend import cpu_backend_available, rasterize_cpu
from geoavatar.render.gsplat_backend import gsplat_available, rasterize_gsplat
from geoavatar.render.torch_backend import rasterize_torch

Backend = Literal["auto", "torch", "cpu", "gsplat"]
BACKENDS = ("auto", "torch", "cpu", "gsplat")


@dataclass
class RasterizeResult:
    """What rasterize() returns. Shapes for one camera; a camera batch adds a leading [C]."""

    rgb: Tensor  # [H, W, 3] colour, background composited: rgb + (1 - alpha) * background
    alpha: Tensor  # [H, W, 1] accumulated opacity
    means2d: Tensor  # [N, 2] screen-space means (pixels); after backward, .grad = d loss / d means2d
    radii: Tensor  # [N, 2] int32 half-size of each Gaussian's box in pixels (x, y); 0 = culled
    visible: Tensor  # [N] bool, projected inside the image and in front of the near plane
    depths: Tensor  # [N] camera-space depth (z) of each mean
    backend: str  # "torch", "cpu" or "gsplat": the backend that ran


def _check_tensor(name: str, value, shapes: tuple[tuple, ...], dtype=None, device=None) -> Tensor:
    """Type, shape (None = any size), floating dtype and device of one argument (no device sync)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"rasterize: argument '{name}' must be a torch.Tensor, got {type(value).__name__}")
    if not any(
        value.dim() == len(shape) and all(s is None or s == d for s, d in zip(shape, value.shape)) for shape in shapes
    ):
        wanted = " or ".join("[" + ", ".join("*" if s is None else str(s) for s in shape) + "]" for shape in shapes)
        raise ValueError(f"rasterize: argument '{name}' must have shape {wanted}, got {list(value.shape)}")
    if not value.is_floating_point():
        raise TypeError(f"rasterize: argument '{name}' must be a floating-point tensor, got {value.dtype}")
    if dtype is not None and value.dtype != dtype:
        raise TypeError(f"rasterize: argument '{name}' has dtype {value.dtype} but 'means' has {dtype}; use one dtype")
    if device is not None and value.device != device:
        raise ValueError(
            f"rasterize: argument '{name}' is on device {value.device} but 'means' is on {device}; "
            "move all inputs to one device"
        )
    return value


@torch.no_grad()
def check_input_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds) -> None:
    """Value checks of the (shape-checked) inputs: finiteness, unit-able quaternions, scales >= 0,
    opacities in [0, 1], rigid viewmats, pinhole Ks. Every condition is reduced on the device and
    read back in ONE transfer (one sync on CUDA); the first failing one raises ValueError."""
    tensors = {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors,
               "viewmat": viewmats, "K": Ks, "background": backgrounds}
    problems: list[tuple[Tensor, str]] = [(~torch.isfinite(value).all(), name) for name, value in tensors.items()]
    last_row = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=means.dtype, device=means.device)
    no = torch.zeros((), dtype=torch.bool, device=means.device)
    problems += [
        ((quats.norm(dim=-1) < 1e-12).any() if len(quats) else no,
         "rasterize: argument 'quats' has zero-length quaternion(s); they cannot be normalised"),
        ((scales < 0).any() if len(scales) else no,
         "rasterize: argument 'scales' has negative values; scales are linear (pass exp(log_scales))"),
        (((opacities < 0) | (opacities > 1)).any() if len(opacities) else no,
         "rasterize: argument 'opacities' must lie in [0, 1] (pass sigmoid(logits))"),
        ((viewmats[:, 3] - last_row).abs().max() > 1e-6,
         "rasterize: argument 'viewmat' must be a rigid world-to-camera matrix with last row [0,0,0,1]"),
        ((Ks[:, 2] - last_row[1:]).abs().max() > 1e-6,
         "rasterize: argument 'K' must be a pinhole intrinsic matrix with last row [0,0,1]"),
        ((Ks[:, 0, 0] <= 0).any() | (Ks[:, 1, 1] <= 0).any(),
         "rasterize: argument 'K' must have positive focal lengths K[0,0], K[1,1]"),
    ]
    failed = torch.stack([flag for flag, _ in problems]).tolist()  # the one read-back
    for (_, message), bad in zip(problems, failed):
        if bad and message in tensors:  # a finiteness flag: count the culprits (error path only)
            value = tensors[message]
            count = int((~torch.isfinite(value)).sum())
            raise ValueError(f"rasterize: argument '{message}' contains {count} NaN/Inf value(s)")
        if bad:
            raise ValueError(message)


def validate_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
                    values: bool = True):
    """Check every argument; returns (viewmats [C,4,4], Ks [C,3,3], backgrounds [C,3], batched).

    Types, shapes, dtypes and devices are checked on every call (free); `values` adds check_input_values
    (one device sync), which a training loop runs at a sampled cadence."""
    _check_tensor("means", means, ((None, 3),))
    n, dtype, device = means.shape[0], means.dtype, means.device
    if dtype not in (torch.float32, torch.float64):
        raise TypeError(f"rasterize: argument 'means' must be float32 or float64, got {dtype}")
    _check_tensor("quats", quats, ((n, 4),), dtype, device)
    _check_tensor("scales", scales, ((n, 3),), dtype, device)
    _check_tensor("opacities", opacities, ((n,),), dtype, device)
    _check_tensor("colors", colors, ((n, 3),), dtype, device)
    _check_tensor("viewmat", viewmat, ((4, 4), (None, 4, 4)), dtype, device)
    _check_tensor("K", K, ((3, 3), (None, 3, 3)), dtype, device)
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ValueError(f"rasterize: argument '{name}' must be a positive int, got {value!r}")
    batched = viewmat.dim() == 3
    viewmats = viewmat if batched else viewmat[None]
    Ks = K if K.dim() == 3 else K[None]
    if (K.dim() == 3) != batched or Ks.shape[0] != viewmats.shape[0]:
        raise ValueError(
            f"rasterize: arguments 'viewmat' {list(viewmat.shape)} and 'K' {list(K.shape)} must both be single "
            "([4,4], [3,3]) or batched with the same number of cameras ([C,4,4], [C,3,3])"
        )
    cameras = viewmats.shape[0]
    if cameras == 0:
        raise ValueError("rasterize: argument 'viewmat' holds no camera")
    if background is None:
        backgrounds = torch.zeros(cameras, 3, dtype=dtype, device=device)
    else:
        _check_tensor("background", background, ((3,), (cameras, 3)), dtype, device)
        backgrounds = background.expand(cameras, 3) if background.dim() == 1 else background
    if values:
        check_input_values(means, quats, scales, opacities, colors, viewmats, Ks, backgrounds)
    return viewmats, Ks, backgrounds, batched


def rasterize(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] rotations, wxyz (normalised inside)
    scales: Tensor,  # [N, 3] standard deviations along the local axes, linear (not log)
    opacities: Tensor,  # [N] in [0, 1] (not logits)
    colors: Tensor,  # [N, 3] RGB
    viewmat: Tensor,  # [4, 4] or [C, 4, 4] world-to-camera, OpenCV axes (+x right, +y down, +z forward)
    K: Tensor,  # [3, 3] or [C, 3, 3] pinhole intrinsics in pixels
    width: int,
    height: int,
    background: Optional[Tensor] = None,  # [3] or [C, 3]; None = black
    backend: Backend = "auto",
    check_values: bool = True,  # value checks (one device sync); shapes/dtypes/devices are always checked
) -> RasterizeResult:
    """Render Gaussians to an image, differentiably in every floating-point input.

    backend "auto" uses gsplat for float32 CUDA tensors when gsplat imports, the native "cpu" kernel
    for CPU tensors when it builds (first use compiles it, ~40 s; without a compiler it warns once),
    the torch backend otherwise; "torch" always uses the pure-PyTorch renderer; "cpu" insists on the
    native kernel (CPU tensors); "gsplat" insists on gsplat (CUDA only).
    """
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: argument 'backend' must be one of {BACKENDS}, got {backend!r}")
    viewmats, Ks, backgrounds, batched = validate_inputs(
        means, quats, scales, opacities, colors, viewmat, K, width, height, background, values=check_values
    )
    if backend == "auto":
        on_cuda = means.device.type == "cuda" and means.dtype == torch.float32
        if on_cuda and gsplat_available():
            backend = "gsplat"
        elif means.device.type == "cpu" and cpu_backend_available():
            backend = "cpu"
        else:
            backend = "torch"
    render = {"gsplat": rasterize_gsplat, "cpu": rasterize_cpu, "torch": rasterize_torch}[backend]
    rgb, alpha, means2d, radii, visible, depths = render(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, batched=batched
    )
    if not batched:  # means2d already comes as [N, 2] from the backend (it must stay on the graph)
        rgb, alpha, radii, visible, depths = rgb[0], alpha[0], radii[0], visible[0], depths[0]
    return RasterizeResult(rgb, alpha, means2d, radii, visible, depths, backend)
