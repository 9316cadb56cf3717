"""Synthetic subjects (geoavatar synth): files, reader round trip, masks, determinism, tracker error,
the novel test segment, and clear errors. Small: 64-80 px, 8 frames."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from geoavatar.data.layout import read_layout
from geoavatar.data.splits import split_timesteps
from geoavatar.data.synth import SynthConfig, TrackingNoise, generate_dataset, script_motion, held_out_frame_count
from geoavatar.data.synth.actor import build_actor
from geoavatar.data.synth.generate import GT_DIR, META_FILE, motion_to_params
from geoavatar.data.synth.motion import JAW_MAX, TEST_JAW_FLOOR, TRAIN_PITCH_RANGE, TRAIN_ROLL_MAX, TRAIN_YAW_RANGE
from geoavatar.data.synth.render import frontal_camera
from geoavatar.data.synth.subjects import get_subject
from geoavatar.data.synth.tracking import apply_tracking_noise
from geoavatar.errors import OptionError
from geoavatar.render.camera import world_to_camera
from geoavatar.render.camera import scale_intrinsics
from geoavatar.render.mesh import box_downsample, rasterize_mesh

FRAMES = 8
SIZE = 64


def _config(**changes) -> SynthConfig:
    base = dict(subject=0, frames=FRAMES, size=SIZE, seed=0, workers=1)
    base.update(changes)
    return SynthConfig(**base)


def _digest(root: Path) -> dict[str, str]:
    """Content hashes of everything but the timing metadata and the optional preview."""
    out = {}
    for path in sorted(root.rglob("*")):
        if path.is_file() and path.name not in (META_FILE, "preview.png"):
            out[str(path.relative_to(root))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "s0"
    return generate_dataset(out, _config(), preview=True, progress=False)


# --- motion and tracker error (no rendering) -----------------------------------------------------


@pytest.mark.parametrize("frames", [10, 40, 160, 300])
def test_test_segment_is_open_mouth_speech_in_novel_combinations_at_seen_poses(frames):
    motion = script_motion(frames, seed=3)
    cut = motion.test_start
    assert frames - cut == held_out_frame_count(frames)
    # Head poses stay inside the training ranges: the test is about the mouth, not extrapolation.
    assert TRAIN_YAW_RANGE[0] <= np.degrees(motion.yaw[cut:]).min() and np.degrees(motion.yaw[cut:]).max() <= TRAIN_YAW_RANGE[1]
    assert TRAIN_PITCH_RANGE[0] <= np.degrees(motion.pitch[cut:]).min() and np.degrees(motion.pitch[cut:]).max() <= TRAIN_PITCH_RANGE[1]
    assert np.degrees(np.abs(motion.roll[cut:])).max() <= TRAIN_ROLL_MAX + 1e-6
    # The mouth is open (teeth visible) once the test speech has eased in, never beyond the training jaw range.
    assert motion.jaw[cut + max(1, (frames - cut) // 4):].min() >= 0.5 * TEST_JAW_FLOOR
    assert motion.jaw.max() <= JAW_MAX + 1e-6
    # Speaking while grinning (smile + stretch with the jaw open): never together in the training part.
    combo = np.minimum(motion.expressions["smile"], motion.expressions["mouth_stretch"] / 0.6) * (motion.jaw >= 0.15)
    assert combo[cut:].max() > 0.5
    assert combo[:cut].max() < 0.05


@pytest.mark.parametrize("frames", [2, 8, 300, 699, 700, 1000])
def test_test_segment_is_the_data_layers_test_split(frames):
    split = split_timesteps(list(range(frames)), source="t") if frames >= 700 else None
    if split is None:
        with pytest.warns(UserWarning):
            split = split_timesteps(list(range(frames)), source="t")
    assert held_out_frame_count(frames) == len(split.test)


def test_long_motion_covers_the_dynamicface_protocol():
    motion = script_motion(300, seed=0)
    cut = motion.test_start
    assert np.degrees(motion.yaw[:cut]).max() >= 28 and np.degrees(motion.yaw[:cut]).min() <= -20
    assert np.degrees(motion.pitch[:cut]).max() >= 14 and np.degrees(motion.pitch[:cut]).min() <= -11
    assert motion.jaw[:cut].max() > 0.25  # talking opens the mouth
    assert (motion.blink_left > 0.9).sum() >= 2  # blinks every 2-4 s over 12 s
    assert np.abs(np.diff(motion.gaze, axis=0)).max() > 0.0
    labels = {label for _, _, label in motion.segments}
    assert {"talking", "hold:smile", "hold:surprise", "test:speech"} <= labels
    assert script_motion(300, seed=0).yaw.tolist() == motion.yaw.tolist()
    assert not np.allclose(script_motion(300, seed=1).jaw, motion.jaw)


def _gt_params(frames=40):
    actor = build_actor(get_subject(0))
    params, _ = motion_to_params(script_motion(frames, 0), actor)
    return actor, params


def test_tracking_noise_off_returns_the_ground_truth_and_on_is_realistic():
    actor, gt = _gt_params()
    kw = dict(fps=25.0, seed=0, num_expr_used=actor.head.exprdirs.shape[-1],
              num_shape_used=actor.head.shapedirs.shape[-1])
    off = apply_tracking_noise(gt, TrackingNoise(enabled=False), **kw)
    for key in gt:
        np.testing.assert_array_equal(off[key], gt[key])
    on = apply_tracking_noise(gt, TrackingNoise(), **kw)
    rot_err = np.degrees(np.linalg.norm(on["rotation"] - gt["rotation"], axis=1))
    assert 0.05 < rot_err.mean() < 5.0
    trans_err_mm = 1000 * np.abs(on["translation"] - gt["translation"])
    assert 0.1 < trans_err_mm.mean() < 20.0
    assert 0.01 < np.abs(on["expr"] - gt["expr"]).mean() < 0.5
    assert not np.allclose(on["jaw_pose"], gt["jaw_pose"])
    # Temporally correlated: consecutive frames' errors are far more alike than random pairs.
    err = on["expr"] - gt["expr"]
    assert np.abs(np.diff(err, axis=0)).mean() < 0.7 * np.abs(err - err[::-1]).mean()


# --- the actor ----------------------------------------------------------------------------------


@pytest.mark.parametrize("index", [0, 1, 2])
def test_actor_has_geometry_the_head_model_cannot_express(index):
    actor = build_actor(get_subject(index))
    lo, median, hi = actor.info["hair_offset_cm"]
    assert 0.1 <= lo and 1.0 <= median <= 3.0 and hi <= 3.7
    assert actor.info["ear_offset_max_mm"] > 2.0
    assert ("glasses_vertices" in actor.info) == get_subject(index).glasses
    assert ("beard_vertices" in actor.info) == get_subject(index).beard
    # With the same parameters, the actor's head vertices are the head model's except at the ears.
    params = actor.model.zero_params(2)
    params["shape"] = torch.from_numpy(actor.shape)
    params["jaw_pose"][:, 0] = 0.2
    params["rotation"][:, 1] = 0.3
    from geoavatar.head.base import HeadModel

    bare = HeadModel(actor.head).forward_params(params).vertices
    full = actor.model.forward_params(params).vertices[:, : actor.num_head_vertices]
    ears = np.zeros(actor.num_head_vertices, bool)
    for name in ("left_ear", "right_ear"):
        ears[np.asarray(actor.head.regions[name])] = True
    diff = (full - bare).norm(dim=-1)  # [2, V]
    assert diff[:, ~torch.from_numpy(ears)].max() < 1e-5
    assert diff[:, torch.from_numpy(ears)].max() > 2e-3


# --- the dataset ---------------------------------------------------------------------------------


def test_dataset_files_and_reader_round_trip(dataset):
    subject = read_layout(dataset)
    assert subject.head_model == "openhead"
    assert subject.num_timesteps == FRAMES
    assert subject.info.image_size == (SIZE, SIZE)
    split = subject.split()
    assert len(split.test) == held_out_frame_count(FRAMES) and max(split.train) < min(split.test)
    for t in range(FRAMES):
        assert (dataset / "images" / f"{t:05d}_00.png").is_file()
        assert (dataset / "fg_masks" / f"{t:05d}_00.png").is_file()
        assert (dataset / GT_DIR / f"{t:05d}.npz").is_file()
    assert (dataset / "preview.png").is_file()
    meta = json.loads((dataset / META_FILE).read_text())
    assert meta["test_start"] == FRAMES - held_out_frame_count(FRAMES)
    assert not meta["channels_unmapped"], meta["channels_unmapped"]
    # static_offset is written as zeros: the hair, ears, ... are not in the parameters.
    assert float(subject.params["static_offset"].abs().max()) == 0.0
    with np.load(dataset / GT_DIR / "00003.npz") as gt:
        assert set(gt.files) >= {"translation", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "expr", "shape"}
        # Tracker error on by default: written parameters differ from the ground truth.
        assert not np.allclose(gt["rotation"], subject.params["rotation"][3:4].numpy())
    assert subject.info.background == pytest.approx(get_subject(0).background_rgb)
    assert not any(p.name.startswith(".") for p in dataset.parent.iterdir())  # no temporary folders left


def test_mask_is_the_rendered_foreground(dataset):
    """The mask equals the supersampled coverage of the actor posed with the ground truth (an
    independent rasterization), the image is the geoavatar.json background exactly where the mask is 0,
    and the mask is larger than the bare head model's coverage (hair volume, ears)."""
    meta = json.loads((dataset / META_FILE).read_text())
    actor = build_actor(get_subject(0))
    camera = frontal_camera(actor, SIZE)
    ssaa = meta["ssaa"]
    t = FRAMES - 2  # a test frame with a turned head and an open mouth
    with np.load(dataset / GT_DIR / f"{t:05d}.npz") as npz:
        params = {k: torch.from_numpy(npz[k]) for k in npz.files if k != "static_offset"}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the generator poses every frame (bitwise the same vertices)
    try:
        vertices = actor.model.forward_params(params).vertices[0]
    finally:
        torch.set_num_threads(threads)

    def coverage(verts, faces):
        frags = rasterize_mesh(world_to_camera(verts, camera.viewmat), torch.from_numpy(faces),
                               scale_intrinsics(camera.K, ssaa), SIZE * ssaa, SIZE * ssaa)
        return box_downsample(frags.mask.float(), ssaa).numpy()

    expected = coverage(vertices, actor.faces)
    mask = np.asarray(Image.open(dataset / "fg_masks" / f"{t:05d}_00.png"), np.float32) / 255
    assert np.abs(mask - expected).max() <= 0.5 / 255 + 1e-6
    assert 0.1 < mask.mean() < 0.8 and ((mask > 0) & (mask < 1)).any()  # anti-aliased edges
    image = np.asarray(Image.open(dataset / "images" / f"{t:05d}_00.png"), np.float32) / 255
    bg = np.asarray(read_layout(dataset).info.background, np.float32)  # exact in 8 bits
    empty = mask == 0
    np.testing.assert_array_equal(image[empty], np.broadcast_to(bg, image[empty].shape))
    full = mask == 1
    assert np.abs(image[full] - bg).mean() > 0.05
    head_only = coverage(vertices[: actor.num_head_vertices], actor.head.faces)
    assert mask.sum() > 1.05 * head_only.sum()


def test_same_seed_same_bytes_other_seed_differs(dataset, tmp_path):
    other = generate_dataset(tmp_path / "b", _config(seed=1), progress=False)
    a = np.asarray(Image.open(dataset / "images" / "00003_00.png"))
    b = np.asarray(Image.open(other / "images" / "00003_00.png"))
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 1.0
    assert _digest(other) != _digest(dataset)
    # Writing over an earlier synthetic dataset replaces it; the same seed gives the same bytes,
    # also when the frames are rendered by worker processes.
    again = generate_dataset(tmp_path / "b", _config(seed=0, workers=2), progress=False)
    assert _digest(again) == _digest(dataset)


def test_subjects_differ_and_noise_off_writes_ground_truth(dataset, tmp_path):
    ref = np.asarray(Image.open(dataset / "images" / "00000_00.png")).astype(np.float32)
    for index in (1, 2):
        out = generate_dataset(tmp_path / f"s{index}", _config(subject=index, frames=4,
                                                               tracking_noise=TrackingNoise(enabled=False)),
                               progress=False)
        image = np.asarray(Image.open(out / "images" / "00000_00.png")).astype(np.float32)
        assert np.abs(image - ref).mean() > 10.0
        subject = read_layout(out)
        for t in range(4):
            with np.load(out / GT_DIR / f"{t:05d}.npz") as gt:
                for key in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "expr"):
                    np.testing.assert_array_equal(subject.params[key][t].numpy(), gt[key][0])
                np.testing.assert_array_equal(subject.params["shape"].numpy(), gt["shape"])


def test_bad_arguments_fail_clearly_and_keep_user_files(tmp_path, monkeypatch):
    from geoavatar.apps.synth import synth

    with pytest.raises(OptionError, match="--subject"):
        synth(tmp_path / "x", subject=3, frames=4, size=32)
    with pytest.raises(ValueError, match="--frames"):
        generate_dataset(tmp_path / "x", _config(frames=1), progress=False)
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep me")
    with pytest.raises(OptionError, match="not a dataset made by `geoavatar synth`"):
        synth(user, frames=4, size=32)
    assert (user / "notes.txt").read_text() == "keep me" and len(list(user.iterdir())) == 1
    a_file = tmp_path / "file.png"
    a_file.write_bytes(b"x")
    with pytest.raises(OptionError, match="--out"):
        generate_dataset(a_file, _config(frames=4), progress=False)
    # A failure half-way leaves nothing that looks like a dataset (and no temporary folder).
    from geoavatar.data.synth import render

    calls = {"n": 0}
    original = render.ActorRenderer.render

    def failing(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("disk full")
        return original(self, *args, **kwargs)

    monkeypatch.setattr(render.ActorRenderer, "render", failing)
    with pytest.raises(RuntimeError, match="disk full"):
        generate_dataset(tmp_path / "half", _config(frames=6, size=32), progress=False)
    assert not (tmp_path / "half").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".half")]


def test_shading_without_the_highlight_removes_exactly_the_blinn_phong_term():
    from geoavatar.data.synth.appearance import HIGHLIGHT, MATERIALS, Appearance, FaceLandmarks

    marks = FaceLandmarks(eye_centres=np.array([[0.03, 0.03, 0.05], [-0.03, 0.03, 0.05]]), eye_radius=0.012,
                          mouth_centre=np.array([0.0, -0.04, 0.07]), mouth_arch_centre=np.array([0.0, -0.04, 0.05]),
                          head_centre=np.zeros(3), nose_tip=np.array([0.0, 0.0, 0.1]))
    appearance = Appearance(get_subject(0), marks)
    view = torch.tensor([0.0, 0.0, -1.0])  # surface -> camera
    light = torch.nn.functional.normalize(torch.tensor(HIGHLIGHT.directions[0]), dim=0)
    half = torch.nn.functional.normalize(light + view, dim=0)  # the normal of the brightest highlight
    normals = torch.stack([half, torch.nn.functional.normalize(torch.tensor([0.9, 0.0, -0.4]), dim=0)])
    p = torch.tensor([[0.0, -0.02, 0.09], [0.05, -0.02, 0.06]])
    weights = torch.zeros(2, len(MATERIALS))
    weights[:, MATERIALS.index("skin")] = 1.0
    args = (p, weights, torch.zeros(2), normals, view.expand(2, 3), torch.zeros(2, dtype=torch.bool), torch.ones(2))
    full, diffuse = appearance.shade_samples(*args), appearance.shade_samples(*args, highlight=False)
    assert torch.equal(full, appearance.shade_samples(*args, highlight=True))
    # at the half vector the highlight is skin's full strength (0.07, unless clamped at 1); far from it ~0
    assert torch.allclose(full[0] - diffuse[0], torch.minimum(torch.full((3,), 0.07), 1.0 - diffuse[0]), atol=1e-5)
    assert float((full[1] - diffuse[1]).abs().max()) < 1e-4 and float(diffuse[0].max()) < 0.999
