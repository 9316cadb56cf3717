"""`geoavatar head show`: contact sheets of head models (a small stand-in model and the real OpenHead)."""

import math
import time

import numpy as np
import pytest
from PIL import Image

from geoavatar.apps.head_show import contact_sheet, head_show
from geoavatar.head.base import HeadModel, HeadModelData
from geoavatar.head.flame import FlameFileNotFoundError


def _sphere(centre, radii, n_lat=10, n_lon=16):
    """UV ellipsoid: vertices [n, 3], faces [m, 3] (outward normals, right-hand rule)."""
    verts = [[centre[0], centre[1] + radii[1], centre[2]]]
    for i in range(1, n_lat):
        theta = math.pi * i / n_lat
        for j in range(n_lon):
            phi = 2 * math.pi * j / n_lon
            verts.append([centre[0] + radii[0] * math.sin(theta) * math.sin(phi), centre[1] + radii[1] * math.cos(theta),
                          centre[2] + radii[2] * math.sin(theta) * math.cos(phi)])
    verts.append([centre[0], centre[1] - radii[1], centre[2]])
    faces = []
    ring = lambda i, j: 1 + (i - 1) * n_lon + j % n_lon  # noqa: E731
    for j in range(n_lon):
        faces.append([0, ring(1, j), ring(1, j + 1)])
        faces.append([len(verts) - 1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)])
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    return np.array(verts, np.float32), np.array(faces, np.int64)


def stand_in_head() -> HeadModel:
    """A toy head: an ellipsoid skull, two eyeballs and a two-part 'mouth' slab, with a jaw and 3 named modes."""
    parts = [_sphere((0, 0, 0), (0.075, 0.1, 0.09)), _sphere((0.03, 0.02, 0.075), (0.012,) * 3, 6, 8),
             _sphere((-0.03, 0.02, 0.075), (0.012,) * 3, 6, 8), _sphere((0, -0.045, 0.06), (0.025, 0.006, 0.015), 4, 8),
             _sphere((0, -0.058, 0.06), (0.025, 0.006, 0.015), 4, 8)]
    verts, faces, offsets = [], [], [0]
    for v, f in parts:
        faces.append(f + offsets[-1])
        verts.append(v)
        offsets.append(offsets[-1] + len(v))
    verts, faces = np.concatenate(verts), np.concatenate(faces)
    num_v = len(verts)
    ids = [np.arange(offsets[i], offsets[i + 1]) for i in range(len(parts))]
    weights = np.zeros((num_v, 5), np.float32)
    weights[:, 1] = 1.0
    jaw = (verts[:, 1] < -0.05) & (verts[:, 2] > 0.02)
    jaw[ids[4]] = True
    jaw[ids[3]] = False
    weights[jaw] = 0.0
    weights[jaw, 2] = 1.0
    jreg = np.zeros((5, num_v), np.float32)
    for j, point in enumerate([(0, -0.1, 0), (0, -0.08, -0.01), (0, -0.04, 0.0), (0.03, 0.02, 0.075), (-0.03, 0.02, 0.075)]):
        nearest = np.argmin(((verts - np.array(point)) ** 2).sum(1))
        jreg[j, nearest] = 1.0
    expr = np.zeros((num_v, 3, 3), np.float32)
    mouth_corner = np.exp(-((verts[:, 1] + 0.05) ** 2 + (np.abs(verts[:, 0]) - 0.03) ** 2) / 0.0004)
    expr[:, 1, 0] = 0.01 * mouth_corner  # "smile": corners up
    expr[ids[1], 1, 1] = -0.004  # "blink" (toy)
    brow = np.exp(-((verts[:, 1] - 0.05) ** 2) / 0.0004) * (verts[:, 2] > 0)
    expr[:, 1, 2] = 0.008 * brow
    mouth_faces = np.arange(sum(len(p[1]) for p in parts[:3]), len(faces))
    data = HeadModelData(
        name="stand-in", v_template=verts, faces=faces, shapedirs=np.zeros((num_v, 3, 2), np.float32),
        exprdirs=expr, j_regressor=jreg, lbs_weights=weights,
        regions={"left_eyeball": ids[1], "right_eyeball": ids[2]},
        vertex_groups={"mouth_upper": ids[3], "mouth_lower": ids[4]}, face_groups={"mouth": mouth_faces},
        metadata={"expression_names": ["smile", "blink", "brow_raise"]},
    )
    return HeadModel(data)


def test_contact_sheet_of_a_stand_in_head():
    head = stand_in_head()
    sheet = contact_sheet(head, tile=96)
    assert sheet.width == 4 * 96
    pixels = np.asarray(sheet).astype(np.float32)
    rows = sheet.height // (96 + max(14, int(96 * 0.09)))
    assert rows == 3  # template views, expressions, open jaw + mouth views
    # 4 template views + 3 named expressions + 4 jaw/mouth views; each shows something.
    tile_h = sheet.height // rows
    for i in range(11):
        r, c = divmod(i, 4)
        tile = pixels[r * tile_h:r * tile_h + 96, c * 96:(c + 1) * 96]
        assert (tile < 250).any(axis=-1).mean() > 0.05, (r, c)
    assert (pixels[2 * tile_h:2 * tile_h + 96, 3 * 96:] >= 250).all()  # the 12th slot stays empty


def openhead_or_skip():
    try:
        from geoavatar.head import load_head_model

        return load_head_model("openhead", mouth="geoavatar")
    except ImportError as err:  # the generated head model is not part of this checkout yet
        pytest.skip(f"OpenHead is not available: {err}")


def test_head_show_writes_a_contact_sheet_of_openhead(tmp_path):
    openhead_or_skip()
    out = tmp_path / "sheet" / "head.png"
    start = time.perf_counter()
    head_show(model="openhead", out=out, mouth="geoavatar", size=96)
    elapsed = time.perf_counter() - start
    image = np.asarray(Image.open(out).convert("RGB")).astype(np.float32)
    assert image.shape[1] == 4 * 96 and image.shape[0] >= 3 * 96
    assert image.std() > 20  # non-trivial content, not a blank sheet
    skin_like = (image[..., 0] > image[..., 2] + 20).mean()
    assert skin_like > 0.1, "expected skin-coloured heads on the sheet"
    assert not list(tmp_path.glob("sheet/.*")), "temporary file left behind"
    assert elapsed < 60


def test_missing_flame_gives_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("GEOAVATAR_FLAME_DIR", raising=False)
    with pytest.raises(FlameFileNotFoundError) as info:
        head_show(model="flame", out=tmp_path / "x.png", flame_dir=tmp_path / "nothing-here")
    message = str(info.value)
    assert "FLAME" in message and "nothing-here" in message
    assert not (tmp_path / "x.png").exists()
