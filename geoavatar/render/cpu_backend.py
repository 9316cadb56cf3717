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

The extension is built on first use with torch.utils.cpp_extension (g++ and ninja; about 40 s on
our machines) into $GEOAVATAR_EXT_CACHE/<key>, else $GEOAVATAR_CACHE/ext/<key>, else
~/.cache/geoavatar/ext/<key>; the key hashes the C++ source, the compiler flags, torch, Python and
the machine, so a cache is never reused by a different build. Without a compiler, or when the build fails, `load_extension()` warns once and
returns None; rasterize(backend="auto") then uses the torch backend.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import sys
import threading
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Optional

import torch
from torch import Tensor

from geoavatar.render.torch_backend import Projection, project_gaussians, render_cameras

SOURCE = Path(__file__).with_name("csrc") / "rasterize_cpu.cpp"
# No -march=native, so a cache built on one machine runs on any x86-64 one (the float32 compositing
# picks AVX-512 / AVX2 code at run time instead). No FMA contraction: every SIMD path and the scalar
# backward then compute the same alpha bit for bit. -fno-trapping-math changes no result (only the
# floating-point exception flags): without it GCC keeps branches in the lane loop and cannot vectorise it.
CFLAGS = ["-O3", "-fopenmp", "-std=c++17", "-ffp-contract=off", "-fno-trapping-math"]
LDFLAGS = ["-fopenmp"]
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

_lock = threading.Lock()
_state: dict = {"module": None, "tried": False, "error": None}


def _cache_root() -> Path:
    """$GEOAVATAR_EXT_CACHE, else $GEOAVATAR_CACHE/ext, else ~/.cache/geoavatar/ext. Builds are keyed by
    their inputs, so one folder can serve several checkouts and test sessions."""
    ext = os.environ.get("GEOAVATAR_EXT_CACHE")
    if ext:
        return Path(ext)
    env = os.environ.get("GEOAVATAR_CACHE")
    return (Path(env) if env else Path.home() / ".cache" / "geoavatar") / "ext"


def _build_key() -> str:
    digest = hashlib.sha256()
    digest.update(SOURCE.read_bytes())
    for part in (CFLAGS, LDFLAGS, torch.__version__, sys.version, platform.machine(), platform.system()):
        digest.update(repr(part).encode())
    return digest.hexdigest()[:16]


def _compiler() -> Optional[str]:
    return shutil.which(os.environ.get("CXX", "c++"))


def load_extension(verbose: bool = False) -> Optional[ModuleType]:
    """The compiled kernel module (built on first use, then loaded from the cache), or None with one
    warning when it cannot be built. Safe to call from several threads; later calls are free."""
    with _lock:
        if _state["tried"]:
            return _state["module"]
        _state["tried"] = True
        try:
            _state["module"] = _build(verbose)
        except Exception as error:  # any build or load failure: fall back, say why once
            _state["error"] = _summarise(error)
            warnings.warn(
                "geoavatar: the native CPU rasterizer (backend 'cpu') could not be built, so rendering on CPU "
                f"uses the slower PyTorch backend. Reason: {_state['error']}. Install g++ (e.g. apt-get install "
                "g++) and ninja (pip install ninja) to enable it.",
                RuntimeWarning,
                stacklevel=3,
            )
        return _state["module"]


def _summarise(error: Exception) -> str:
    """One line: the first compiler 'error:' line when there is one, else the exception's last line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    first_error = next((line for line in lines if "error:" in line), None)
    return f"{type(error).__name__}: {first_error or (lines[-1] if lines else '')}"


def _ninja_dirs() -> list[str]:
    """Folders that may hold the `ninja` of PyPI's ninja package when the venv is not activated."""
    dirs = [str(Path(sys.executable).parent)]
    try:
        import ninja  # the PyPI package: BIN_DIR holds its executable

        dirs.insert(0, str(ninja.BIN_DIR))
    except (ImportError, AttributeError):
        pass
    return dirs


def _clear_stale_lock(build_dir: Path, max_age_s: float = 900.0) -> None:
    """cpp_extension waits forever on the lock file of a build that was killed: drop one that is old."""
    lock = build_dir / "lock"
    try:
        if time.time() - lock.stat().st_mtime > max_age_s:
            lock.unlink()
    except FileNotFoundError:
        pass


def _source_copy(build_dir: Path) -> Path:
    """SOURCE copied into its build folder (the key hashes it, so one content per folder), the path compiled.

    ninja rebuilds when a build command changes, and the command names the source's path: compiled from each
    checkout's own csrc/, a cache shared by several checkouts (worktrees, an installed copy and a clone) was
    rebuilt, about a minute, whenever the last build came from another one."""
    from geoavatar.io.atomic import atomic_write_bytes

    copy = build_dir / SOURCE.name
    data = SOURCE.read_bytes()
    if not copy.is_file() or copy.read_bytes() != data:  # untouched when equal: its time stays, ninja is content
        atomic_write_bytes(copy, data)
    return copy


def _build(verbose: bool) -> ModuleType:
    from torch.utils import cpp_extension

    if _compiler() is None:
        raise RuntimeError(f"no C++ compiler found (looked for {os.environ.get('CXX', 'c++')!r} on PATH)")
    path_before = os.environ.get("PATH", "")
    if shutil.which("ninja") is None:  # a venv used without activation: its bin folder is not on PATH
        os.environ["PATH"] = os.pathsep.join([*_ninja_dirs(), path_before])
    try:
        if not cpp_extension.is_ninja_available():
            raise RuntimeError("ninja is not available (pip install ninja)")
        key = _build_key()
        build_dir = _cache_root() / f"rasterize_cpu-{key}"
        build_dir.mkdir(parents=True, exist_ok=True)
        _clear_stale_lock(build_dir)
        name = f"geoavatar_rasterize_cpu_{key}"  # unique per build: never clashes with another in sys.modules
        if not (build_dir / f"{name}.so").exists():
            print("geoavatar: building the native CPU rasterizer (first use only, about a minute) in "
                  f"{build_dir} ...", file=sys.stderr, flush=True)
        return cpp_extension.load(
            name=name,
            sources=[str(_source_copy(build_dir))],
            extra_cflags=CFLAGS,
            extra_ldflags=LDFLAGS,
            build_directory=str(build_dir),
            verbose=verbose,
        )
    finally:
        os.environ["PATH"] = path_before


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
