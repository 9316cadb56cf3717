"""GeoAvatar's native CPU extensions: C++/OpenMP kernels built by `make install` (else on first use) and cached.

Three extensions, each owned by its layer: the renderer's rasterizer (render/csrc/rasterize_cpu.cpp, loaded by
render/cpu_backend.py), the avatar's face placement, polar coordinates and surface splats
(avatar/csrc/binding_cpu.cpp, loaded by avatar/fused.py) and the SSIM of the training loss and eval
(imaging/csrc/ssim_cpu.cpp, loaded by imaging/quality.py). Each includes csrc/cpu_common.h from this package (torch
headers, the thread count, a parallel loop, input checks). Each is an `ExtensionSpec`; its loader keeps a
`new_state()` dict and calls `load_extension(spec, state)`.

An extension is built with torch.utils.cpp_extension (g++ and ninja) into $GEOAVATAR_EXT_CACHE/<name>-<key>,
else $GEOAVATAR_CACHE/ext/..., else ~/.cache/geoavatar/ext/...; the key hashes the sources (the header
included), the compiler flags, torch and Python (versions and folders) and the machine, so a cache is never reused
by a different build.
Without a compiler, or when the build fails, `load_extension` warns once (naming the extension and what runs
instead) and returns None; the callers then take their PyTorch path.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import sys
import sysconfig
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Optional

import torch

COMMON_HEADER = Path(__file__).with_name("csrc") / "cpu_common.h"
# No -march=native, so a cache built on one machine runs on any x86-64 one (the rasterizer's float32
# compositing picks AVX-512 / AVX2 code at run time instead). No FMA contraction: every SIMD path and the scalar
# backward then compute the same alpha bit for bit. -fno-trapping-math changes no result (only the
# floating-point exception flags): without it GCC keeps branches in the lane loop and cannot vectorise it.
# Tuples, handed to torch as fresh lists: cpp_extension.load appends torch's libraries to the list it gets, and a
# module-level list changed by the first build changed the next extension's key (a second build of it, ~40 s,
# in every process that loaded the two in the other order: `train` after `prepare`).
CFLAGS = ("-O3", "-fopenmp", "-std=c++17", "-ffp-contract=off", "-fno-trapping-math")
LDFLAGS = ("-fopenmp",)

_build_lock = threading.Lock()  # one build at a time, and a state filled once, whatever the thread


@dataclass(frozen=True)
class ExtensionSpec:
    """One native extension: its name (build folder and module stem), its C++ source, and the words of the
    warning when it cannot be built."""

    name: str  # e.g. "rasterize_cpu"
    source: Path  # the .cpp; it includes cpu_common.h by file name
    what: str  # what it is, e.g. "the native CPU rasterizer (backend 'cpu')"
    instead: str  # what runs without it, e.g. "rendering on CPU uses the slower PyTorch backend"

    @property
    def sources(self) -> tuple[Path, ...]:
        return (self.source, COMMON_HEADER)


def new_state() -> dict:
    """A loader's cache: the module once loaded, whether a build was tried, and why it failed."""
    return {"module": None, "tried": False, "error": None}


def cache_root() -> Path:
    """$GEOAVATAR_EXT_CACHE, else $GEOAVATAR_CACHE/ext, else ~/.cache/geoavatar/ext. Builds are keyed by
    their inputs, so one folder can serve several checkouts and test sessions."""
    ext = os.environ.get("GEOAVATAR_EXT_CACHE")
    if ext:
        return Path(ext)
    env = os.environ.get("GEOAVATAR_CACHE")
    return (Path(env) if env else Path.home() / ".cache" / "geoavatar") / "ext"


def build_key(spec: ExtensionSpec) -> str:
    digest = hashlib.sha256()
    for source in spec.sources:
        digest.update(source.read_bytes())
    for part in (CFLAGS, LDFLAGS, torch.__version__, sys.version, platform.machine(), platform.system(),
                 *_toolchain_paths()):
        digest.update(repr(part).encode())
    return digest.hexdigest()[:16]


def _toolchain_paths() -> tuple[str, str]:
    """The folders ninja's build command names (torch's headers and libraries, Python's headers). Two
    environments with the same versions (a venv and a fresh clone's) write different commands, and ninja rebuilds
    when the command changes: with one key they rebuilt each other's folder, ~30 s an extension, every time."""
    return str(Path(torch.__file__).resolve().parent), sysconfig.get_paths()["include"]


def load_extension(spec: ExtensionSpec, state: dict, verbose: bool = False) -> Optional[ModuleType]:
    """The compiled module of `spec` (built on first use, then loaded from the cache), or None with one
    warning when it cannot be built; `state` (new_state()) remembers the outcome. Safe from several threads."""
    with _build_lock:
        if state["tried"]:
            return state["module"]
        state["tried"] = True
        try:
            state["module"] = _build(spec, verbose)
        except Exception as error:  # any build or load failure: fall back, say why once
            state["error"] = _summarise(error)
            warnings.warn(
                f"geoavatar: {spec.what} could not be built, so {spec.instead}. Reason: {state['error']}. "
                "Install g++ (e.g. apt-get install g++) and ninja (pip install ninja) to enable it.",
                RuntimeWarning,
                stacklevel=4,
            )
        return state["module"]


def _summarise(error: Exception) -> str:
    """One line: the first compiler 'error:' line when there is one, else the exception's last line."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    first_error = next((line for line in lines if "error:" in line), None)
    return f"{type(error).__name__}: {first_error or (lines[-1] if lines else '')}"


def _compiler() -> Optional[str]:
    return shutil.which(os.environ.get("CXX", "c++"))


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


def _source_copies(spec: ExtensionSpec, build_dir: Path) -> Path:
    """The sources copied into their build folder (the key hashes them, so one content per folder); the path of
    the .cpp to compile, whose #include "cpu_common.h" finds the copy beside it.

    ninja rebuilds when a build command changes, and the command names the source's path: compiled from each
    checkout's own csrc/, a cache shared by several checkouts (worktrees, an installed copy and a clone) was
    rebuilt, about a minute, whenever the last build came from another one."""
    from geoavatar.io.atomic import atomic_write_bytes

    for source in spec.sources:
        copy, data = build_dir / source.name, source.read_bytes()
        if not copy.is_file() or copy.read_bytes() != data:  # untouched when equal: its time stays, ninja is content
            atomic_write_bytes(copy, data)
    return build_dir / spec.source.name


def _build(spec: ExtensionSpec, verbose: bool) -> ModuleType:
    from torch.utils import cpp_extension

    if _compiler() is None:
        raise RuntimeError(f"no C++ compiler found (looked for {os.environ.get('CXX', 'c++')!r} on PATH)")
    path_before = os.environ.get("PATH", "")
    if shutil.which("ninja") is None:  # a venv used without activation: its bin folder is not on PATH
        os.environ["PATH"] = os.pathsep.join([*_ninja_dirs(), path_before])
    try:
        if not cpp_extension.is_ninja_available():
            raise RuntimeError("ninja is not available (pip install ninja)")
        key = build_key(spec)
        build_dir = cache_root() / f"{spec.name}-{key}"
        build_dir.mkdir(parents=True, exist_ok=True)
        _clear_stale_lock(build_dir)
        name = f"geoavatar_{spec.name}_{key}"  # unique per build: never clashes with another in sys.modules
        if not (build_dir / f"{name}.so").exists():
            print(f"geoavatar: building {spec.what} (first use only, under a minute) in {build_dir} ...",
                  file=sys.stderr, flush=True)
        return cpp_extension.load(name=name, sources=[str(_source_copies(spec, build_dir))],
                                  extra_cflags=list(CFLAGS), extra_ldflags=list(LDFLAGS),
                                  build_directory=str(build_dir), verbose=verbose)
    finally:
        os.environ["PATH"] = path_before


__all__ = ["CFLAGS", "COMMON_HEADER", "ExtensionSpec", "LDFLAGS", "build_key", "cache_root", "load_extension",
           "new_state"]
