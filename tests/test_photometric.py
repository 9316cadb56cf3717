"""Photometric tracking (geoavatar.prep.photometric): recovery of a known perturbation on frames rendered with
the appearance model itself, crops, the `track` app's copy, and the prepare stage (--no-photometric, resume)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import needs_shared_video, shared_video
from geoavatar.head import load_head_model
from geoavatar.head.params import HeadParams
from geoavatar.prep.photometric import (
    PhotometricConfig,
    PhotometricTargets,
    SurfaceAppearance,
    crop_boxes,
    fit_photometric,
    grow_faces,
    level_factor,
    photometric_loss,
    region_weights,
    render_at,
    weighted_faces,
    weighted_vertex_ids,
)
from geoavatar.prep.tracking import camera_viewmat

needs_video = needs_shared_video("wojtek.mp4")


@pytest.fixture(scope="module")
def head():
    return load_head_model("openhead", mouth="geoavatar")


@pytest.fixture(autouse=True)
def one_thread():
    """The fit on one thread, as prepare and track run it: its renders are small, and on a busy 2-core machine
    2 threads made these tests 3-40x slower."""
    from geoavatar.runtime import num_threads

    with num_threads(1):
        yield


def _truth(head, frames: int) -> HeadParams:
    g = torch.Generator().manual_seed(0)
    params = HeadParams.from_npz(head.zero_params(batch=frames))
    expr = torch.zeros(frames, head.num_expr)
    expr[:, :4] = 0.8 * torch.rand(frames, 4, generator=g)
    return params.replace(shape=torch.zeros(head.num_shape), expr=expr,
                          rotation=0.15 * (torch.rand(frames, 3, generator=g) - 0.5),
                          jaw_pose=torch.stack([0.05 + 0.1 * torch.rand(frames, generator=g), torch.zeros(frames),
                                                torch.zeros(frames)], -1))


PATTERN_SIZE = 128  # side of the frames rendered with the appearance model itself


def _pattern_appearance(head, config: PhotometricConfig) -> SurfaceAppearance:
    """The appearance model on every face with a patterned albedo (stripes in canonical space), neutral light."""
    appearance = SurfaceAppearance(head, np.arange(head.num_faces), config)
    centres, _, _ = appearance.geometry(head.template_output().vertices.detach())
    c = centres[0]
    pattern = torch.stack([0.5 + 0.4 * torch.sin(90 * c[:, 0]), 0.5 + 0.4 * torch.sin(70 * c[:, 1] + 1.0),
                           0.5 + 0.3 * torch.cos(60 * c[:, 2] + 60 * c[:, 0])], -1)
    appearance.albedo.data.copy_(pattern)
    return appearance


def _render_frames(head, params: HeadParams, size: int):
    """Frames of the appearance model itself (_pattern_appearance, one Gaussian per face) over grey."""
    appearance = _pattern_appearance(head, PhotometricConfig(per_face=1))
    viewmat = torch.as_tensor(camera_viewmat(0.55), dtype=torch.float32)
    K = torch.tensor([[2.2 * size, 0, size / 2], [0, 2.2 * size, size / 2], [0, 0, 1.0]])
    images, masks = [], []
    with torch.no_grad():
        vertices = head.forward_params(params, vertex_ids=appearance.vertex_ids).vertices
        for t in range(params.batch):
            result = appearance.render(vertices[t], viewmat, K, size, size)
            rgb = result.rgb + (1 - result.alpha) * 0.5
            images.append((rgb.clamp(0, 1) * 255).round().byte().numpy())
            masks.append(((result.alpha[..., 0] > 0.5) * 255).byte().numpy())
    return np.stack(images), np.stack(masks), viewmat.numpy(), K.numpy()


def depth_response(head, truth: HeadParams, frames, size: int, shifts, supersample: bool = True) -> list[float]:
    """fit_photometric's image term on `frames` (_render_frames of `truth`) at the pyramid level `size` of a fit to
    PATTERN_SIZE, rendered as the fit renders it, with the exact albedo on the fit's faces, at the truth moved by
    each of `shifts` (m) along the optical axis."""
    images, masks, viewmat, K = frames
    T = truth.batch
    sizes = (size, PATTERN_SIZE) if size < PATTERN_SIZE else (PATTERN_SIZE,)
    config = PhotometricConfig(per_face=1, sizes=sizes, epochs=(1,) * len(sizes), supersample=supersample)
    factor = level_factor(config, size)
    weighted = weighted_faces(head)
    faces = grow_faces(head, weighted, config.render_rings)
    appearance = SurfaceAppearance(head, faces, config, weighted=weighted)
    appearance.albedo.data.copy_(_pattern_appearance(head, config).albedo.data[faces])
    view = torch.as_tensor(viewmat).expand(T, 4, 4)
    boxes = crop_boxes(head, truth, view, torch.as_tensor(K).expand(T, 3, 3), weighted_vertex_ids(head), config.crop_margin)
    level = PhotometricTargets.from_arrays(images, masks, viewmat, K, PATTERN_SIZE, boxes).level(size)
    weights = region_weights(appearance, head, truth, level, T, factor)
    out = []
    for shift in shifts:
        moved = truth.replace(translation=truth.translation + shift * view[:, 2, :3])  # row 2: the optical axis
        with torch.no_grad():
            vertices = head.forward_params(moved, vertex_ids=appearance.vertex_ids).vertices
            losses = [photometric_loss(render_at(appearance, vertices[t], level.viewmat[t], level.K[t], size, size, factor)[0],
                                       level.images[t], weights[t]) for t in range(T)]
        out.append(float(torch.stack(losses).mean()))
    return out


def _vertex_error(head, a: HeadParams, b: HeadParams, ids) -> float:
    with torch.no_grad():
        return float((head.forward_params(a, vertex_ids=ids).vertices - head.forward_params(b, vertex_ids=ids).vertices)
                     .norm(dim=-1).mean())


def test_fit_recovers_a_known_perturbation_of_pose_and_expression(head):
    """Six frames of a rendered head, every frame's pose, jaw and expression perturbed, are pulled back to the truth.

    The perturbations are centred over the frames: an offset common to every frame is the gauge of a fit whose
    albedo is estimated from the same frames (the albedo slides with it; BENCHMARKS.md, photometric tracking), and
    prepare pins it with its landmark term. What the image term must do is make the frames agree with one another."""
    frames, size = 6, 96
    truth = _truth(head, frames)
    images, masks, viewmat, K = _render_frames(head, truth, size)
    g = torch.Generator().manual_seed(1)
    centred = lambda x: x - x.mean(0, keepdim=True)  # noqa: E731
    noisy = truth.replace(
        rotation=truth.rotation + centred(0.035 * torch.randn(frames, 3, generator=g)),
        translation=truth.translation + centred(0.004 * torch.randn(frames, 3, generator=g) * torch.tensor([1, 1, 0.3])),
        expr=truth.expr + centred(0.25 * torch.randn(frames, head.num_expr, generator=g) * (torch.arange(head.num_expr) < 4)),
        jaw_pose=truth.jaw_pose + centred(torch.randn(frames, 1, generator=g) * torch.tensor([0.04, 0, 0])))
    # One chunk holds every frame, so the shared albedo gets one Adam step per epoch (a video of 400 frames gets
    # 50): its rate while the pose moves is raised to match.
    config = PhotometricConfig(sizes=(48, 96), epochs=(30, 20), chunk=frames, appearance_epochs=20, prior_weight=0.01,
                               pose_smooth_weight=0.01, lr_albedo_pose=0.05)
    viewmats = np.broadcast_to(viewmat, (frames, 4, 4))
    boxes = crop_boxes(head, noisy, torch.as_tensor(viewmats.copy()), torch.as_tensor(K).expand(frames, 3, 3),
                       weighted_vertex_ids(head), config.crop_margin)
    targets = PhotometricTargets.from_arrays(images, masks, viewmat, K, max(config.sizes), boxes)
    result = fit_photometric(head, noisy, targets, config)
    ids = weighted_vertex_ids(head)
    before, after = _vertex_error(head, noisy, truth, ids), _vertex_error(head, result.params, truth, ids)
    assert after < before / 2.5, (before, after)
    assert result.residual.mean() < result.residual_before.mean() / 2
    assert result.params.rotation.shape == (frames, 3) and np.isfinite(result.residual).all()


SHIFTS_MM = (-20, -10, -5, 0, 5, 10, 20)


def _depth_minimum_mm(head, size: int, supersample: bool = True) -> int:
    truth = _truth(head, 3)
    frames = _render_frames(head, truth, PATTERN_SIZE)
    losses = depth_response(head, truth, frames, size, [1e-3 * d for d in SHIFTS_MM], supersample)
    return SHIFTS_MM[int(np.argmin(losses))]


@pytest.mark.parametrize("size", [PATTERN_SIZE, PATTERN_SIZE // 2])
def test_image_term_is_least_at_the_true_depth(head, size):
    """With the exact albedo the image term is least at the true depth, at the frames' own size and (rendered at
    that size, area-downsampled) at a coarse level."""
    assert _depth_minimum_mm(head, size) == 0


def test_coarse_render_without_supersampling_prefers_a_farther_head(head):
    """Why PhotometricConfig.supersample: sub-pixel Gaussians rendered at the coarse size are not the downsampled frame."""
    assert _depth_minimum_mm(head, PATTERN_SIZE // 2, supersample=False) >= 10


@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_native_surface_splats_match_the_appearance_models_torch_ops(head, dtype, tolerance):
    """The native loop that SurfaceAppearance.render uses (avatar.fused.surface_splats) against the model's own
    PyTorch ops (geometry, colours): centres, std, colours and the gradients of vertices, albedo and lighting."""
    from geoavatar.avatar.fused import native_loops_available, surface_splats

    if not native_loops_available():
        pytest.skip("the avatar's native CPU loops did not build here")
    config = PhotometricConfig()
    appearance = SurfaceAppearance(head, grow_faces(head, weighted_faces(head), config.render_rings), config).to(dtype)
    appearance.bary.fill_(1.0 / 3.0)  # in the dtype itself: the buffer was made from float32 thirds
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        appearance.albedo.uniform_(0.2, 0.9, generator=g)
        appearance.light.add_(0.2 * torch.randn(9, 3, generator=g, dtype=dtype))
    params = HeadParams.from_npz(head.zero_params()).replace(expr=0.5 * torch.randn(1, head.num_expr, generator=g))
    start = head.forward_params(params, vertex_ids=appearance.vertex_ids).vertices[0].to(dtype).detach()
    count = appearance.faces.shape[0]
    weights = [torch.randn(count, *shape, generator=g, dtype=dtype) for shape in ((3,), (), (3,))]

    def loss_and_grads(outputs, vertices):
        loss = sum((w * o).sum() for w, o in zip(weights, outputs))
        return torch.autograd.grad(loss, [vertices, appearance.albedo, appearance.light])

    vertices = start.clone().requires_grad_(True)
    centre, normal, std = (x[0] for x in appearance.geometry(vertices[None]))
    reference = (centre, std, appearance.colours(normal))
    reference_grads = loss_and_grads(reference, vertices)
    vertices = start.clone().requires_grad_(True)
    native = surface_splats(vertices, appearance.albedo, appearance.light, appearance.faces, appearance.size)
    assert native is not None
    for ours, theirs in zip((*native, *loss_and_grads(native, vertices)), (*reference, *reference_grads)):
        assert ours.dtype == dtype and ours.shape == theirs.shape
        assert float((ours - theirs).abs().max()) <= tolerance * float(theirs.abs().max())


def test_render_is_the_same_with_and_without_the_native_loop(head, monkeypatch):
    """SurfaceAppearance.render through the native loop and through its PyTorch ops: the same image."""
    import geoavatar.prep.photometric as photometric

    config = PhotometricConfig()
    appearance = SurfaceAppearance(head, grow_faces(head, weighted_faces(head), config.render_rings), config)
    with torch.no_grad():
        appearance.albedo.uniform_(0.2, 0.9, generator=torch.Generator().manual_seed(0))
    # A turned head: facing the camera, mirror-image splats lie at exactly equal depth, and which of them blends first
    # is a tie that the two paths' last-bit differences (1e-8 in a centre) decide each its own way.
    params = HeadParams.from_npz(head.zero_params())
    params.rotation[:] = torch.tensor([0.05, 0.2, 0.03])
    vertices = head.forward_params(params, vertex_ids=appearance.vertex_ids).vertices[0]
    viewmat = torch.as_tensor(camera_viewmat(0.6), dtype=torch.float32)
    K = torch.tensor([[250.0, 0, 64], [0, 250, 64], [0, 0, 1]])
    native = appearance.render(vertices, viewmat, K, 128, 128).rgb
    monkeypatch.setattr(photometric, "surface_splats", lambda *args: None)
    plain = appearance.render(vertices, viewmat, K, 128, 128).rgb
    assert float(plain.amax()) > 0.1  # the face is in the picture
    assert torch.allclose(native, plain, atol=1e-5)


def test_crops_and_appearance_sets(head):
    weighted = weighted_faces(head)
    grown = grow_faces(head, weighted, 2)
    assert set(weighted) <= set(grown) and len(grown) < head.num_faces  # scalp, back of the head stay out
    scalp = set(np.asarray(head.regions["scalp"]))
    assert not any(set(face) <= scalp for face in head.faces[weighted].tolist())
    params = HeadParams.from_npz(head.zero_params(batch=2))
    viewmat = torch.as_tensor(camera_viewmat(0.6), dtype=torch.float32).expand(2, 4, 4)
    K = torch.tensor([[400.0, 0, 128], [0, 400, 128], [0, 0, 1]]).expand(2, 3, 3)
    boxes = crop_boxes(head, params, viewmat, K, weighted_vertex_ids(head), 1.25)
    assert boxes.shape == (2, 3) and 40 < boxes[0, 2] < 200 and abs(boxes[0, 0] + boxes[0, 2] / 2 - 128) < 20
    image = np.zeros((2, 256, 256, 3), np.uint8)
    image[:, 100:140, 100:140] = 255
    targets = PhotometricTargets.from_arrays(image, None, viewmat[0].numpy(), K[0].numpy(), 64, boxes)
    assert targets.images.shape == (2, 64, 64, 3) and targets.level(32).images.shape == (2, 32, 32, 3)
    # The crop's intrinsics map the same world point onto the same image content.
    s = 64 / boxes[0, 2]
    assert torch.allclose(targets.K[0, 0, 2], torch.tensor(s * (128 - boxes[0, 0]), dtype=torch.float32), atol=1e-3)
    with pytest.raises(ValueError, match="sizes"):
        PhotometricConfig(sizes=(64,), epochs=(1, 2))


def test_track_writes_a_copy_with_fitted_parameters(tmp_path, capsys):
    from geoavatar.apps.track import TrackError, track
    from geoavatar.errors import OptionError
    from geoavatar.data.dataset import open_subject
    from geoavatar.data.synth.generate import SynthConfig, generate_dataset

    data = generate_dataset(tmp_path / "synth", SynthConfig(subject=0, frames=4, size=96, workers=1), progress=False)
    out = tmp_path / "tracked"
    assert track(data, out, sizes=(32, 48), epochs=(1, 1), chunk=2, progress=False) == 0
    source, copy = open_subject(data), open_subject(out)
    assert copy.num_timesteps == 4 and (out / "images").is_dir() and (out / "flame_param_gt").is_dir()
    assert not torch.equal(source.params["rotation"], copy.params["rotation"])
    assert torch.equal(source.params["shape"], copy.params["shape"])
    np.testing.assert_array_equal(source.frames[0].K, copy.frames[0].K)
    report = json.loads((out / "track.json").read_text())
    assert len(report["photometric_residual"]["per_frame"]) == 4
    with pytest.raises(TrackError, match="exists"):
        track(data, out, progress=False)
    with pytest.raises(OptionError, match="would delete the dataset"):  # --overwrite never replaces its input
        track(data, tmp_path, overwrite=True, progress=False)
    assert (data / "flame_param").is_dir()


def test_prepare_and_track_share_the_fit_defaults():
    import inspect

    from geoavatar.apps.track import track
    from geoavatar.prep.pipeline import PrepareConfig, photometric_config

    defaults = PhotometricConfig()
    prepare = PrepareConfig(video=Path("talk.mp4"), out=Path("out"))
    assert prepare.photometric and prepare.photometric_epochs == defaults.epochs
    assert photometric_config(prepare) == PhotometricConfig(tracking=photometric_config(prepare).tracking)
    options = inspect.signature(track).parameters
    assert (options["sizes"].default, options["epochs"].default, options["per_face"].default) == (
        defaults.sizes, defaults.epochs, defaults.per_face)


@needs_video
def test_prepare_photometric_stage_no_photometric_and_resume(tmp_path, monkeypatch):
    from geoavatar.data import open_dataset
    from geoavatar.prep import photometric
    from geoavatar.prep.pipeline import PrepareConfig, run_prepare

    threads = []  # the stage runs on one thread whatever the process's count (pipeline.PHOTOMETRIC_THREADS)
    fit = photometric.fit_photometric
    monkeypatch.setattr(photometric, "fit_photometric", lambda *a, **k: threads.append(torch.get_num_threads()) or fit(*a, **k))

    messages: list[str] = []
    options = dict(video=shared_video("wojtek.mp4"), size=128, max_frames=5, tracking_steps=(30, 40), progress=False, overlay=False,
                   photometric_epochs=(1, 1), workers=1, log=messages.append)  # inline: the recorder above sees the fit
    plain = run_prepare(PrepareConfig(out=tmp_path / "plain", photometric=False, **options))
    work = tmp_path / "plain" / ".prepare"
    assert not (work / "photometric.npz").exists()
    tracking = np.load(work / "tracking.npz")
    written = open_dataset(plain).subject.params
    for key in ("rotation", "translation", "neck_pose", "jaw_pose", "eyes_pose", "expr"):  # the landmark fit, as is
        fitted_values = tracking[f"param_{key}"]
        np.testing.assert_allclose(written[key].numpy()[:, :fitted_values.shape[1]], fitted_values, atol=1e-6, err_msg=key)
    assert "photometric_residual" not in json.loads((tmp_path / "plain" / "report.json").read_text())

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        fitted = run_prepare(PrepareConfig(out=tmp_path / "plain", photometric=True, **options))
        assert threads == [1] and torch.get_num_threads() == 2  # one thread inside the stage, the count restored
    finally:
        torch.set_num_threads(before)
    assert any("tracking' is complete" in m for m in messages)  # the landmark fit is reused
    refined = open_dataset(fitted).subject.params
    assert not np.allclose(refined["expr"].numpy()[:, :tracking["param_expr"].shape[1]], tracking["param_expr"])
    report = json.loads((tmp_path / "plain" / "report.json").read_text())
    assert len(report["photometric_residual"]["per_frame"]) == 5
    messages.clear()
    run_prepare(PrepareConfig(out=tmp_path / "plain", photometric=True, **options))
    assert any("stage 'photometric' is complete, skipped" in m for m in messages)
    assert any("stage 'write' is complete, skipped" in m for m in messages)


@needs_video
def test_prepare_photometric_in_segments_over_workers(tmp_path, monkeypatch):
    """The photometric stage cut into segments (3 of 3-4 frames here, 2 frames of overlap, one appearance fitted
    first on a sample of 3 frames): the same fit on one process or two, every frame refined."""
    import shutil

    from geoavatar.prep import pipeline
    from geoavatar.prep.pipeline import PrepareConfig, run_prepare

    monkeypatch.setattr(pipeline, "PHOTOMETRIC_SEGMENT", 4)
    monkeypatch.setattr(pipeline, "PHOTOMETRIC_OVERLAP", 2)
    monkeypatch.setattr(pipeline, "PHOTOMETRIC_SAMPLE", 3)
    options = dict(video=shared_video("wojtek.mp4"), size=96, max_frames=10, tracking_steps=(10, 10), progress=False, overlay=False,
                   photometric_epochs=(1, 1), log=lambda message: None)
    run_prepare(PrepareConfig(out=tmp_path / "one", photometric=False, workers=1, **options))
    shutil.copytree(tmp_path / "one", tmp_path / "two")
    fits = []
    for name, workers in (("one", 1), ("two", 2)):
        run_prepare(PrepareConfig(out=tmp_path / name, photometric=True, workers=workers, **options))
        fits.append(np.load(tmp_path / name / ".prepare" / "photometric.npz"))
    marker = json.loads((tmp_path / "two" / ".prepare" / "photometric.json").read_text())
    assert marker["log"][0].startswith("3 segment(s)") and "one appearance fitted on 3 frames" in marker["log"][0]
    assert "segment 2 (frames 7-9)" in marker["log"][-1]
    for key in fits[0].files:
        np.testing.assert_array_equal(fits[0][key], fits[1][key], err_msg=key)
    tracking = np.load(tmp_path / "one" / ".prepare" / "tracking.npz")
    moved = np.abs(fits[0]["param_expr"] - tracking["param_expr"]).max(1)
    assert (moved > 0).all() and np.isfinite(fits[0]["residual"]).all()


def test_frames_without_pixels_get_no_image_term(head):
    """A frame with an empty mask (prepare: no face found there) is never compared with its image: its residual is
    NaN, not 0, a chunk of such frames alone does not crash the appearance steps, and what the image shows there
    changes nothing."""
    frames, size = 4, 48
    truth = _truth(head, frames)
    images, masks, viewmat, K = _render_frames(head, truth, size)
    masks[2:] = 0  # the second chunk has no face
    config = PhotometricConfig(sizes=(size,), epochs=(2,), chunk=2, appearance_epochs=1, per_face=1)
    boxes = crop_boxes(head, truth, torch.as_tensor(viewmat).expand(frames, 4, 4).clone(),
                       torch.as_tensor(K).expand(frames, 3, 3), weighted_vertex_ids(head), config.crop_margin)
    fits = []
    for seed in (0, 1):  # two different pictures where the face is lost
        shown = images.copy()
        shown[2:] = np.random.default_rng(seed).integers(0, 256, shown[2:].shape, dtype=np.uint8)
        targets = PhotometricTargets.from_arrays(shown, masks, viewmat, K, size, boxes)
        fits.append(fit_photometric(head, truth, targets, config))
    result = fits[0]
    assert np.isfinite(result.residual[:2]).all() and np.isnan(result.residual[2:]).all()
    assert np.isnan(result.residual_before[2:]).all()
    assert all(torch.isfinite(getattr(result.params, key)).all() for key in ("rotation", "translation", "expr"))
    for key in ("rotation", "translation", "expr", "jaw_pose"):
        torch.testing.assert_close(getattr(fits[1].params, key), getattr(result.params, key), atol=1e-5, rtol=0)
    from geoavatar.prep.photometric import residual_report

    summary = residual_report(result.residual, result.residual_before)
    assert summary["per_frame"][2:] == [None, None] and summary["mean"] == pytest.approx(result.residual[:2].mean())


@needs_video
def test_prepare_photometric_on_a_video_that_loses_the_face(tmp_path):
    """A real clip whose face is lost for a stretch (frames filled with a flat colour) goes through prepare
    --photometric: those frames are interpolated, flagged in report.json, get no image term (null residual) and
    keep parameters that run smoothly between their neighbours'."""
    from geoavatar.io.video import Mp4Writer
    from geoavatar.prep.pipeline import PrepareConfig, run_prepare
    from geoavatar.prep.video import decode_frames

    frames = [rgb[::2, ::2].copy() for _, rgb in decode_frames(shared_video("wojtek.mp4"), max_frames=9)]  # 256 px
    lost = [3, 4, 5]
    for k in lost:
        frames[k][:] = (90, 130, 160)
    video = tmp_path / "lost.mp4"
    with Mp4Writer(video, fps=25, crf=23) as writer:  # x264's default quality: the bounds below were set on it
        for rgb in frames:
            writer.write(rgb)
    out = tmp_path / "out"
    run_prepare(PrepareConfig(video=video, out=out, size=128, tracking_steps=(30, 40), photometric=True,
                              photometric_epochs=(1, 1), overlay=False, progress=False, log=lambda message: None))
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 9 and report["missing_source_frames"] == lost and report["interpolated_frames"] == lost
    residual = report["photometric_residual"]
    assert [k for k, e in enumerate(residual["per_frame"]) if e is None] == lost
    assert all(0 < e < 0.2 for k, e in enumerate(residual["per_frame"]) if k not in lost)
    seen = [e for e in residual["per_frame"] if e is not None]
    assert residual["mean"] == pytest.approx(np.mean(seen), abs=1e-4)
    fit = np.load(out / ".prepare" / "photometric.npz")
    for key in ("param_rotation", "param_translation", "param_expr", "param_jaw_pose"):
        values = fit[key]
        assert np.isfinite(values).all(), key
        # the lost stretch stays within the range its neighbours span (plus a margin of their own frame-to-frame motion)
        around = values[[lost[0] - 1, lost[-1] + 1]]
        step = np.maximum(np.abs(np.diff(values[:3], axis=0)).max(0), np.abs(np.diff(values[6:], axis=0)).max(0))
        low, high = around.min(0) - 2 * step - 1e-4, around.max(0) + 2 * step + 1e-4
        assert ((values[lost] >= low) & (values[lost] <= high)).all(), key
    # the overlay names the fit it shows and flags the lost frames (an orange caption)
    from geoavatar.prep.overlay import FLAGGED
    from geoavatar.prep.pipeline import overlay_frames

    config = PrepareConfig(video=video, out=out, size=128, tracking_steps=(30, 40), photometric_epochs=(1, 1))
    pictures = dict(overlay_frames(config, out / ".prepare", rows=[2, 3]))
    orange = [(np.abs(pictures[row][:20].astype(int) - FLAGGED).max(-1) < 40).sum() for row in (2, 3)]
    assert orange[0] == 0 and orange[1] > 10, orange
