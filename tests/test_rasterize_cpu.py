"""Tests of the native CPU backend ("cpu", geoavatar/render/cpu_backend.py + csrc/rasterize_cpu.cpp).

The kernel is compared with the dense float64 reference of test_rasterize.py (forward within 1e-6 in
float64, gradients within 1e-4 of the largest) and with the PyTorch backend (forward within 1e-5,
gradients within 1e-4, float32 and float64), on the same scenes and hard cases; gradcheck runs in
float64 on a tiny scene. The extension comes from the user's build cache (`make install` builds it; see
conftest.py), else it is built once (about 40 s); without a compiler these tests skip with the reason, except the
fallback test, which simulates a missing compiler.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from geoavatar.render import cpu_backend, rasterize
from geoavatar.render.cpu_backend import cpu_backend_error, load_extension, rasterize_cpu
from geoavatar.render.torch_backend import rasterize_torch
from test_rasterize import (
    F64,
    PARAMS,
    _assert_grad_close,
    _loss,
    _loss_weights,
    _with_grad,
    dense_reference,
    look_at_viewmat,
    make_scene,
)


@pytest.fixture(scope="module")
def native():
    """The compiled kernel module (built here on the first test of the session)."""
    module = load_extension()
    if module is None:
        pytest.skip(f"native CPU rasterizer unavailable: {cpu_backend_error()}")
    return module


def _render(fn, scene, background=None, **kwargs):
    """One camera through rasterize_torch / rasterize_cpu; returns (rgb, alpha, means2d, radii, visible)."""
    dtype = scene["means"].dtype
    bg = torch.zeros(1, 3, dtype=dtype) if background is None else background[None]
    s = scene
    rgb, alpha, m2d, radii, visible, _ = fn(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"],
                                             s["viewmat"][None], s["K"][None], s["width"], s["height"], bg,
                                             batched=False, **kwargs)
    return rgb[0], alpha[0], m2d, radii[0], visible[0]


def _compare_with_reference(scene, background=None, **kwargs):
    """cpu backend vs dense reference and vs torch backend: forward and every gradient."""
    w_rgb, w_alpha = _loss_weights(scene["height"], scene["width"], scene["means"].dtype)
    ref_scene, cpu_scene, torch_scene = _with_grad(scene), _with_grad(scene), _with_grad(scene)
    ref_rgb, ref_alpha, ref_m2d, ref_radii = dense_reference(**ref_scene, background=background)
    _loss(ref_rgb, ref_alpha, w_rgb, w_alpha).backward()
    rgb, alpha, m2d, radii, visible = _render(rasterize_cpu, cpu_scene, background, **kwargs)
    _loss(rgb, alpha, w_rgb, w_alpha).backward()
    t_rgb, t_alpha, t_m2d, _, _ = _render(rasterize_torch, torch_scene, background)
    _loss(t_rgb, t_alpha, w_rgb, w_alpha).backward()
    assert (rgb - ref_rgb).abs().max() <= 1e-6
    assert (alpha - ref_alpha).abs().max() <= 1e-6
    assert (rgb - t_rgb).abs().max() <= 1e-6 and (alpha - t_alpha).abs().max() <= 1e-6
    assert torch.equal(radii, ref_radii) and torch.equal(visible, (ref_radii > 0).any(1))
    for name in PARAMS:
        _assert_grad_close(f"{name} vs reference", cpu_scene[name].grad, ref_scene[name].grad)
        _assert_grad_close(f"{name} vs torch backend", cpu_scene[name].grad, torch_scene[name].grad)
    _assert_grad_close("means2d vs reference", m2d.grad, ref_m2d.grad)
    _assert_grad_close("means2d vs torch backend", m2d.grad, t_m2d.grad)
    return ref_alpha


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_dense_reference_and_torch_backend(native, seed):
    ref_alpha = _compare_with_reference(make_scene(seed))
    assert ref_alpha.max() > 0.5  # the scene renders something


def test_background_odd_sizes_and_tile_sizes(native):
    scene = make_scene(4, width=21, height=13)  # sizes that tiles do not divide
    background = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    for tile_size in (1, 3, 16, 64):
        _compare_with_reference(scene, background, tile_size=tile_size)


def test_saturated_pixels_stop_at_transmittance_threshold(native):
    n = 30  # opaque, overlapping Gaussians: the 0.999 cap and the 1e-4 transmittance stop
    scene = dict(
        means=torch.stack([torch.zeros(n), torch.zeros(n), torch.linspace(2, 3, n)], -1).to(F64),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1),
        scales=torch.full((n, 3), 0.3, dtype=F64),
        opacities=torch.tensor([0.95, 1.0, 0.6] * (n // 3), dtype=F64),
        colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=F64),
        viewmat=torch.eye(4, dtype=F64),
        K=torch.tensor([[20.0, 0, 8.5], [0, 20.0, 8.5], [0, 0, 1]], dtype=F64),
        width=16,
        height=16,
    )
    ref_alpha = _compare_with_reference(scene, torch.tensor([0.3, 0.3, 0.3], dtype=F64))
    assert ref_alpha.max() > 0.9998


def _use_simd_path(monkeypatch, native, path):
    """Selects a float32 compositing path through the environment; skips when this CPU lacks it."""
    if path not in native.simd_paths():
        pytest.skip(f"this CPU runs only {native.simd_paths()}")
    monkeypatch.setenv(cpu_backend.SIMD_ENV, path)
    assert cpu_backend.simd_path() == path


@pytest.mark.parametrize("path", ["avx512", "avx2", "vector", "scalar"])
def test_float32_matches_torch_backend(native, monkeypatch, path):
    _use_simd_path(monkeypatch, native, path)
    scene64 = make_scene(6, n=300, width=64, height=48)
    scene = {k: (v.float() if torch.is_tensor(v) else v) for k, v in scene64.items()}
    background = torch.tensor([0.4, 0.2, 0.1])
    w_rgb, w_alpha = _loss_weights(48, 64, torch.float32)
    cpu_scene, torch_scene = _with_grad(scene), _with_grad(scene)
    rgb, alpha, m2d, radii, _ = _render(rasterize_cpu, cpu_scene, background)
    _loss(rgb, alpha, w_rgb, w_alpha).backward()
    t_rgb, t_alpha, t_m2d, t_radii, _ = _render(rasterize_torch, torch_scene, background)
    _loss(t_rgb, t_alpha, w_rgb, w_alpha).backward()
    assert rgb.dtype == torch.float32 and alpha.max() > 0.5
    assert (rgb - t_rgb).abs().max() <= 1e-5 and (alpha - t_alpha).abs().max() <= 1e-5
    assert torch.equal(radii, t_radii)
    for name in PARAMS:
        _assert_grad_close(name, cpu_scene[name].grad, torch_scene[name].grad)
    _assert_grad_close("means2d", m2d.grad, t_m2d.grad)
    ref_rgb, ref_alpha, _, _ = dense_reference(**scene64, background=background.double())
    assert (rgb.double() - ref_rgb).abs().max() < 2e-4


def _float32_render_and_grads(scene, background):
    s = _with_grad(scene)
    rgb, alpha, m2d, _, _ = _render(rasterize_cpu, s, background)
    (rgb.square().sum() + alpha.sum()).backward()
    return [rgb, alpha, m2d.grad] + [s[name].grad for name in PARAMS]


def test_lane_paths_agree(native, monkeypatch):
    lanes = [path for path in ("avx512", "avx2", "vector") if path in native.simd_paths()]
    if len(lanes) < 2:
        pytest.skip(f"needs two lane paths, this CPU runs {native.simd_paths()}")
    scene = make_scene(12, n=400, width=53, height=37, dtype=torch.float32)  # partial tiles and rows
    background = torch.tensor([0.3, 0.1, 0.8])
    outputs = {}
    for path in lanes + ["scalar"]:
        monkeypatch.setenv(cpu_backend.SIMD_ENV, path)
        outputs[path] = _float32_render_and_grads(scene, background)
    first = outputs[lanes[0]]
    for path in lanes[1:]:
        for wide, narrow in zip(first[:2], outputs[path][:2]):
            assert torch.equal(wide, narrow)  # one forward code, no FMA contraction: the same bits
        for wide, narrow in zip(first[2:], outputs[path][2:]):  # float per-lane sums, lane counts differ
            torch.testing.assert_close(wide, narrow, atol=1e-6, rtol=1e-5)
    # the scalar path differs in exp (libm) and state precision (double), not in what it computes
    assert not all(torch.equal(a, b) for a, b in zip(first, outputs["scalar"]))
    for path in lanes:
        for got, scalar in zip(outputs[path], outputs["scalar"]):
            torch.testing.assert_close(got, scalar, atol=2e-6, rtol=1e-4)


@pytest.mark.parametrize("path", ["avx512", "avx2", "vector"])
def test_simd_paths_with_any_tile_size(native, monkeypatch, path):
    _use_simd_path(monkeypatch, native, path)
    scene = make_scene(13, n=300, width=45, height=30, dtype=torch.float32)
    background = torch.tensor([0.6, 0.2, 0.4])
    reference = _float32_render_and_grads(scene, background)
    for tile_size in (1, 3, 24, 64):  # rows shorter and longer than the lanes, one tile for the image
        s = _with_grad(scene)
        rgb, alpha, m2d, _, _ = _render(rasterize_cpu, s, background, tile_size=tile_size)
        assert torch.equal(rgb, reference[0]) and torch.equal(alpha, reference[1])  # per pixel, the same steps
        (rgb.square().sum() + alpha.sum()).backward()
        for got, want in zip([m2d.grad] + [s[name].grad for name in PARAMS], reference[2:]):
            torch.testing.assert_close(got, want, atol=1e-6, rtol=1e-5)  # float sums grouped by other tiles


def test_simd_path_setting(native, monkeypatch):
    monkeypatch.setenv(cpu_backend.SIMD_ENV, "auto")
    assert cpu_backend.simd_path() == native.simd_paths()[0]
    assert native.simd_paths()[-2:] == ["vector", "scalar"]  # every build runs both
    monkeypatch.setenv(cpu_backend.SIMD_ENV, "sse9")
    with pytest.raises(ValueError, match="GEOAVATAR_CPU_SIMD='sse9'"):
        cpu_backend.simd_path()


def test_zero_and_all_culled_gaussians(native):
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    for scene in (make_scene(0, n=0, special=False), make_scene(0, n=4, special=False)):
        if scene["means"].shape[0]:
            scene["means"] = scene["means"] - torch.tensor([0.0, 0.0, 10.0], dtype=F64)  # all behind the camera
        scene = _with_grad(scene)
        out = rasterize(**scene, background=bg, backend="cpu")
        assert out.backend == "cpu" and not out.visible.any()
        torch.testing.assert_close(out.rgb, bg.expand(24, 32, 3))
        assert out.alpha.abs().max() == 0
        out.rgb.sum().backward()  # no error; zero gradients
        assert scene["colors"].grad is None or not scene["colors"].grad.any()


def test_gradcheck_tiny_scene(native):
    scene = make_scene(8, n=6, width=10, height=8, special=False)
    scene["means"] = scene["means"] * 0.15
    scene["scales"] = scene["scales"] * 2.0
    bg = torch.tensor([0.1, 0.4, 0.7], dtype=F64, requires_grad=True)
    tensors = [scene[name].clone().requires_grad_(True) for name in PARAMS]

    def render(means, quats, scales, opacities, colors, background):
        out = rasterize(means, quats, scales, opacities, colors, scene["viewmat"], scene["K"], 10, 8,
                        background=background, backend="cpu")
        return out.rgb, out.alpha

    assert render(*tensors, bg)[1].max() > 0.3
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # hundreds of tiny renders: no OpenMP hand-offs on a loaded machine
    try:
        assert torch.autograd.gradcheck(render, (*tensors, bg), eps=1e-6, atol=1e-5, rtol=1e-4)
    finally:
        torch.set_num_threads(threads)


def test_camera_batch_and_public_api(native):
    scene = _with_grad(make_scene(9))
    views = torch.stack([scene["viewmat"], look_at_viewmat([-0.5, 0.3, -2.2], [0.1, 0.0, 0.0])])
    Ks = torch.stack([scene["K"], scene["K"]])
    base = {k: v for k, v in scene.items() if k not in ("viewmat", "K")}
    batch = rasterize(**base, viewmat=views, K=Ks, backend="cpu")
    assert batch.backend == "cpu" and batch.rgb.shape == (2, 24, 32, 3) and batch.means2d.shape == (2, 50, 2)
    batch.rgb.sum().backward()
    batch_grad = batch.means2d.grad.clone()
    for c in range(2):
        single = rasterize(**base, viewmat=views[c], K=Ks[c], backend="torch")
        torch.testing.assert_close(batch.rgb[c], single.rgb, atol=1e-6, rtol=0)
        torch.testing.assert_close(batch.radii[c], single.radii)
        single.rgb.sum().backward()
        torch.testing.assert_close(batch_grad[c], single.means2d.grad, atol=1e-8, rtol=1e-6)


def test_results_do_not_depend_on_the_thread_count(native):
    scene = make_scene(10, n=400, width=64, height=48, dtype=torch.float32)
    threads = torch.get_num_threads()
    outputs = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            s = _with_grad(scene)
            rgb, alpha, m2d, _, _ = _render(rasterize_cpu, s, None)
            (rgb.square().sum() + alpha.sum()).backward()
            outputs.append([rgb, alpha, m2d.grad] + [s[name].grad for name in PARAMS])
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(*outputs):
        assert torch.equal(one, two)  # bitwise: tiles are independent, per-Gaussian sums in a fixed order


def test_auto_picks_cpu_for_cpu_tensors(native):
    scene = make_scene(11, n=5, width=8, height=8, special=False)
    assert rasterize(**scene).backend == "cpu"
    assert rasterize(**scene, backend="torch").backend == "torch"


def test_cpu_backend_rejects_other_devices(native):
    scene = make_scene(11, n=5, width=8, height=8, special=False)
    scene = {k: (v.to("meta") if torch.is_tensor(v) else v) for k, v in scene.items()}
    with pytest.raises(ValueError, match="backend 'cpu'"):
        cpu_backend.rasterize_to_pixels_cpu(scene["means"][:, :2], scene["means"], scene["opacities"], scene["colors"],
                                            scene["colors"][0], torch.zeros(5, 2, dtype=torch.int32),
                                            scene["opacities"], 8, 8)
    with pytest.raises(ValueError, match="backend 'cpu' needs CPU tensors"):
        rasterize_cpu(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
                      scene["viewmat"][None], scene["K"][None], 8, 8, scene["colors"][:1])


def test_missing_compiler_warns_once_and_auto_falls_back(monkeypatch):
    monkeypatch.setattr(cpu_backend, "_state", {"module": None, "tried": False, "error": None})
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    scene = make_scene(11, n=5, width=8, height=8, special=False)
    with pytest.warns(RuntimeWarning, match="could not be built.*no C\\+\\+ compiler") as record:
        out = rasterize(**scene)
    assert out.backend == "torch"
    assert sum(issubclass(w.category, RuntimeWarning) for w in record) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a second render warns no more
        assert rasterize(**scene).backend == "torch"
    with pytest.raises(RuntimeError, match="backend 'cpu' is unavailable: .*no C\\+\\+ compiler"):
        rasterize(**scene, backend="cpu")
