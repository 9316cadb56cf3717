"""Process-wide runtime settings applied once by the CLI entry point (and the test suite), and the
`--device` option's meaning (`resolve_device`), shared by every command.

glibc hands large blocks back to the OS and zero-fills them again on the next allocation; PyTorch on
CPU then runs 2-5x slower and noisily (measured on our 2-core machines, see DESIGN.md). Turning off
mmap for large blocks and raising the trim threshold keeps freed memory in the process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from contextlib import contextmanager

# mallopt parameter numbers from <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_THRESHOLD_BYTES = 64 * 1024**3

_applied = False


def apply_malloc_settings() -> bool:
    """Apply the glibc malloc settings to this process and to child processes.

    Returns True when mallopt was called (glibc present), False elsewhere (macOS, musl).
    """
    os.environ.setdefault("MALLOC_MMAP_MAX_", "0")
    os.environ.setdefault("MALLOC_TRIM_THRESHOLD_", str(_TRIM_THRESHOLD_BYTES))
    libc_name = ctypes.util.find_library("c")
    if libc_name is None:
        return False
    try:
        libc = ctypes.CDLL(libc_name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok_mmap = mallopt(_M_MMAP_MAX, 0) == 1
    # mallopt takes an int: clamp the threshold to INT_MAX (2 GiB) in-process.
    ok_trim = mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1
    return ok_mmap and ok_trim


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity mask on Linux)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def configure_threads() -> int:
    """Use every core the process may run on, unless GEOAVATAR_THREADS or OMP_NUM_THREADS says otherwise."""
    import torch

    env = os.environ.get("GEOAVATAR_THREADS") or os.environ.get("OMP_NUM_THREADS")
    threads = max(1, int(env)) if env else available_cores()
    torch.set_num_threads(threads)
    return threads


@contextmanager
def num_threads(threads: int):
    """Run a block with `threads` CPU threads for torch (and the native rasterizer, which reads torch's count);
    the previous count after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def resolve_device(name: str):
    """The torch.device for a --device option: auto (CUDA when available, else CPU), cpu, cuda or cuda:N.

    ValueError (naming the option) for a malformed name or CUDA asked for where there is none."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"--device: {err}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine (use --device cpu or auto)")
    return device


def setup_process() -> None:
    """Malloc settings first (before large allocations), then threads. Idempotent."""
    global _applied
    if _applied:
        return
    apply_malloc_settings()
    configure_threads()
    _applied = True
