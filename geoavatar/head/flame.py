"""FLAME 2020 / 2023, loaded from files the user downloads (FLAME cannot be shipped).

    data = load_flame("~/flame")          # or env GEOAVATAR_FLAME_DIR, or --flame-dir
    head = HeadModel(data)

Files looked for in the FLAME folder:
- `flame2023.pkl` (FLAME 2023, preferred by version="auto") or `generic_model.pkl` (FLAME 2020),
  both from https://flame.is.tue.mpg.de after registration;
- `FLAME_masks.pkl` ("FLAME Vertex Masks" on the same site): the 14 region vertex lists.

Both are Python 2 pickles referencing chumpy; they are read with the restricted unpickler of
`geoavatar.io.safe_pickle` (numpy, scipy.sparse, a chumpy stand-in, nothing else).

Lip rings: FLAME has no lip-ring list of its own. We use the inner lip rings (the 15 vertices
along the upper and the lower edge of the mouth opening) that VHAP / GaussianAvatars define on
FLAME's topology (`FlameMask.create_custom_mask`, names lip_inside_ring_upper/lower), reoriented so
that x increases (subject's right corner -> left corner). Those ids are facts about FLAME's
5023-vertex mesh, so they are used only when the mesh has 5023 vertices. A model with another
topology must carry its rings in the masks file under the keys `lip_ring_upper` and
`lip_ring_lower` (15 ids each); otherwise loading fails with an error that says so.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from geoavatar.errors import GeoAvatarError, OptionError
from geoavatar.head.base import FLAME_SHAPE_DIM, JOINT_NAMES, PARENTS, REGION_NAMES, HeadModelData
from geoavatar.io.safe_pickle import load_restricted_pickle

FLAME_SITE = "https://flame.is.tue.mpg.de"
FLAME_DIR_ENV = "GEOAVATAR_FLAME_DIR"
MODEL_FILES = {"2023": "flame2023.pkl", "2020": "generic_model.pkl"}
MASKS_FILE = "FLAME_masks.pkl"
FLAME_NUM_VERTICES = 5023

# Inner lip rings on FLAME's topology (VHAP / GaussianAvatars: lip_inside_ring_upper / _lower).
FLAME_LIP_RING_UPPER = (1595, 1746, 1747, 1742, 1739, 1665, 1666, 3514, 2783, 2782, 2854, 2857, 2862, 2861, 2731)
FLAME_LIP_RING_LOWER = (1572, 1573, 1860, 1862, 1830, 1835, 1852, 3497, 2941, 2933, 2930, 2945, 2943, 2709, 2708)

_REQUIRED_KEYS = ("v_template", "f", "shapedirs", "J_regressor", "weights", "kintree_table")


class FlameFileNotFoundError(GeoAvatarError, FileNotFoundError):
    """A FLAME file the user has to download is missing; the message says what, where and how."""


class FlameFileError(GeoAvatarError, ValueError):
    """A FLAME model or masks file is not what it should be; the message names the file."""


def resolve_flame_dir(flame_dir: str | Path | None = None) -> Path:
    """The FLAME folder: the argument, else env GEOAVATAR_FLAME_DIR; error when neither is set or it is missing."""
    if flame_dir is None:
        flame_dir = os.environ.get(FLAME_DIR_ENV) or None
        origin = f"environment variable {FLAME_DIR_ENV}"
    else:
        origin = "--flame-dir"
    if flame_dir is None:
        raise FlameFileNotFoundError(
            f"no FLAME folder given: pass --flame-dir DIR (flame_dir=...) or set {FLAME_DIR_ENV}=DIR. "
            + _download_hint()
        )
    path = Path(flame_dir).expanduser()
    if not path.is_dir():
        raise FlameFileNotFoundError(f"FLAME folder '{path}' (from {origin}) does not exist. " + _download_hint())
    return path


def _download_hint() -> str:
    return (
        f"FLAME cannot be shipped with GeoAvatar: register at {FLAME_SITE}, download FLAME 2023 "
        f"('{MODEL_FILES['2023']}') or FLAME 2020 ('{MODEL_FILES['2020']}') and 'FLAME Vertex Masks' "
        f"('{MASKS_FILE}') from the same site, and put the files in one folder given by --flame-dir "
        f"or the environment variable {FLAME_DIR_ENV}."
    )


def find_flame_files(flame_dir: str | Path | None = None, version: str = "auto") -> tuple[Path, Path, str]:
    """(model pickle, masks pickle, version) in the FLAME folder; FlameFileNotFoundError names what is missing."""
    if version not in ("auto", *MODEL_FILES):
        raise OptionError(f"unknown FLAME version '{version}'; choose auto, 2023 or 2020")
    folder = resolve_flame_dir(flame_dir)
    candidates = ["2023", "2020"] if version == "auto" else [version]
    model_path, found_version = None, None
    for v in candidates:
        if (folder / MODEL_FILES[v]).is_file():
            model_path, found_version = folder / MODEL_FILES[v], v
            break
    if model_path is None:
        wanted = " or ".join(f"'{MODEL_FILES[v]}'" for v in candidates)
        raise FlameFileNotFoundError(f"FLAME model file {wanted} not found in '{folder}'. " + _download_hint())
    masks_path = folder / MASKS_FILE
    if not masks_path.is_file():
        raise FlameFileNotFoundError(f"FLAME masks file '{MASKS_FILE}' not found in '{folder}'. " + _download_hint())
    return model_path, masks_path, found_version


def load_flame(flame_dir: str | Path | None = None, version: str = "auto") -> HeadModelData:
    """FLAME as HeadModelData: template, 300 shape + 100 expression modes, pose correctives, LBS, masks, lip rings."""
    model_path, masks_path, found_version = find_flame_files(flame_dir, version)
    model = load_restricted_pickle(model_path)
    masks = load_restricted_pickle(masks_path)
    return flame_head_data(model, masks, source=str(model_path), masks_source=str(masks_path), version=found_version)


def flame_head_data(model: dict, masks: dict, source: str = "<flame>", masks_source: str = "<masks>",
                    version: str = "unknown") -> HeadModelData:
    """Convert the plain dicts of a FLAME model pickle and a masks pickle into HeadModelData."""
    if not isinstance(model, dict):
        raise FlameFileError(f"{source}: expected a dict of FLAME arrays, found {type(model).__name__}")
    missing = [k for k in _REQUIRED_KEYS if k not in model]
    if missing:
        raise FlameFileError(f"{source}: not a FLAME model, keys missing: {', '.join(missing)}")

    v_template = np.asarray(model["v_template"], dtype=np.float32)  # [V, 3]
    num_vertices = v_template.shape[0]
    faces = np.asarray(model["f"], dtype=np.int64)  # [F, 3]
    dirs = np.asarray(model["shapedirs"], dtype=np.float32)  # [V, 3, 300 + 100]
    if dirs.ndim != 3 or dirs.shape[:2] != (num_vertices, 3):
        raise FlameFileError(f"{source}: shapedirs has shape {dirs.shape}, expected [{num_vertices}, 3, modes]")
    num_shape = min(FLAME_SHAPE_DIM, dirs.shape[2])  # FLAME stores 300 identity then the expression modes
    shapedirs, exprdirs = dirs[:, :, :num_shape], dirs[:, :, num_shape:]
    j_regressor = model["J_regressor"]
    j_regressor = np.asarray(j_regressor.toarray() if hasattr(j_regressor, "toarray") else j_regressor, np.float32)
    weights = np.asarray(model["weights"], dtype=np.float32)  # [V, J]
    posedirs = model.get("posedirs")
    posedirs = None if posedirs is None else np.asarray(posedirs, dtype=np.float32)  # [V, 3, 36]
    kintree = np.asarray(model["kintree_table"]).astype(np.int64)  # [2, J]; root parent is 2**32-1
    parents = tuple(int(p) for p in kintree[0, 1:])
    if kintree.shape != (2, len(JOINT_NAMES)) or parents != PARENTS[1:]:
        raise FlameFileError(f"{source}: kinematic tree {kintree.tolist()} is not FLAME's 5-joint chain {PARENTS}")

    regions = _read_regions(masks, masks_source, num_vertices)
    ring_upper, ring_lower = _lip_rings(masks, v_template, masks_source)

    data = HeadModelData(
        name="flame",
        v_template=v_template,
        faces=faces,
        shapedirs=shapedirs,
        exprdirs=exprdirs,
        j_regressor=j_regressor,
        lbs_weights=weights,
        posedirs=posedirs,
        regions=regions,
        lip_ring_upper=ring_upper,
        lip_ring_lower=ring_lower,
        metadata={
            "source": source,
            "masks": masks_source,
            "version": version,
            "num_shape": int(shapedirs.shape[2]),
            "num_expr": int(exprdirs.shape[2]),
            "num_vertices": int(num_vertices),
            "num_faces": int(faces.shape[0]),
            "license": f"FLAME, user-supplied ({FLAME_SITE}); not redistributable",
        },
    )
    try:
        return data.validate()
    except ValueError as err:
        raise FlameFileError(f"{source}: {err}") from err


def _read_regions(masks, masks_source: str, num_vertices: int) -> dict[str, np.ndarray]:
    if not isinstance(masks, dict):
        raise FlameFileError(f"{masks_source}: expected a dict of region name -> vertex ids, found {type(masks).__name__}")
    missing = [name for name in REGION_NAMES if name not in masks]
    if missing:
        raise FlameFileError(f"{masks_source}: FLAME masks file lacks the regions {', '.join(missing)}")
    regions = {}
    for name in REGION_NAMES:
        ids = np.asarray(masks[name]).astype(np.int64).ravel()
        if ids.size and (ids.min() < 0 or ids.max() >= num_vertices):
            raise FlameFileError(f"{masks_source}: region '{name}' has vertex ids outside 0..{num_vertices - 1}")
        regions[name] = ids
    return regions


def _lip_rings(masks: dict, v_template: np.ndarray, masks_source: str) -> tuple[np.ndarray, np.ndarray]:
    """Upper and lower inner lip rings [15] each, ordered by increasing x (subject's right -> left)."""
    if "lip_ring_upper" in masks and "lip_ring_lower" in masks:
        rings = [np.asarray(masks[k]).astype(np.int64).ravel() for k in ("lip_ring_upper", "lip_ring_lower")]
        origin = f"{masks_source} (keys lip_ring_upper / lip_ring_lower)"
    elif v_template.shape[0] == FLAME_NUM_VERTICES:
        rings = [np.asarray(FLAME_LIP_RING_UPPER, np.int64), np.asarray(FLAME_LIP_RING_LOWER, np.int64)]
        origin = "FLAME's topology (VHAP / GaussianAvatars inner lip rings)"
    else:
        raise FlameFileError(
            f"{masks_source}: the model has {v_template.shape[0]} vertices, not FLAME's {FLAME_NUM_VERTICES}, so "
            "FLAME's lip-ring vertex ids do not apply; add keys 'lip_ring_upper' and 'lip_ring_lower' "
            "(15 vertex ids each, along the mouth opening) to the masks file"
        )
    out = []
    for name, ring in zip(("upper", "lower"), rings):
        if ring.shape != (15,) or ring.min() < 0 or ring.max() >= v_template.shape[0]:
            raise FlameFileError(f"lip ring '{name}' from {origin} must be 15 valid vertex ids, got {ring.tolist()}")
        x = v_template[ring, 0]
        if x[0] > x[-1]:  # store from the subject's right corner (smaller x) to the left corner
            ring = ring[::-1].copy()
        out.append(ring)
    return out[0], out[1]
