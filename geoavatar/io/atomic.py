"""Atomic writes of files and folders: the one implementation every writer of GeoAvatar uses.

    with atomic_file(path) as tmp: writer(tmp)       # any writer that wants a file name (PyAV, PIL)
    atomic_write_bytes / _text / _json / _npz / _png(path, ...)
    folder = temporary_folder_for(target); ...; replace_folder(folder, target)
    with atomic_folder(target) as folder: ...        # the same, removed again on an error

A file is written to a temporary name in its own folder, synced, and moved over `path` with
os.replace, so a killed process leaves the old file or the new one, never a torn one; on any error
the temporary file is removed. A folder appears the same way, whole or not at all.

Files get the mode a plain open() would give them (0o666 less the umask), folders 0o777 less the
umask: mkstemp / mkdtemp create 0600 / 0700, which would hide a user's results from their group.

A full disk or quota (ENOSPC, EDQUOT) becomes DiskFullError (a GeoAvatarError, so one line at the
CLI) naming the file and saying that the previous file, if any, is unchanged.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Any, Iterator

from geoavatar.errors import DiskFullError, OutputPathError, disk_full_error, is_disk_full

_UMASK_LOCK = threading.Lock()


@functools.lru_cache(maxsize=1)
def _umask() -> int:
    """The process umask, read once: os has no getter, so set it and put it back (under a lock)."""
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    return 0o666 & ~_umask()


def folder_mode() -> int:
    return 0o777 & ~_umask()


def _unchanged(path: Path) -> str:
    return f"the previous {path.name} is unchanged" if path.exists() else "nothing was written"


@contextlib.contextmanager
def disk_full_as_error(path: str | os.PathLike, what: str | None = None) -> Iterator[None]:
    """Turn ENOSPC / EDQUOT raised inside the block into DiskFullError naming `path` (+ `what` is left)."""
    try:
        yield
    except OSError as err:
        if not is_disk_full(err):
            raise
        raise disk_full_error(path, err, what if what is not None else _unchanged(Path(path))) from err


def _sync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)  # the data is on disk before the rename makes it visible
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside `path`; when the block ends normally it becomes `path`.

    `suffix` ends the temporary name (for writers that pick the format from it). On any exception the
    temporary file is removed and `path` is left as it was."""
    path = Path(path)
    tmp: Path | None = None
    if path.is_dir():  # found now, not after the work that the file holds
        raise OutputPathError(f"{path} is a folder: give a file name")
    try:
        with disk_full_as_error(path):
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
            except (FileExistsError, NotADirectoryError, PermissionError) as err:
                raise OutputPathError(f"cannot write {path}: {err.strerror} ({err.filename})") from err
            os.close(fd)
            tmp = Path(name)
            yield tmp
            _sync(tmp)
            os.chmod(tmp, file_mode())
            os.replace(tmp, path)
            tmp = None
    finally:
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically; returns the path."""
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, value: Any, indent: int | None = 2) -> Path:
    """`value` as JSON (NaN allowed, as Python writes it) with a final newline."""
    return atomic_write_text(path, json.dumps(value, indent=indent, allow_nan=True) + "\n")


def atomic_write_npz(path: str | os.PathLike, compressed: bool = False, **arrays) -> Path:
    """numpy arrays as an npz (np.savez, or np.savez_compressed when `compressed`)."""
    import numpy as np

    save = np.savez_compressed if compressed else np.savez
    with atomic_file(path) as tmp:
        with open(tmp, "wb") as handle:  # a handle: np.savez would append .npz to a bare name
            save(handle, **arrays)
    return Path(path)


def atomic_write_png(path: str | os.PathLike, image, **options) -> Path:
    """A PIL image or a uint8 array [H, W, 3] / [H, W] as PNG; `options` go to PIL's save (compress_level...)."""
    from PIL import Image

    if not isinstance(image, Image.Image):
        import numpy as np

        image = Image.fromarray(np.ascontiguousarray(image))
    with atomic_file(path) as tmp:
        image.save(tmp, format="PNG", **options)
    return Path(path)


# --- folders ---------------------------------------------------------------------------------------


def temporary_folder_for(target: str | os.PathLike, tag: str = "partial") -> Path:
    """A new empty folder beside `target` (hidden name), with a normal folder's mode."""
    target = Path(target)
    with disk_full_as_error(target, "nothing was written"):
        target.parent.mkdir(parents=True, exist_ok=True)
        folder = Path(tempfile.mkdtemp(prefix=f".{target.name}.{tag}-", dir=target.parent))
    folder.chmod(folder_mode())  # mkdtemp makes 0700
    return folder


def replace_folder(new: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Move the folder `new` to `target`; an existing `target` is moved aside first, deleted after.

    If the second move fails, the previous `target` is put back, so `target` is the old or the new folder."""
    new, target = Path(new), Path(target)
    if not target.exists():
        os.replace(new, target)
        return target
    old = temporary_folder_for(target, "old")
    os.rmdir(old)  # only its unique name is wanted: os.replace does not move a folder over a folder
    os.replace(target, old)
    try:
        os.replace(new, target)
    except BaseException:
        os.replace(old, target)
        raise
    if old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    else:  # a file stood where the folder goes: rmtree would leave it behind, hidden
        old.unlink(missing_ok=True)
    return target


@contextlib.contextmanager
def atomic_folder(target: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside `target`; when the block ends normally it replaces `target`.

    On any exception the temporary folder is deleted and `target` is left as it was; a full disk
    becomes DiskFullError naming `target`."""
    target = Path(target)
    folder = temporary_folder_for(target)
    try:
        with disk_full_as_error(target, f"{target} is unchanged" if target.exists() else "nothing was written"):
            yield folder
        replace_folder(folder, target)
    finally:
        if folder.exists():
            shutil.rmtree(folder, ignore_errors=True)


__all__ = [
    "DiskFullError", "atomic_file", "atomic_folder", "atomic_write_bytes", "atomic_write_json", "atomic_write_npz",
    "atomic_write_png", "atomic_write_text", "disk_full_as_error", "file_mode", "folder_mode", "replace_folder",
    "temporary_folder_for",
]
