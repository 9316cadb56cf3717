"""The standard 3D Gaussian Splatting PLY (the layout of the 3DGS reference code, read by common
splat viewers: SuperSplat, the antimatter15 / gsplat.js viewers, Nerfstudio, GaussianAvatars).

One binary little-endian `vertex` element with float32 properties, in this order:

    x y z            centre
    nx ny nz         normals (unused by 3DGS, written as 0)
    f_dc_0..2        SH degree-0 coefficient per channel (RGB = 0.5 + 0.28209479 * f_dc)
    f_rest_0..       higher SH bands, channel-major (none for SH degree 0, GeoAvatar's setting)
    opacity          logit of the opacity (viewers apply a sigmoid)
    scale_0..2       log of the standard deviations (viewers apply exp)
    rot_0..3         rotation quaternion w, x, y, z (normalised on write)

Written with plyfile, atomically (geoavatar.io.atomic: the umask's mode, DiskFullError on a full disk).
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoavatar.io.atomic import atomic_write_bytes

BASE_PROPERTIES = ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
TAIL_PROPERTIES = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
PLY_PROPERTIES = BASE_PROPERTIES + TAIL_PROPERTIES  # SH degree 0


@dataclass
class GaussianPly:
    """Gaussians in the PLY's parametrisation (numpy float32)."""

    means: np.ndarray  # [N, 3]
    f_dc: np.ndarray  # [N, 3]
    opacity_logits: np.ndarray  # [N]
    log_scales: np.ndarray  # [N, 3]
    quats: np.ndarray  # [N, 4] w, x, y, z, unit
    f_rest: np.ndarray | None = None  # [N, 3, K] higher SH bands (None: degree 0)

    def __len__(self) -> int:
        return int(self.means.shape[0])


def _as_rows(name: str, value, count: int | None, width: int | None) -> np.ndarray:
    array = np.asarray(value, dtype=np.float32)
    expected = (count,) if width is None else (count, width)
    if array.ndim != len(expected) or (count is not None and array.shape[0] != count) or (
            width is not None and array.shape[1] != width):
        shown = ", ".join("N" if s is None else str(s) for s in expected)
        raise ValueError(f"write_gaussian_ply: '{name}' must have shape [{shown}], got {list(array.shape)}")
    if not np.isfinite(array).all():
        raise ValueError(f"write_gaussian_ply: '{name}' contains NaN or infinite values")
    return array


def write_gaussian_ply(path: str | os.PathLike, gaussians: GaussianPly) -> Path:
    """Write `gaussians` as a standard 3DGS PLY at `path` (atomically); returns the path."""
    from plyfile import PlyData, PlyElement


    means = _as_rows("means", gaussians.means, None, 3)
    count = means.shape[0]
    f_dc = _as_rows("f_dc", gaussians.f_dc, count, 3)
    opacity = _as_rows("opacity_logits", gaussians.opacity_logits, count, None)
    scales = _as_rows("log_scales", gaussians.log_scales, count, 3)
    quats = _as_rows("quats", gaussians.quats, count, 4)
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    if count and float(norms.min()) < 1e-12:
        raise ValueError("write_gaussian_ply: 'quats' has zero-length quaternion(s)")
    quats = quats / norms
    rest = np.zeros((count, 0), dtype=np.float32)
    if gaussians.f_rest is not None:
        f_rest = np.asarray(gaussians.f_rest, dtype=np.float32)
        if f_rest.ndim != 3 or f_rest.shape[:2] != (count, 3):
            raise ValueError(f"write_gaussian_ply: 'f_rest' must have shape [N, 3, K], got {list(f_rest.shape)}")
        rest = f_rest.reshape(count, -1)  # channel-major, as the 3DGS reference code flattens it
    names = BASE_PROPERTIES + tuple(f"f_rest_{i}" for i in range(rest.shape[1])) + TAIL_PROPERTIES
    columns = np.concatenate([means, np.zeros_like(means), f_dc, rest, opacity[:, None], scales, quats], axis=1)
    vertex = np.empty(count, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertex[name] = columns[:, i]
    buffer = io.BytesIO()
    PlyData([PlyElement.describe(vertex, "vertex")], text=False, byte_order="<").write(buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def read_gaussian_ply(path: str | os.PathLike) -> GaussianPly:
    """Read a 3DGS PLY (any SH degree); ValueError naming the file when it is not one."""
    from plyfile import PlyData

    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except FileNotFoundError:
        raise
    except Exception as err:  # noqa: BLE001 - plyfile raises several kinds on a foreign file
        raise ValueError(f"{path}: not a readable PLY file ({err})") from err
    if "vertex" not in ply:
        raise ValueError(f"{path}: has no 'vertex' element")
    vertex = ply["vertex"].data
    names = set(vertex.dtype.names or ())
    missing = [name for name in PLY_PROPERTIES if name not in names and not name.startswith("n")]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY (missing properties {', '.join(missing)})")

    def stack(keys) -> np.ndarray:
        return np.stack([np.asarray(vertex[key], dtype=np.float32) for key in keys], axis=1)

    rest_names = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    f_rest = stack(rest_names).reshape(len(vertex), 3, -1) if rest_names else None
    return GaussianPly(
        means=stack(("x", "y", "z")),
        f_dc=stack(("f_dc_0", "f_dc_1", "f_dc_2")),
        opacity_logits=np.asarray(vertex["opacity"], dtype=np.float32),
        log_scales=stack(("scale_0", "scale_1", "scale_2")),
        quats=stack(("rot_0", "rot_1", "rot_2", "rot_3")),
        f_rest=f_rest,
    )


__all__ = ["GaussianPly", "PLY_PROPERTIES", "read_gaussian_ply", "write_gaussian_ply"]
