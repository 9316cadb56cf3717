"""`geoavatar prepare` on a few frames of the real test video (128 px), and each bad-input error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import needs_shared_video, shared_video

needs_video = needs_shared_video("wojtek.mp4")


def _write_video(path: Path, frames: list[np.ndarray], fps: int = 25) -> Path:
    from geoavatar.io.video import Mp4Writer

    with Mp4Writer(path, fps=fps) as video:
        for rgb in frames:
            video.write(rgb)
    return path


def _config(video, out, **changes):
    from geoavatar.prep.pipeline import PrepareConfig

    # the photometric stage has its own tests (test_photometric.py): without it these run in seconds
    options = dict(video=video, out=out, size=128, max_frames=6, tracking_steps=(40, 60), photometric=False,
                   workers=1, progress=False, log=lambda message: None)
    options.update(changes)
    return PrepareConfig(**options)


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    from geoavatar.prep.pipeline import run_prepare

    out = tmp_path_factory.mktemp("prepare") / "wojtek"
    messages: list[str] = []
    config = _config(shared_video("wojtek.mp4"), out, log=messages.append)
    dataset = run_prepare(config)
    return config, out, dataset, messages


@needs_video
def test_prepare_writes_every_output(prepared):
    from geoavatar.data import open_dataset

    config, out, dataset, _ = prepared
    assert dataset == out / "dataset"
    for stage in ("frames", "landmarks", "masks", "tracking", "write"):
        assert (out / ".prepare" / f"{stage}.json").is_file()
    for name in ("transforms.json", "transforms_train.json", "transforms_test.json", "canonical_flame_param.npz",
                 "geoavatar.json"):
        assert (dataset / name).is_file(), name
    frames = json.loads((dataset / "transforms.json").read_text())["frames"]
    assert len(frames) == 6
    from PIL import Image

    for frame in frames:
        with Image.open(dataset / frame["file_path"]) as image:
            assert image.size == (128, 128) and image.mode == "RGB"
        with Image.open(dataset / frame["fg_mask_path"]) as mask:
            alpha = np.asarray(mask)
        assert alpha.shape == (128, 128)
        assert 0.05 < (alpha > 127).mean() < 0.8  # a head, not everything, not nothing
        assert alpha[-1].max() < 128 or alpha[0].max() < 128  # clothes at the bottom or background at the top cut
        with np.load(dataset / frame["flame_param_path"]) as npz:
            assert npz["expr"].shape == (1, 100) and npz["shape"].shape == (300,)
    with np.load(dataset / "canonical_flame_param.npz") as npz:  # the person's smooth static offset
        from geoavatar.head import load_head_data

        offset = npz["static_offset"]
        assert offset.shape == (1, load_head_data("openhead").num_vertices, 3) and np.isfinite(offset).all()
        assert 0.0 < np.abs(offset).max() < 0.03
    test = json.loads((dataset / "transforms_test.json").read_text())["timestep_indices"]
    assert test == [4, 5]  # the last 20 %, rounded up
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 6 and len(report["reprojection_error_over_face_width"]["per_frame"]) == 6
    assert report["reprojection_error_over_face_width"]["median"] < 0.05
    capture = report["capture"]  # the capture check: ranges per split, its verdict, its picture
    assert capture["splits"]["train"]["frames"] == 4 and capture["splits"]["test"]["frames"] == 2
    assert capture["verdict"].startswith("capture check: ") and (out / "coverage.png").stat().st_size > 10_000
    crop = out / ".prepare" / "frames" / "00000.png"  # the crops are linked into the dataset, not encoded again
    assert (dataset / frames[0]["file_path"]).read_bytes() == crop.read_bytes()
    import av

    with av.open(str(out / "overlay.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 6
    train = open_dataset(dataset, "train")  # the training side reads it
    assert len(train) == 4 and train[0]["image"].shape[:2] == (128, 128)


@needs_video
def test_the_dataset_does_not_depend_on_the_worker_count(prepared, tmp_path):
    """Every stage splits its frames into fixed ranges and blocks, so two worker processes write, byte for byte,
    the dataset one process writes."""
    from geoavatar.prep.pipeline import run_prepare

    _, out, dataset, _ = prepared
    other = run_prepare(_config(shared_video("wojtek.mp4"), tmp_path / "two", workers=2))
    names = sorted(path.relative_to(dataset) for path in dataset.rglob("*") if path.is_file())
    assert len(names) == 6 * 3 + 6  # images, masks, parameters; canonical, transforms x 4, geoavatar.json
    for name in names:
        assert (other / name).read_bytes() == (dataset / name).read_bytes(), name
    report, again = (json.loads((folder / "report.json").read_text()) for folder in (out, tmp_path / "two"))
    assert report == again


@needs_video
def test_tracking_reprojects_landmarks(prepared):
    _, out, _, _ = prepared
    fit = np.load(out / ".prepare" / "tracking.npz")
    marks = np.load(out / ".prepare" / "landmarks.npz")
    detected = marks["filtered"][:, fit["landmark_ids"], :2]
    width = np.linalg.norm(marks["filtered"][:, 234, :2] - marks["filtered"][:, 454, :2], axis=-1)
    error = np.median(np.linalg.norm(fit["projected"] - detected, axis=-1), axis=1) / width
    assert np.allclose(error, fit["errors"], atol=1e-5)
    assert error.max() < 0.05
    assert 0.0 <= fit["param_jaw_pose"][:, 0].min() + 1e-3


@needs_video
def test_rerun_skips_complete_stages(prepared):
    from geoavatar.prep.pipeline import STAGES, run_prepare

    config, out, _, _ = prepared
    before = (out / "dataset" / "transforms.json").stat().st_mtime_ns
    messages: list[str] = []
    config.log = messages.append
    run_prepare(config)
    assert sum("skipped" in m for m in messages) == len(STAGES)
    assert (out / "dataset" / "transforms.json").stat().st_mtime_ns == before


@needs_video
def test_tracking_in_chunks_takes_the_same_steps(prepared, monkeypatch):
    """The tracker's data term differentiated a few frames at a time (a long video's graph would not fit) sums to
    the gradient of the whole: the fit is the same up to the float rounding of the sums."""
    from geoavatar.prep import tracking
    from geoavatar.prep.pipeline import load_tracking_head

    config, out, _, _ = prepared
    marks = np.load(out / ".prepare" / "landmarks.npz")
    _, model = load_tracking_head(config)
    principal = np.full((6, 2), 64.0)
    settings = tracking.TrackingConfig(rigid_steps=10, full_steps=15, fit_static_offset=False)
    fits = []
    for chunk in (1024, 4):  # one chunk of 6 frames; chunks of 3
        monkeypatch.setattr(tracking, "DATA_CHUNK", chunk)
        fits.append(tracking.track(model, marks["filtered"], marks["confidence"], principal, 128, settings))
    for key, value in fits[0].params.items():
        np.testing.assert_allclose(fits[1].params[key], value, atol=2e-5, err_msg=key)
    assert fits[1].log[-1].split(",")[1] == fits[0].log[-1].split(",")[1]  # the data term, as logged


def test_landmark_head_matches_full_model():
    from geoavatar.head import HeadModel, load_head_data
    from geoavatar.head.smooth_offset import smooth_offset
    from geoavatar.prep.tracking import landmark_head, offset_rows

    data = load_head_data("openhead")
    full, reduced = HeadModel(data), landmark_head(data)
    params = full.zero_params(3)
    generator = torch.Generator().manual_seed(0)
    for key in params:
        params[key] = 0.2 * torch.randn(params[key].shape, generator=generator)
    expected = full.forward_params(params).landmarks
    assert torch.allclose(reduced.forward_params(params).landmarks, expected, atol=1e-6)
    subset = reduced.landmark_vertex_ids  # the tracker's batched vertex-subset mode
    assert torch.allclose(reduced.forward_params(params, vertex_ids=subset).landmarks, expected, atol=1e-6)
    assert torch.allclose(full.forward_params(params, vertex_ids=full.landmark_vertex_ids).landmarks, expected, atol=1e-6)
    assert reduced.num_vertices < full.num_vertices // 10

    # With a static offset: the reduced model's rows of the smooth field give the full model's landmarks.
    offsets = smooth_offset(data, reduced.data.metadata["vertex_ids"])
    theta = 0.004 * np.random.default_rng(1).standard_normal((offsets.num_free, 3))
    params["static_offset"] = torch.as_tensor(offsets.extend(theta), dtype=torch.float32)
    expected = full.forward_params(params).landmarks
    reduced_params = dict(params, static_offset=torch.as_tensor(offset_rows(offsets, reduced) @ theta, dtype=torch.float32))
    assert torch.allclose(reduced.forward_params(reduced_params, vertex_ids=subset).landmarks, expected, atol=1e-6)
    assert torch.allclose(full.forward_params(params, vertex_ids=full.landmark_vertex_ids).landmarks, expected, atol=1e-6)


def test_crop_boxes_are_smooth_and_inside():
    from geoavatar.prep.video import smooth_crop_boxes

    rng = np.random.default_rng(0)
    centres = np.array([200.0, 150.0]) + rng.normal(0, 5, (50, 2))  # jittery detections
    found = np.ones(50, bool)
    found[10:13] = False
    boxes = smooth_crop_boxes(centres, np.full(50, 100.0), found, (640, 360), scale=2.4)
    assert np.allclose(boxes[:, 2], 240.0)
    assert np.abs(np.diff(boxes[:, :2], axis=0)).max() < 1.0  # jitter of 5 px smoothed away
    assert (boxes[:, 0] - 120 >= 0).all() and (boxes[:, 1] + 120 <= 360).all()


def _set_display_rotation(path: Path, quarter_turns_clockwise: int) -> None:
    """Write the display matrix a phone writes into the mp4's track header (tkhd, version 0)."""
    import struct

    data = bytearray(path.read_bytes())
    box = data.index(b"tkhd")
    assert data[box + 4] == 0, "tkhd version 0 expected"
    cos, sin = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns_clockwise % 4]
    matrix = [cos << 16, sin << 16, 0, -sin << 16, cos << 16, 0, 0, 0, 1 << 30]  # 16.16 and 2.30 fixed point
    data[box + 44:box + 80] = struct.pack(">9i", *matrix)
    path.write_bytes(bytes(data))


def test_rotation_metadata_is_honoured(tmp_path):
    from geoavatar.prep.video import decode_frames, probe_video

    upright = np.zeros((64, 48, 3), np.uint8)  # portrait, with a bright block at the top left
    upright[:, :, 2] = np.linspace(0, 200, 48, dtype=np.uint8)[None]
    upright[4:20, 4:16] = 255
    stored = np.ascontiguousarray(np.rot90(upright, k=1))  # the sensor's landscape frame [48, 64, 3]
    video = _write_video(tmp_path / "phone.mp4", [stored] * 3)
    _set_display_rotation(video, 1)  # shown turned a quarter clockwise
    info = probe_video(video)
    assert (info.width, info.height) == (48, 64) and info.rotation == 270
    frames = [rgb for _, rgb in decode_frames(video)]
    assert len(frames) == 3 and frames[0].shape == (64, 48, 3)
    assert np.abs(frames[0].astype(float) - upright).mean() < 6.0  # upright again, up to the codec's loss


def test_unreadable_file_is_a_clear_error(tmp_path):
    from geoavatar.prep.errors import PrepareError
    from geoavatar.prep.pipeline import run_prepare

    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    out = tmp_path / "out"
    with pytest.raises(PrepareError, match="broken.mp4.*not a readable video"):
        run_prepare(_config(bad, out))
    assert not out.exists()
    with pytest.raises(PrepareError, match="file not found"):
        run_prepare(_config(tmp_path / "missing.mp4", out))
    with pytest.raises(PrepareError, match="cannot make the output folder"):  # --out under a file
        run_prepare(_config(bad, bad / "out"))


def test_video_without_a_face_is_a_clear_error(tmp_path):
    from geoavatar.prep.errors import PrepareError
    from geoavatar.prep.pipeline import run_prepare

    video = _write_video(tmp_path / "blank.mp4", [np.full((96, 96, 3), 40 + 20 * i, np.uint8) for i in range(8)])
    out = tmp_path / "out"
    with pytest.raises(PrepareError, match="no face was found in any of its 6 frames"):
        run_prepare(_config(video, out))
    assert not out.exists()


@needs_video
def test_too_short_video_is_a_clear_error(tmp_path):
    from geoavatar.prep.errors import PrepareError
    from geoavatar.prep.pipeline import run_prepare
    from geoavatar.prep.video import decode_frames

    frames = [rgb[::4, ::4].copy() for _, rgb in decode_frames(shared_video("wojtek.mp4"), max_frames=3)]
    video = _write_video(tmp_path / "short.mp4", frames)
    out = tmp_path / "out"
    with pytest.raises(PrepareError, match="3 frame.*fewer than the 5 needed"):
        run_prepare(_config(video, out))
    assert not out.exists()


def test_flame_without_files_names_what_is_missing(tmp_path):
    from geoavatar.prep.errors import PrepareError
    from geoavatar.prep.pipeline import load_tracking_head

    with pytest.raises(PrepareError, match="flame2023.pkl"):
        load_tracking_head(_config(tmp_path / "v.mp4", tmp_path / "o", head="flame", flame_dir=tmp_path))


@needs_video
def test_head_region_keeps_the_hair_of_a_bowed_head(prepared):
    from geoavatar.head import landmarks_mediapipe as mpids
    from geoavatar.prep.masks import HAIR_MIN_REACH, HAIR_SCALE, head_region_polygons

    _, out, _, _ = prepared
    points = np.load(out / ".prepare" / "landmarks.npz")["filtered"][0, :, :2].astype(np.float64)  # [478, 2]
    width = np.linalg.norm(points[234] - points[454])
    bowed = points.copy()
    centre_y = points[list(mpids.FACE_OVAL), 1].mean()
    bowed[:, 1] = centre_y + 0.6 * (points[:, 1] - centre_y)  # a forward bow foreshortens the face vertically
    for landmarks in (points, bowed):
        head, _ = head_region_polygons(landmarks)
        centre = landmarks[list(mpids.FACE_OVAL)].mean(0)
        reach = centre[1] - head[:, 1].min()  # image y points down: the top of the region above the oval's centre
        assert reach >= 0.99 * HAIR_SCALE * HAIR_MIN_REACH * width
