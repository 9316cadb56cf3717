"""The torch Dataset: item shapes and dtypes, downscaling with K, the decode cache, the split rule,
and the error for a head model that is not available."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

import geoavatar.data.dataset as dataset_module
from geoavatar.data import (
    DataConfig,
    DatasetError,
    HeadAvatarDataset,
    LayoutWriter,
    ShortVideoWarning,
    SplitConfig,
    open_subject,
    split_timesteps,
)
from geoavatar.data.splits import ExplicitSplit
from geoavatar.head.base import JOINT_NAMES, HeadModel, HeadModelData
from geoavatar.render.camera import look_at, project

WIDTH, HEIGHT = 64, 48
K_PIX = np.array([[70.0, 0.0, 32.0], [0.0, 70.0, 24.0], [0.0, 0.0, 1.0]])


def _write(root, frames: int = 8, head_model: str = "openhead", test_frames: int = 2):
    rng = np.random.default_rng(0)
    with LayoutWriter(root, head_model=head_model, image_size=(WIDTH, HEIGHT), shape=rng.normal(size=10),
                      static_offset=np.zeros((6, 3)), split=SplitConfig(test_frames=test_frames)) as writer:
        for t in range(frames):
            image = np.zeros((HEIGHT, WIDTH, 3), np.uint8)
            image[..., 0] = t * 10
            image[:, WIDTH // 2:, 1] = 255  # right half green: checks downscaling keeps the layout
            mask = np.zeros((HEIGHT, WIDTH), np.uint8)
            mask[8:40, 16:48] = 255
            params = {"expr": np.full(5, float(t)), "rotation": np.zeros(3), "neck_pose": np.zeros(3),
                      "jaw_pose": np.array([0.1, 0.0, 0.0]), "eyes_pose": np.zeros(6), "translation": np.zeros(3)}
            writer.add_frame(t, image, params, look_at([0.0, 0.0, 0.5], [0.0, 0.0, 0.0]), K_PIX, mask=mask)


@pytest.fixture
def subject(tmp_path):
    _write(tmp_path / "subject")
    return open_subject(tmp_path / "subject")


def test_item_shapes_and_dtypes(subject):
    dataset = HeadAvatarDataset(subject, "train")
    assert len(dataset) == 6 and dataset.timesteps == (0, 1, 2, 3, 4, 5)
    item = dataset[3]
    assert item["image"].shape == (HEIGHT, WIDTH, 3) and item["image"].dtype == torch.float32
    assert item["mask"].shape == (HEIGHT, WIDTH, 1) and item["mask"].dtype == torch.float32
    assert 0.0 <= item["image"].min() and item["image"].max() <= 1.0
    assert item["image"][0, 0, 0].item() == pytest.approx(30 / 255)
    assert item["mask"].sum().item() == 32 * 32
    assert item["viewmat"].shape == (4, 4) and item["viewmat"].dtype == torch.float32
    assert item["K"].shape == (3, 3) and item["K"].dtype == torch.float32
    assert torch.allclose(item["K"], torch.tensor(K_PIX, dtype=torch.float32))
    assert item["background"].tolist() == [1.0, 1.0, 1.0]
    assert (item["timestep"], item["row"], item["camera"]) == (3, 3, 0)
    assert (item["width"], item["height"]) == (WIDTH, HEIGHT)
    params = item["params"]
    assert {k: tuple(v.shape) for k, v in params.items()} == {
        "translation": (1, 3), "rotation": (1, 3), "neck_pose": (1, 3), "jaw_pose": (1, 3), "eyes_pose": (1, 6),
        "expr": (1, 100), "shape": (300,), "static_offset": (1, 6, 3),
    }
    assert all(v.dtype == torch.float32 for v in params.values())
    assert params["expr"][0, :5].tolist() == [3.0] * 5


def test_items_collate_and_drive_a_head_model(subject):
    """The params of an item feed HeadModel.forward_params directly (the npz layout is the model's)."""
    rng = np.random.default_rng(1)
    vertices = 8
    lbs = np.zeros((vertices, len(JOINT_NAMES)), np.float32)
    lbs[:, 0] = 1.0
    data = HeadModelData(
        name="tiny", v_template=rng.normal(size=(vertices, 3)).astype(np.float32),
        faces=np.array([[0, 1, 2], [2, 3, 4]]), shapedirs=rng.normal(size=(vertices, 3, 4)).astype(np.float32),
        exprdirs=rng.normal(size=(vertices, 3, 3)).astype(np.float32),
        j_regressor=np.full((len(JOINT_NAMES), vertices), 1.0 / vertices, np.float32), lbs_weights=lbs,
    )
    item = HeadAvatarDataset(subject, "train")[2]
    out = HeadModel(data).forward_params(item["params"])
    assert out.vertices.shape == (1, vertices, 3) and torch.isfinite(out.vertices).all()
    batch = next(iter(DataLoader(HeadAvatarDataset(subject, "train"), batch_size=3)))
    assert batch["image"].shape == (3, HEIGHT, WIDTH, 3) and batch["params"]["expr"].shape == (3, 1, 100)


def test_resolution_downscales_and_scales_K(subject):
    full = HeadAvatarDataset(subject, "test")[0]
    half = HeadAvatarDataset(subject, "test", DataConfig(resolution=32))[0]
    assert half["image"].shape == (24, 32, 3) and half["mask"].shape == (24, 32, 1)
    assert (half["width"], half["height"]) == (32, 24)
    assert torch.allclose(half["K"], torch.tensor([[35.0, 0, 16], [0, 35, 12], [0, 0, 1]]))
    # A 3D point lands at half the pixel coordinates (pixel centres at +0.5 scale exactly).
    point = torch.tensor([[0.03, -0.02, 0.05]])
    px_full, _ = project(point, full["viewmat"], full["K"])
    px_half, _ = project(point, half["viewmat"], half["K"])
    assert torch.allclose(px_half, px_full / 2, atol=1e-5)
    # Area downscaling keeps the content: the right half is green, the mask box halves.
    assert half["image"][:, 16:, 1].min() == 1.0 and half["image"][:, :16, 1].max() == 0.0
    assert half["mask"].sum().item() == pytest.approx(16 * 16)
    # Never upscaled.
    same = HeadAvatarDataset(subject, "test", DataConfig(resolution=512))[0]
    assert same["image"].shape == (HEIGHT, WIDTH, 3)


def test_cache_decodes_each_frame_once(subject, monkeypatch):
    dataset = HeadAvatarDataset(subject, "train", DataConfig(resolution=32)).preload()
    assert dataset.cache_bytes() == 6 * 24 * 32 * 4

    def fail(*args, **kwargs):
        raise AssertionError("a cached dataset decoded an image again")

    monkeypatch.setattr(dataset_module, "decode_frame", fail)
    for index in range(len(dataset)):
        assert dataset[index]["image"].shape == (24, 32, 3)
    uncached = HeadAvatarDataset(subject, "train", DataConfig(cache="none"))
    with pytest.raises(AssertionError, match="decoded"):
        uncached[0]


def test_missing_image_at_decode_time_is_named(subject):
    dataset = HeadAvatarDataset(subject, "train")
    dataset.frames[1].image_path.unlink()
    with pytest.raises(DatasetError, match=r"file not found: .*00001_00\.png"):
        dataset[1]


def test_image_size_mismatch_is_named(subject):
    from PIL import Image

    frame = subject.frames[0]
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(frame.image_path)
    with pytest.raises(DatasetError, match=r"00000_00\.png is 10x10 but .* declares 64x48"):
        HeadAvatarDataset(subject, "train")[0]


def test_every_bad_file_is_named_before_any_frame_is_decoded(subject, monkeypatch):
    from PIL import Image

    frames = subject.frames
    frames[0].image_path.write_bytes(b"\x89PNG\r\n\x1a\n garbage, not an image")  # corrupt
    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(frames[2].image_path)  # wrong size
    data = frames[3].image_path.read_bytes()
    frames[3].image_path.write_bytes(data[: len(data) // 2])  # truncated: header intact, no IEND
    Image.fromarray(np.zeros((HEIGHT, WIDTH + 1), np.uint8)).save(frames[4].mask_path)  # mask of the wrong size
    frames[5].mask_path.unlink()

    def fail(*args, **kwargs):
        raise AssertionError("the check decoded an image")

    monkeypatch.setattr(dataset_module, "decode_frame", fail)
    with pytest.raises(DatasetError) as raised:
        HeadAvatarDataset(subject, "train")  # made, not yet read: training would not reach step 0
    message = str(raised.value)
    assert "\n" not in message and message.startswith("5 bad image files: ")
    assert f"{frames[0].image_path}: not a readable image" in message
    assert f"{frames[2].image_path} is 12x10 but " in message and "declares 64x48" in message
    assert f"{frames[3].image_path}: truncated PNG" in message
    assert f"{frames[4].mask_path} is 65x48" in message
    assert f"file not found: {frames[5].mask_path}" in message
    assert str(frames[1].image_path) not in message  # good files are not named
    # The test split's frames (6, 7) are untouched: that split still opens.
    assert len(HeadAvatarDataset(subject, "test")) == 2


def test_bad_file_list_is_capped(tmp_path):
    _write(tmp_path / "many", frames=14, test_frames=1)
    subject = open_subject(tmp_path / "many")
    for frame in subject.frames:
        frame.image_path.write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=r"^13 bad image files: .*; and 3 more$") as raised:
        HeadAvatarDataset(subject, "train")
    assert str(raised.value).count("not a readable image") == dataset_module.MAX_NAMED


def test_header_check_accepts_jpeg_and_rgba_png(tmp_path):
    from PIL import Image

    image = Image.fromarray(np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8))
    image.save(tmp_path / "a.jpg", quality=90)
    image.convert("RGBA").save(tmp_path / "b.png")
    for name in ("a.jpg", "b.png"):
        assert dataset_module.header_problem(tmp_path / name, WIDTH, HEIGHT, "test") is None
    data = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "c.jpg").write_bytes(data[: len(data) - 200])
    assert "truncated JPEG" in dataset_module.header_problem(tmp_path / "c.jpg", WIDTH, HEIGHT, "test")


# --- splits ----------------------------------------------------------------------------------------


def test_split_holds_out_the_last_350_frames():
    split = split_timesteps(range(1000))
    assert split.test == tuple(range(650, 1000)) and split.train == tuple(range(650))
    assert split.source == "rule"
    assert len(split.val) == 4 and set(split.val) <= set(split.train) and split.val[0] == 0


def test_split_test_frames_option_and_no_leak():
    split = split_timesteps(list(reversed(range(100))), SplitConfig(test_frames=30, val_frames=3))
    assert split.test == tuple(range(70, 100)) and split.train == tuple(range(70))
    assert set(split.train).isdisjoint(split.test) and set(split.val).isdisjoint(split.test)
    assert split.val == (0, 34, 69)
    everything = split_timesteps(range(10), SplitConfig(test_frames=0))
    assert everything.test == () and everything.train == tuple(range(10))


def test_short_video_falls_back_to_a_quarter():
    with pytest.warns(ShortVideoWarning, match="400 frames are too few .* last 350 .* last 100"):
        split = split_timesteps(range(400))  # wojtek.mp4: 400 frames
    assert split.test == tuple(range(300, 400)) and split.train == tuple(range(300))
    with pytest.warns(ShortVideoWarning):
        assert split_timesteps(range(5)).test == (3, 4)  # ceil(25 % of 5) = 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(split_timesteps(range(700)).test) == 350  # exactly twice: no fallback


def test_explicit_split_files_rule_unless_overridden():
    explicit = ExplicitSplit(train=(0, 1, 2, 3, 4, 5, 6), val=(), test=(7, 8, 9))
    honoured = split_timesteps(range(10), SplitConfig(), explicit)
    assert honoured.source == "files" and honoured.test == (7, 8, 9) and set(honoured.val) <= set(honoured.train)
    overridden = split_timesteps(range(10), SplitConfig(test_frames=2), explicit)
    assert overridden.source == "rule" and overridden.test == (8, 9)
    leaking = ExplicitSplit(train=(0, 1, 2, 3), val=(), test=(3, 4))
    with pytest.raises(DatasetError, match="share 1 timestep"):
        split_timesteps(range(5), SplitConfig(), leaking)


def test_dataset_splits_follow_the_files_and_the_option(subject):
    assert HeadAvatarDataset(subject, "test").timesteps == (6, 7)
    assert HeadAvatarDataset(subject, "test", DataConfig(test_frames=3)).timesteps == (5, 6, 7)
    assert HeadAvatarDataset(subject, "train", DataConfig(test_frames=3)).timesteps == (0, 1, 2, 3, 4)
    val = HeadAvatarDataset(subject, "val")
    assert set(val.timesteps) <= set(range(6)) and len(val) == 4
    assert len(HeadAvatarDataset(subject, "all")) == 8
    with pytest.raises(ValueError, match="unknown split"):
        HeadAvatarDataset(subject, "validation")


# --- head model availability -----------------------------------------------------------------------


def test_flame_dataset_without_flame_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.delenv("GEOAVATAR_FLAME_DIR", raising=False)
    _write(tmp_path / "flame_subject", frames=4, head_model="flame", test_frames=1)
    subject = open_subject(tmp_path / "flame_subject")
    with pytest.raises(DatasetError, match="head model 'flame' .*FLAME is not available"):
        HeadAvatarDataset(subject, "train")
    with pytest.raises(DatasetError, match="FLAME is not available") as err:
        HeadAvatarDataset(subject, "train", head_options={"flame_dir": tmp_path / "no_flame_here"})
    assert "no_flame_here" in str(err.value)  # flame.py's message, naming the folder, is passed on
    # Skipping the check (e.g. to inspect the data) still works.
    assert len(HeadAvatarDataset(subject, "train", check_head=False)) == 3
