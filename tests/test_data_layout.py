"""VHAP / GaussianAvatars layout: write -> read round trip, VHAP exports without geoavatar.json,
atomic writing, and the named errors for bad data."""

from __future__ import annotations

import json
import logging
import os

import numpy as np
import pytest
import torch
from PIL import Image

from geoavatar.data import DatasetError, LayoutWriter, SplitConfig, open_subject, read_layout
from geoavatar.render.camera import look_at, project

WIDTH, HEIGHT = 40, 32
K_PIX = np.array([[60.0, 0.0, 19.5], [0.0, 62.0, 16.5], [0.0, 0.0, 1.0]])


def _frame_params(t: int, expr_dim: int = 20) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(t)
    return {
        "expr": rng.normal(size=expr_dim).astype(np.float32),
        "rotation": rng.normal(scale=0.1, size=3),
        "neck_pose": rng.normal(scale=0.1, size=3),
        "jaw_pose": np.array([0.05 * t, 0.0, 0.0]),
        "eyes_pose": rng.normal(scale=0.1, size=6),
        "translation": rng.normal(scale=0.01, size=3),
    }


def _images(t: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(100 + t)
    image = rng.integers(0, 256, size=(HEIGHT, WIDTH, 3), dtype=np.uint8)
    mask = (rng.random((HEIGHT, WIDTH)) > 0.5).astype(np.uint8) * 255
    return image, mask


def _viewmat(t: int) -> torch.Tensor:
    angle = 0.1 * t
    return look_at([0.6 * np.sin(angle), 0.05, 0.6 * np.cos(angle)], [0.0, 0.0, 0.0]).double()


def write_subject(root, frames: int = 6, head_model: str = "openhead", static_offset: bool = True):
    shape = np.linspace(-1, 1, 30).astype(np.float32)
    offset = np.random.default_rng(0).normal(scale=1e-3, size=(25, 3)).astype(np.float32) if static_offset else None
    with LayoutWriter(root, head_model=head_model, image_size=(WIDTH, HEIGHT), shape=shape, static_offset=offset,
                      source="test", split=SplitConfig(test_frames=1)) as writer:
        for t in range(frames):
            image, mask = _images(t)
            writer.add_frame(t, image, _frame_params(t), _viewmat(t), K_PIX, mask=mask)
    return shape, offset


def test_write_read_round_trip(tmp_path):
    root = tmp_path / "subject"
    shape, offset = write_subject(root, frames=6)
    info = json.loads((root / "geoavatar.json").read_text())
    assert info == {"head_model": "openhead", "image_size": [WIDTH, HEIGHT], "background": [1.0, 1.0, 1.0],
                    "source": "test", "format_version": 1}

    subject = read_layout(root)
    assert subject.layout == "vhap" and subject.head_model == "openhead"
    assert subject.timesteps == tuple(range(6))
    # Padded to the FLAME npz sizes, leading entries preserved.
    assert subject.params["shape"].shape == (300,)
    assert torch.allclose(subject.params["shape"][:30], torch.from_numpy(shape))
    assert subject.params["shape"][30:].abs().max() == 0
    assert subject.params["expr"].shape == (6, 100)
    assert subject.params["static_offset"].shape == (1, 25, 3)
    assert torch.allclose(subject.params["static_offset"][0], torch.from_numpy(offset))
    for t in range(6):
        expected = _frame_params(t)
        row = subject.frame_params(t)
        assert torch.allclose(row["expr"][0, :20], torch.from_numpy(expected["expr"]))
        for key in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation"):
            assert row[key].shape == (1, expected[key].size)
            assert torch.allclose(row[key][0].double(), torch.from_numpy(expected[key]), atol=1e-6), key
        frame = subject.frames[t]
        assert np.allclose(frame.viewmat, _viewmat(t).numpy(), atol=1e-6)
        assert np.allclose(frame.K, K_PIX)
        assert (frame.width, frame.height) == (WIDTH, HEIGHT)
        image, mask = _images(t)
        assert np.array_equal(np.asarray(Image.open(frame.image_path)), image)
        assert np.array_equal(np.asarray(Image.open(frame.mask_path)), mask)
    # The canonical parameters are VHAP's: zero pose and expression, jaw open 0.3 rad.
    assert subject.canonical["jaw_pose"].tolist() == [[pytest.approx(0.3), 0.0, 0.0]]
    assert subject.canonical["expr"].abs().max() == 0
    # The split files follow our rule and are honoured on reading.
    assert subject.explicit_split is not None
    assert set(subject.explicit_split.train).isdisjoint(subject.explicit_split.test)


def test_written_files_look_like_vhap(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=4)
    transforms = json.loads((root / "transforms_train.json").read_text())
    frame = transforms["frames"][0]
    for key in ("timestep_index", "camera_index", "file_path", "fg_mask_path", "flame_param_path", "transform_matrix",
                "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x"):
        assert key in frame, key
    assert frame["file_path"] == "images/00000_00.png" and frame["flame_param_path"] == "flame_param/00000.npz"
    npz = np.load(root / "flame_param" / "00000.npz")
    assert {k: npz[k].shape for k in npz.files} == {
        "translation": (1, 3), "rotation": (1, 3), "neck_pose": (1, 3), "jaw_pose": (1, 3), "eyes_pose": (1, 6),
        "expr": (1, 100), "shape": (300,), "static_offset": (1, 25, 3),
    }
    # transform_matrix is camera-to-world with OpenGL axes: the camera looks down its -z axis at the head.
    c2w = np.array(frame["transform_matrix"])
    eye = c2w[:3, 3]
    assert np.allclose(-c2w[:3, 2], -eye / np.linalg.norm(eye), atol=1e-9)


def _write_vhap_export(root, frames: int = 3):
    """A monocular VHAP export as `export_as_nerf_dataset.py` writes it (no geoavatar.json)."""
    (root / "images").mkdir(parents=True)
    (root / "fg_masks").mkdir()
    (root / "flame_param").mkdir()
    shape = np.zeros(300, np.float32)
    static_offset = np.zeros((1, 5143, 3), np.float32)
    entries = []
    for t in range(frames):
        Image.fromarray(np.full((HEIGHT, WIDTH, 3), 200, np.uint8)).save(root / f"images/{t:05d}_00.png")
        Image.fromarray(np.full((HEIGHT, WIDTH), 255, np.uint8)).save(root / f"fg_masks/{t:05d}_00.png")
        np.savez(root / f"flame_param/{t:05d}.npz", translation=np.zeros((1, 3)), rotation=np.zeros((1, 3)),
                 neck_pose=np.zeros((1, 3)), jaw_pose=np.zeros((1, 3)), eyes_pose=np.zeros((1, 6)), shape=shape,
                 expr=np.full((1, 100), t, np.float32), static_offset=static_offset)
        c2w = np.eye(4)
        c2w[2, 3] = 1.0  # VHAP's monocular camera: at (0, 0, 1), looking at the origin
        entries.append({"timestep_index": t, "timestep_index_original": t, "timestep_id": f"frame_{t:05d}",
                        "camera_index": 0, "camera_id": "00", "cx": WIDTH / 2, "cy": HEIGHT / 2, "fl_x": 50.0,
                        "fl_y": 50.0, "h": HEIGHT, "w": WIDTH, "camera_angle_x": 0.7, "camera_angle_y": 0.6,
                        "transform_matrix": c2w.tolist(), "file_path": f"images/{t:05d}_00.png",
                        "fg_mask_path": f"fg_masks/{t:05d}_00.png", "flame_param_path": f"flame_param/{t:05d}.npz"})
    np.savez(root / "canonical_flame_param.npz", translation=np.zeros((1, 3)), rotation=np.zeros((1, 3)),
             neck_pose=np.zeros((1, 3)), jaw_pose=np.array([[0.3, 0, 0]]), eyes_pose=np.zeros((1, 6)), shape=shape,
             expr=np.zeros((1, 100)), static_offset=static_offset)
    cut = frames - 1
    for name, subset in (("train", entries[:cut]), ("val", []), ("test", entries[cut:])):
        data = {"frames": subset, "timestep_indices": [f["timestep_index"] for f in subset], "camera_indices": [0]}
        (root / f"transforms_{name}.json").write_text(json.dumps(data))
    return entries


def test_reads_vhap_export_unchanged(tmp_path, caplog):
    root = tmp_path / "vhap"
    _write_vhap_export(root)
    with caplog.at_level(logging.INFO, logger="geoavatar.data.layout"):
        subject = open_subject(root)
    assert subject.head_model == "flame"
    assert "no geoavatar.json" in caplog.text and "FLAME" in caplog.text
    assert subject.params["static_offset"].shape == (1, 5143, 3)
    assert subject.params["expr"][:, 0].tolist() == [0.0, 1.0, 2.0]
    assert subject.explicit_split.train == (0, 1) and subject.explicit_split.test == (2,)
    # The OpenGL camera at z = +1 sees the origin at the principal point, 1 m in front of it.
    frame = subject.frames[0]
    pixels, depth = project(torch.zeros(1, 3, dtype=torch.float64), torch.from_numpy(frame.viewmat),
                            torch.from_numpy(frame.K))
    assert torch.allclose(pixels, torch.tensor([[WIDTH / 2, HEIGHT / 2]], dtype=torch.float64))
    assert depth.item() == pytest.approx(1.0)


def test_writer_is_atomic(tmp_path):
    root = tmp_path / "subject"
    with pytest.raises(RuntimeError, match="boom"):
        with LayoutWriter(root, head_model="openhead", image_size=(WIDTH, HEIGHT), shape=np.zeros(10)) as writer:
            image, mask = _images(0)
            writer.add_frame(0, image, _frame_params(0), _viewmat(0), K_PIX, mask=mask)
            assert not root.exists()  # nothing under the target name while writing
            raise RuntimeError("boom")
    assert not root.exists()
    assert list(tmp_path.iterdir()) == []  # the temporary folder is gone too
    write_subject(root, frames=2)
    with pytest.raises(FileExistsError):
        LayoutWriter(root, head_model="openhead", image_size=(WIDTH, HEIGHT), shape=np.zeros(10))
    write_subject_overwrite = LayoutWriter(root, head_model="flame", image_size=(WIDTH, HEIGHT), shape=np.zeros(10),
                                           overwrite=True)
    image, mask = _images(0)
    write_subject_overwrite.add_frame(0, image, _frame_params(0), _viewmat(0), K_PIX)
    write_subject_overwrite.add_frame(1, image, _frame_params(1), _viewmat(1), K_PIX)
    write_subject_overwrite.finish(SplitConfig(test_frames=1))
    assert read_layout(root).head_model == "flame"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["subject"]
    mask = os.umask(0o022)
    os.umask(mask)
    assert root.stat().st_mode & 0o777 == 0o777 & ~mask  # a normal folder, not mkdtemp's 0700


def test_writer_rejects_bad_input(tmp_path):
    writer = LayoutWriter(tmp_path / "s", head_model="openhead", image_size=(WIDTH, HEIGHT), shape=np.zeros(10))
    image, _ = _images(0)
    with pytest.raises(ValueError, match="image is"):
        writer.add_frame(0, image[:-1], _frame_params(0), _viewmat(0), K_PIX)
    bad = _frame_params(0)
    bad["eyes_pose"] = np.zeros(3)
    with pytest.raises(ValueError, match="eyes_pose"):
        writer.add_frame(0, image, bad, _viewmat(0), K_PIX)
    writer.add_frame(0, image, _frame_params(0), _viewmat(0), K_PIX)
    with pytest.raises(ValueError, match="already written"):
        writer.add_frame(0, image, _frame_params(0), _viewmat(0), K_PIX)
    writer.abort()
    with pytest.raises(ValueError, match="head_model"):
        LayoutWriter(tmp_path / "t", head_model="smplx", image_size=(WIDTH, HEIGHT), shape=np.zeros(10))


# --- bad data: each error names the file -----------------------------------------------------------


def test_missing_image_is_named(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=3)
    (root / "images" / "00001_00.png").unlink()
    with pytest.raises(DatasetError, match=r"image not found: .*00001_00\.png"):
        read_layout(root)


def test_missing_npz_is_named(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=3)
    (root / "flame_param" / "00002.npz").unlink()
    with pytest.raises(DatasetError, match=r"parameter file not found: .*00002\.npz"):
        read_layout(root)


def test_wrong_parameter_shape_is_named(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=3)
    path = root / "flame_param" / "00001.npz"
    arrays = dict(np.load(path))
    arrays["eyes_pose"] = np.zeros((1, 3), np.float32)
    np.savez(path, **arrays)
    with pytest.raises(DatasetError, match=r"00001\.npz: 'eyes_pose' must have shape \(1, 6\), got \(1, 3\)"):
        read_layout(root)
    arrays.pop("eyes_pose")
    np.savez(path, **arrays)
    with pytest.raises(DatasetError, match=r"00001\.npz: missing parameter\(s\) eyes_pose"):
        read_layout(root)


def test_inconsistent_expression_sizes_are_named(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=3)
    path = root / "flame_param" / "00002.npz"
    arrays = dict(np.load(path))
    arrays["expr"] = np.zeros((1, 50), np.float32)
    np.savez(path, **arrays)
    with pytest.raises(DatasetError, match=r"00002\.npz: 'expr' has shape \(1, 50\)"):
        read_layout(root)


def test_mismatched_frame_counts(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=4)
    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    data["timestep_indices"].append(99)
    path.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="transforms_train.json.*do not match"):
        read_layout(root)


def test_shared_npz_is_a_frame_count_mismatch(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=3)
    for name in ("transforms.json", "transforms_train.json", "transforms_val.json", "transforms_test.json"):
        path = root / name
        data = json.loads(path.read_text())
        for frame in data["frames"]:
            frame["flame_param_path"] = "flame_param/00000.npz"
        path.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="share 1 flame_param files"):
        read_layout(root)


def test_bad_geoavatar_json(tmp_path):
    root = tmp_path / "subject"
    write_subject(root, frames=2)
    (root / "geoavatar.json").write_text(json.dumps({"head_model": "bfm", "format_version": 1}))
    with pytest.raises(DatasetError, match=r"geoavatar\.json: head_model must be one of flame, openhead"):
        read_layout(root)


def test_not_a_dataset(tmp_path):
    with pytest.raises(DatasetError, match="dataset folder not found"):
        open_subject(tmp_path / "nope")
    with pytest.raises(DatasetError, match="not a dataset"):
        open_subject(tmp_path)


def test_vhap_export_opens_as_a_dataset_when_flame_is_supplied(tmp_path, monkeypatch):
    """FLAME is located (not loaded) by the availability check, so placeholder files stand in for it."""
    from geoavatar.data import HeadAvatarDataset
    from geoavatar.head.flame import MASKS_FILE, MODEL_FILES

    flame_dir = tmp_path / "flame"
    flame_dir.mkdir()
    (flame_dir / MODEL_FILES["2023"]).write_bytes(b"")
    (flame_dir / MASKS_FILE).write_bytes(b"")
    monkeypatch.setenv("GEOAVATAR_FLAME_DIR", str(flame_dir))
    root = tmp_path / "vhap"
    _write_vhap_export(root, frames=3)
    test = HeadAvatarDataset(open_subject(root), "test")  # the export's own split files rule
    assert test.timesteps == (2,)
    item = test[0]
    assert item["params"]["static_offset"].shape == (1, 5143, 3) and item["params"]["expr"][0, 0] == 2.0
    assert item["image"][0, 0].tolist() == [pytest.approx(200 / 255)] * 3 and item["mask"].min() == 1.0
