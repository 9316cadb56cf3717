"""INSTA / metrical-tracker reader on a tiny set of `.frame` files written here in the tracker's format."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from geoavatar.data import DataConfig, DatasetError, HeadAvatarDataset, open_subject, read_insta
from geoavatar.data.insta import load_frame_file
from geoavatar.geometry import axis_angle_to_matrix
from geoavatar.render.camera import look_at

SIZE = 24  # INSTA images are square (512 in the benchmark)


def _six_d(axis_angle) -> np.ndarray:
    """PyTorch3D's matrix_to_rotation_6d: the first two ROWS of the matrix, [1, 6]."""
    matrix = axis_angle_to_matrix(torch.tensor(axis_angle, dtype=torch.float64))
    return matrix[:2, :].reshape(1, 6).numpy().astype(np.float32)


JAW = [0.2, 0.05, -0.03]
LEFT_EYE = [0.1, -0.2, 0.0]
RIGHT_EYE = [0.12, -0.18, 0.01]


def _payload(frame: int) -> dict:
    """What metrical-tracker's Tracker.save_checkpoint writes (numpy arrays inside a dict)."""
    viewmat = look_at([0.1 * frame, 0.0, 1.0], [0.0, 0.0, 0.0]).double().numpy()
    K = np.array([[[30.0, 0.0, SIZE / 2], [0.0, 30.0, SIZE / 2], [0.0, 0.0, 1.0]]], np.float32)
    return {
        "flame": {
            "exp": np.full((1, 100), 0.1 * frame, np.float32),
            "shape": np.linspace(0, 1, 300, dtype=np.float32)[None],
            "tex": np.zeros((1, 140), np.float32),
            "sh": np.zeros((1, 9, 3), np.float32),
            "eyes": np.concatenate([_six_d(LEFT_EYE), _six_d(RIGHT_EYE)], axis=1),
            "eyelids": np.array([[0.1, 0.2]], np.float32),
            "jaw": _six_d(JAW),
        },
        "camera": {"R": np.zeros((1, 6), np.float32), "t": np.zeros((1, 3), np.float32),
                   "fl": np.array([[5.0]], np.float32), "pp": np.zeros((1, 2), np.float32)},
        "opencv": {"R": viewmat[None, :3, :3].astype(np.float32), "t": viewmat[None, :3, 3].astype(np.float32), "K": K},
        "img_size": np.array([SIZE, SIZE]),
        "frame_id": f"{frame:05d}",
        "global_step": 100 + frame,
    }


def write_insta(root, frames: int = 5, first_image: int = 0, rgba: bool = True):
    (root / "checkpoint").mkdir(parents=True)
    (root / "images").mkdir()
    for i in range(frames):
        torch.save(_payload(i), root / "checkpoint" / f"{i:05d}.frame")
        rgb = np.full((SIZE, SIZE, 3), 10 * i, np.uint8)
        alpha = np.zeros((SIZE, SIZE, 1), np.uint8)
        alpha[4:20, 6:18] = 255
        pixels = np.concatenate([rgb, alpha], axis=-1) if rgba else rgb
        Image.fromarray(pixels).save(root / "images" / f"{i + first_image:05d}.png")


def test_reads_frames_and_converts_conventions(tmp_path):
    write_insta(tmp_path)
    subject = open_subject(tmp_path)
    assert subject.layout == "insta" and subject.head_model == "flame"
    assert subject.timesteps == (0, 1, 2, 3, 4)
    params = subject.params
    # The head stays at the origin: the camera moves.
    for key in ("rotation", "translation", "neck_pose"):
        assert params[key].abs().max() == 0, key
    assert torch.allclose(params["jaw_pose"], torch.tensor([JAW] * 5), atol=1e-5)
    assert torch.allclose(params["eyes_pose"], torch.tensor([LEFT_EYE + RIGHT_EYE] * 5), atol=1e-5)
    assert torch.allclose(params["expr"][:, 0], torch.tensor([0.0, 0.1, 0.2, 0.3, 0.4]))
    assert params["shape"].shape == (300,) and params["eyelids"].shape == (5, 2)
    for i, frame in enumerate(subject.frames):
        expected = look_at([0.1 * i, 0.0, 1.0], [0.0, 0.0, 0.0]).double().numpy()
        assert np.allclose(frame.viewmat, expected, atol=1e-6)
        assert np.allclose(frame.K, [[30, 0, SIZE / 2], [0, 30, SIZE / 2], [0, 0, 1]])
        assert frame.image_path.name == f"{i:05d}.png" and frame.mask_path is None  # mask = alpha


def test_six_d_uses_rows_not_columns(tmp_path):
    """A column-stored 6D would give the inverse rotation; the rows convention gives JAW back."""
    write_insta(tmp_path, frames=2)
    jaw = read_insta(tmp_path).params["jaw_pose"][0]
    assert torch.allclose(jaw, torch.tensor(JAW), atol=1e-5)
    assert not torch.allclose(jaw, -torch.tensor(JAW), atol=1e-2)


def test_dataset_items_from_insta(tmp_path):
    write_insta(tmp_path, frames=4)
    dataset = HeadAvatarDataset(open_subject(tmp_path), "all", DataConfig(test_frames=1), check_head=False)
    item = dataset[2]
    assert item["image"].shape == (SIZE, SIZE, 3) and item["mask"].shape == (SIZE, SIZE, 1)
    assert item["image"][0, 0, 0].item() == pytest.approx(20 / 255)
    assert item["mask"].sum().item() == pytest.approx(16 * 12)
    assert item["params"]["jaw_pose"].shape == (1, 3) and item["timestep"] == 2


def test_images_numbered_from_one(tmp_path):
    write_insta(tmp_path, frames=3, first_image=1)  # ffmpeg numbering, as FlashAvatar's data
    subject = read_insta(tmp_path)
    assert [f.image_path.name for f in subject.frames] == ["00001.png", "00002.png", "00003.png"]
    assert subject.timesteps == (0, 1, 2)


def test_masks_from_a_folder(tmp_path):
    write_insta(tmp_path, frames=2, rgba=False)
    (tmp_path / "matted").mkdir()
    for i in range(2):
        rgba = np.zeros((SIZE, SIZE, 4), np.uint8)
        rgba[:10, :, 3] = 255
        Image.fromarray(rgba).save(tmp_path / "matted" / f"{i:05d}.png")
    subject = read_insta(tmp_path)
    assert subject.frames[0].mask_path.parent.name == "matted"
    item = HeadAvatarDataset(subject, "all", DataConfig(test_frames=1), check_head=False)[0]
    assert item["mask"].sum().item() == pytest.approx(10 * SIZE)


# --- bad data ---------------------------------------------------------------------------------------


def test_missing_image_is_named(tmp_path):
    write_insta(tmp_path, frames=3)
    (tmp_path / "images" / "00001.png").unlink()
    with pytest.raises(DatasetError, match=r"3 \.frame files but images/ has 2 images"):
        read_insta(tmp_path)
    with pytest.raises(DatasetError, match=r"00001\.frame: image not found: .*00001\.png"):
        read_insta(tmp_path, strict_frame_count=False)


def test_wrong_array_shape_is_named(tmp_path):
    write_insta(tmp_path, frames=2)
    payload = _payload(1)
    payload["flame"]["eyes"] = payload["flame"]["eyes"][:, :6]
    torch.save(payload, tmp_path / "checkpoint" / "00001.frame")
    with pytest.raises(DatasetError, match=r"00001\.frame: 'flame.eyes' must have shape \(1, 12\), got \(1, 6\)"):
        read_insta(tmp_path)


def test_missing_key_is_named(tmp_path):
    write_insta(tmp_path, frames=2)
    payload = _payload(0)
    del payload["opencv"]["K"]
    torch.save(payload, tmp_path / "checkpoint" / "00000.frame")
    with pytest.raises(DatasetError, match=r"00000\.frame: missing 'opencv.K'"):
        read_insta(tmp_path)


class _Exploit:
    """Unpickling this with a plain unpickler would create a file (stand-in for running code)."""

    def __init__(self, target):
        self.target = str(target)

    def __reduce__(self):
        return (open, (self.target, "w"))


def test_unsafe_pickle_is_refused(tmp_path):
    write_insta(tmp_path, frames=2)
    marker = tmp_path / "pwned"
    payload = _payload(0)
    payload["evil"] = _Exploit(marker)
    torch.save(payload, tmp_path / "checkpoint" / "00000.frame")
    with pytest.raises(DatasetError, match=r"00000\.frame: not loadable .* safe loader"):
        load_frame_file(tmp_path / "checkpoint" / "00000.frame")
    assert not marker.exists()


def test_corrupt_file_is_named(tmp_path):
    write_insta(tmp_path, frames=2)
    (tmp_path / "checkpoint" / "00001.frame").write_bytes(b"not a torch file")
    with pytest.raises(DatasetError, match=r"00001\.frame: not loadable"):
        read_insta(tmp_path)
