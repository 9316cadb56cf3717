"""Tests of geoavatar.render.rasterize against a brute-force dense reference written here.

The reference (`dense_reference`) evaluates every Gaussian at every pixel in float64 and composites
them one Gaussian at a time, front to back, with a per-pixel transmittance image. It applies the same
gsplat 1.5.3 rules as the renderer, written out independently of the renderer's code:
  - per Gaussian: near plane z >= 0.01 (and z <= 1e10), det(cov2d + 0.3 I) > 0, opacity >= 1/255,
    the opacity-aware box (extent min(3.33, sqrt(2 ln(255 o))) sigma per axis, radius = ceil) must
    overlap the image; a Gaussian failing any of these is dropped entirely;
  - per pixel (centres at +0.5): alpha = min(0.999, o exp(-1/2 d^T conic d)); alpha < 1/255 skipped;
    a pixel stops before the Gaussian that would take its transmittance to <= 1e-4.
It does NOT restrict a Gaussian to its box (every Gaussian is evaluated at every pixel), so it also
checks that the renderer's box/tile enumeration loses nothing. Its gradients come from plain autograd
through the dense [Gaussians x pixels] tensors (fine at test sizes, forbidden in the renderer).
"""

from __future__ import annotations

import sys

import pytest
import torch

from geoavatar.geometry import quaternion_to_matrix
from geoavatar.render import RasterizeResult, rasterize
from geoavatar.render.cpu_backend import cpu_backend_available
from geoavatar.render.gsplat_backend import gsplat_available
from geoavatar.render.torch_backend import plan_rows, project_gaussians, rasterize_torch

F64 = torch.float64


# ----------------------------------------------------------------------------- reference
def dense_reference(means, quats, scales, opacities, colors, viewmat, K, width, height, background=None):
    """rgb [H,W,3], alpha [H,W,1], means2d [N,2] (graph node), radii [N,2] by brute force (see module doc)."""
    n = means.shape[0]
    rot_view, trans_view = viewmat[:3, :3], viewmat[:3, 3]
    cam = torch.einsum("ij,nj->ni", rot_view, means) + trans_view  # [N, 3]
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    front = (z >= 0.01) & (z <= 1e10)
    z = torch.where(front, z, torch.ones_like(z))
    rot = quaternion_to_matrix(quats)  # normalises, like gsplat
    cov = rot @ torch.diag_embed(scales * scales) @ rot.transpose(1, 2)  # [N, 3, 3]
    cov_cam = rot_view @ cov @ rot_view.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    half_x, half_y = width / (2 * fx), height / (2 * fy)  # tan of the half field of view
    u = torch.clamp(x / z, -(cx / fx + 0.3 * half_x), (width - cx) / fx + 0.3 * half_x)
    v = torch.clamp(y / z, -(cy / fy + 0.3 * half_y), (height - cy) / fy + 0.3 * half_y)
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [torch.stack([fx / z, zero, -fx * u / z], -1), torch.stack([zero, fy / z, -fy * v / z], -1)], 1
    )  # [N, 2, 3]
    cov2d = jac @ cov_cam @ jac.transpose(1, 2) + 0.3 * torch.eye(2, dtype=means.dtype)
    det = torch.linalg.det(cov2d)
    keep = front & (det > 0) & (opacities >= 1 / 255)
    cov2d = torch.where(keep[:, None, None], cov2d, torch.eye(2, dtype=means.dtype).expand(n, 2, 2))
    conic = torch.linalg.inv(cov2d)  # [N, 2, 2]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    if means2d.requires_grad:
        means2d.retain_grad()
    with torch.no_grad():
        keep = keep.clone()  # the culled-covariance where() above saved the first mask for backward
        safe_o = torch.where(keep, opacities, torch.ones_like(opacities))
        extent = torch.sqrt(2 * torch.log(safe_o * 255)).clamp(max=3.33)
        radii = torch.ceil(extent[:, None] * torch.sqrt(torch.diagonal(cov2d, dim1=1, dim2=2)))
        m = means2d
        keep &= (radii > 0).any(1)
        keep &= (m[:, 0] + radii[:, 0] > 0) & (m[:, 0] - radii[:, 0] < width)
        keep &= (m[:, 1] + radii[:, 1] > 0) & (m[:, 1] - radii[:, 1] < height)
        radii = torch.where(keep[:, None], radii, torch.zeros_like(radii)).to(torch.int32)

    jj, ii = torch.meshgrid(torch.arange(width, dtype=F64), torch.arange(height, dtype=F64), indexing="xy")
    pix = torch.stack([jj.reshape(-1) + 0.5, ii.reshape(-1) + 0.5], -1).to(means.dtype)  # [P, 2]
    d = means2d[:, None, :] - pix[None]  # [N, P, 2]  every Gaussian at every pixel
    sigma = 0.5 * torch.einsum("npi,nij,npj->np", d, conic, d)
    alpha = torch.clamp(opacities[:, None] * torch.exp(-sigma), max=0.999)
    alpha = torch.where(keep[:, None] & (sigma >= 0) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))

    order = torch.argsort(torch.where(keep, cam[:, 2].detach(), torch.zeros_like(z)), stable=True)
    transmittance = torch.ones(pix.shape[0], dtype=means.dtype)
    done = torch.zeros(pix.shape[0], dtype=torch.bool)
    rgb = torch.zeros(pix.shape[0], 3, dtype=means.dtype)
    for g in order.tolist():
        if not bool(keep[g]):
            continue
        a = alpha[g]
        next_t = transmittance * (1 - a)
        done = done | ((a > 0) & (next_t <= 1e-4))
        use = (a > 0) & ~done
        rgb = rgb + torch.where(use[:, None], (a * transmittance)[:, None] * colors[g], torch.zeros_like(rgb))
        transmittance = torch.where(use, next_t, transmittance)
    if background is not None:
        rgb = rgb + transmittance[:, None] * background
    return rgb.reshape(height, width, 3), (1 - transmittance).reshape(height, width, 1), means2d, radii


# ----------------------------------------------------------------------------- scenes
def look_at_viewmat(eye, target, dtype=F64):
    """World-to-camera [4,4], OpenCV axes (+z towards target, +y down)."""
    eye, target = torch.as_tensor(eye, dtype=dtype), torch.as_tensor(target, dtype=dtype)
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, torch.tensor([0.0, -1.0, 0.0], dtype=dtype)), dim=0)
    down = torch.linalg.cross(forward, right)
    rot = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    view = torch.eye(4, dtype=dtype)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ eye
    return view


def make_scene(seed: int, n: int = 40, width: int = 32, height: int = 24, dtype=F64, special: bool = True):
    """Random Gaussians in front of a camera at 2.5 units, plus (special=True) the hard cases."""
    gen = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=gen, dtype=dtype) * 0.5
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    scales = torch.exp(torch.randn(n, 3, generator=gen, dtype=dtype) * 0.5 - 2.5)
    opacities = torch.rand(n, generator=gen, dtype=dtype) * 0.98 + 0.01
    colors = torch.rand(n, 3, generator=gen, dtype=dtype)
    view = look_at_viewmat([0.3, -0.2, -2.5], [0.0, 0.0, 0.0], dtype)
    K = torch.tensor([[30.0, 0, width / 2 + 0.7], [0, 31.0, height / 2 - 0.4], [0, 0, 1]], dtype=dtype)
    if special:
        cam_to_world = torch.linalg.inv(view)

        def world(p):
            return (cam_to_world @ torch.tensor([*p, 1.0], dtype=dtype))[:3]

        cases = [
            ([0.1, 0.0, -0.5], [0.05, 0.05, 0.05]),  # behind the camera
            ([0.0, 0.1, 0.005], [0.05, 0.05, 0.05]),  # centre just in front of the eye, before the near plane
            ([0.05, 0.0, 0.012], [0.01, 0.01, 0.02]),  # just past the near plane, straddling it
            ([40.0, 3.0, 2.0], [0.05, 0.05, 0.05]),  # far outside the image
            ([1.6, 0.0, 2.0], [0.3, 0.3, 0.3]),  # centre outside the image, clamped Jacobian, overlaps it
            ([0.0, -1.0, 1.5], [0.4, 0.2, 0.3]),  # centre above the image, overlaps it
            ([0.1, 0.1, 2.0], [1e-6, 1e-6, 0.05]),  # needle (extremely thin)
            ([-0.2, 0.0, 2.2], [1e-7, 0.1, 0.1]),  # flat disc seen from a slant
            ([0.0, 0.0, 3.0], [2.0, 2.0, 2.0]),  # covers the whole image
            ([0.2, 0.2, 2.0], [0.05, 0.05, 0.05]),  # opacity below 1/255: culled
        ]
        extra_means = torch.stack([world(p) for p, _ in cases])
        extra_scales = torch.tensor([s for _, s in cases], dtype=dtype)
        extra_opac = torch.full((len(cases),), 0.7, dtype=dtype)
        extra_opac[-1] = 0.002
        extra_opac[-2] = 0.3
        means = torch.cat([means, extra_means])
        scales = torch.cat([scales, extra_scales])
        opacities = torch.cat([opacities, extra_opac])
        quats = torch.cat([quats, torch.randn(len(cases), 4, generator=gen, dtype=dtype)])
        colors = torch.cat([colors, torch.rand(len(cases), 3, generator=gen, dtype=dtype)])
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=view, K=K,
                width=width, height=height)


PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _with_grad(scene):
    scene = dict(scene)
    for name in PARAMS:
        scene[name] = scene[name].detach().clone().requires_grad_(True)
    return scene


def _loss_weights(height, width, dtype=F64, seed=7):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(height, width, 3, generator=gen, dtype=dtype), torch.randn(height, width, 1, generator=gen, dtype=dtype)


def _loss(rgb, alpha, w_rgb, w_alpha):
    return (rgb * w_rgb).sum() + (alpha * w_alpha).sum() + 0.5 * (rgb * rgb).sum()


def _assert_grad_close(name, got, ref, rel=1e-4):
    assert got is not None and ref is not None, name
    scale = ref.abs().max().clamp_min(1e-12)
    err = (got - ref).abs().max()
    assert err <= rel * scale, f"gradient of {name}: max error {err:.3e} vs max |ref| {scale:.3e}"


def _run_both(scene, background=None, **render_kwargs):
    w_rgb, w_alpha = _loss_weights(scene["height"], scene["width"], scene["means"].dtype)
    ref_scene, our_scene = _with_grad(scene), _with_grad(scene)
    ref_rgb, ref_alpha, ref_m2d, ref_radii = dense_reference(**ref_scene, background=background)
    _loss(ref_rgb, ref_alpha, w_rgb, w_alpha).backward()
    if render_kwargs:
        bg = torch.zeros(1, 3, dtype=scene["means"].dtype) if background is None else background[None]
        s = our_scene
        rgb, alpha, m2d, radii, visible, _ = rasterize_torch(
            s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], s["viewmat"][None], s["K"][None],
            s["width"], s["height"], bg, batched=False, **render_kwargs,
        )
        out = RasterizeResult(rgb[0], alpha[0], m2d, radii[0], visible[0], None, "torch")
    else:
        out = rasterize(**our_scene, background=background, backend="torch")
    _loss(out.rgb, out.alpha, w_rgb, w_alpha).backward()
    return (ref_rgb, ref_alpha, ref_m2d, ref_radii, ref_scene), (out, our_scene)


# ----------------------------------------------------------------------------- correctness
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_dense_reference_forward_and_gradients(seed):
    scene = make_scene(seed)
    (ref_rgb, ref_alpha, ref_m2d, ref_radii, ref_scene), (out, our_scene) = _run_both(scene)
    assert out.rgb.shape == (24, 32, 3) and out.alpha.shape == (24, 32, 1)
    assert (out.rgb - ref_rgb).abs().max() <= 1e-6
    assert (out.alpha - ref_alpha).abs().max() <= 1e-6
    assert torch.equal(out.radii, ref_radii)
    assert torch.equal(out.visible, (ref_radii > 0).any(1))
    assert ref_alpha.max() > 0.5  # the scene does render something
    for name in PARAMS:
        _assert_grad_close(name, our_scene[name].grad, ref_scene[name].grad)
    _assert_grad_close("means2d", out.means2d.grad, ref_m2d.grad)


def test_hard_cases_are_culled_or_rendered_as_expected():
    scene = make_scene(3)
    out = rasterize(**scene, backend="torch")
    n = scene["means"].shape[0] - 10
    vis = out.visible[n:].tolist()
    # behind, before near plane, past near plane, far outside, outside-overlapping, above, needle, disc, huge, faint
    assert vis == [False, False, True, False, True, True, True, True, True, False]
    assert out.radii[n + 8].min() > 16  # the huge one covers the image
    assert out.means2d[~out.visible].abs().max() == 0


def test_background_and_tile_and_chunk_variants_match_reference():
    scene = make_scene(4, width=21, height=13)  # sizes that tiles do not divide
    background = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    variants = (
        {"tile_size": 1},
        {"tile_size": 3, "chunk_pairs": 64},  # many chunks, per-pair state kept for backward
        {"tile_size": 5, "chunk_pairs": 200, "keep_pairs_limit": 0},  # backward recomputes every chunk
        {"tile_size": 16},
        {"method": "naive"},
    )
    for kwargs in variants:
        (ref_rgb, ref_alpha, ref_m2d, _, ref_scene), (out, our_scene) = _run_both(scene, background, **kwargs)
        assert (out.rgb - ref_rgb).abs().max() <= 1e-6, kwargs
        assert (out.alpha - ref_alpha).abs().max() <= 1e-6, kwargs
        for name in PARAMS:
            _assert_grad_close(f"{name} {kwargs}", our_scene[name].grad, ref_scene[name].grad)
        _assert_grad_close(f"means2d {kwargs}", out.means2d.grad, ref_m2d.grad)


def test_background_composition_rule():
    scene = make_scene(5)
    bg = torch.tensor([0.3, 0.1, 0.8], dtype=F64)
    plain = rasterize(**scene, backend="torch")
    with_bg = rasterize(**scene, background=bg, backend="torch")
    torch.testing.assert_close(with_bg.rgb, plain.rgb + (1 - plain.alpha) * bg, atol=1e-12, rtol=0)
    torch.testing.assert_close(with_bg.alpha, plain.alpha)


def test_saturated_pixels_stop_at_transmittance_threshold():
    # 30 opaque, overlapping Gaussians: central pixels hit the alpha cap and the 1e-4 transmittance stop.
    n = 30
    scene = dict(
        means=torch.stack([torch.zeros(n), torch.zeros(n), torch.linspace(2, 3, n)], -1).to(F64),
        quats=torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1),
        scales=torch.full((n, 3), 0.3, dtype=F64),
        opacities=torch.tensor([0.95, 1.0, 0.6] * (n // 3), dtype=F64),  # 1.0 hits the 0.999 cap at the centre
        colors=torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=F64),
        viewmat=torch.eye(4, dtype=F64),
        K=torch.tensor([[20.0, 0, 8.5], [0, 20.0, 8.5], [0, 0, 1]], dtype=F64),  # means on a pixel centre
        width=16,
        height=16,
    )
    (ref_rgb, ref_alpha, ref_m2d, _, ref_scene), (out, our_scene) = _run_both(scene)
    assert ref_alpha.max() > 0.9998
    assert (out.rgb - ref_rgb).abs().max() <= 1e-6
    assert (out.alpha - ref_alpha).abs().max() <= 1e-6
    for name in PARAMS:
        _assert_grad_close(name, our_scene[name].grad, ref_scene[name].grad)


def test_zero_gaussians():
    scene = make_scene(0, n=0, special=False)
    scene = _with_grad(scene)
    out = rasterize(**scene, background=torch.tensor([0.1, 0.2, 0.3], dtype=F64), backend="torch")
    assert out.rgb.shape == (24, 32, 3) and out.means2d.shape == (0, 2) and out.radii.shape == (0, 2)
    torch.testing.assert_close(out.rgb, torch.tensor([0.1, 0.2, 0.3], dtype=F64).expand(24, 32, 3))
    assert out.alpha.abs().max() == 0
    out.rgb.sum().backward()  # no error; empty gradients
    assert scene["means"].grad is None or scene["means"].grad.numel() == 0


def test_a_gaussian_that_misses_every_pixel_centre_of_its_tiles():
    """A faint sub-pixel Gaussian on a pixel corner: its box touches a tile, but its alpha is under 1/255 at every pixel
    centre, so the tile's chunk has no row left after the cull (this crashed the torch backend's scan)."""
    means = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64, requires_grad=True)
    K = torch.tensor([[50.0, 0.0, 16.0], [0.0, 50.0, 16.0], [0.0, 0.0, 1.0]], dtype=F64)
    out = rasterize(means, torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64), torch.full((1, 3), 1e-4, dtype=F64),
                    torch.tensor([0.006], dtype=F64), torch.ones(1, 3, dtype=F64), torch.eye(4, dtype=F64), K, 32, 32,
                    backend="torch")
    assert int(out.radii.min()) > 0 and out.alpha.abs().max() == 0  # in the plan, yet on no pixel
    out.rgb.sum().backward()
    assert means.grad is not None and means.grad.abs().max() == 0


def test_float32_close_to_float64_reference():
    scene64 = make_scene(6)
    scene32 = {k: (v.float() if torch.is_tensor(v) else v) for k, v in scene64.items()}
    ref_rgb, ref_alpha, _, _ = dense_reference(**scene64)
    out = rasterize(**scene32, backend="torch")
    assert out.rgb.dtype == torch.float32
    assert (out.rgb.double() - ref_rgb).abs().max() < 2e-4
    assert (out.alpha.double() - ref_alpha).abs().max() < 2e-4


def test_gradcheck_tiny_scene():
    scene = make_scene(8, n=6, width=10, height=8, special=False)
    scene["means"] = scene["means"] * 0.15  # gather the Gaussians in the small view
    scene["scales"] = scene["scales"] * 2.0
    bg = torch.tensor([0.1, 0.4, 0.7], dtype=F64, requires_grad=True)
    tensors = [scene[name].clone().requires_grad_(True) for name in PARAMS]

    def render(means, quats, scales, opacities, colors, background):
        out = rasterize(means, quats, scales, opacities, colors, scene["viewmat"], scene["K"], 10, 8,
                        background=background, backend="torch")
        return out.rgb, out.alpha

    assert render(*tensors, bg)[1].max() > 0.3
    # hundreds of tiny renders: one thread avoids OpenMP hand-offs (slow on a loaded, shared machine)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert torch.autograd.gradcheck(render, (*tensors, bg), eps=1e-6, atol=1e-5, rtol=1e-4)
    finally:
        torch.set_num_threads(threads)


def test_camera_batch_matches_single_cameras():
    scene = _with_grad(make_scene(9))
    view2 = look_at_viewmat([-0.5, 0.3, -2.2], [0.1, 0.0, 0.0])
    views = torch.stack([scene["viewmat"], view2])
    Ks = torch.stack([scene["K"], scene["K"]])
    base = {k: v for k, v in scene.items() if k not in ("viewmat", "K")}
    batch = rasterize(**base, viewmat=views, K=Ks, backend="torch")
    assert batch.rgb.shape == (2, 24, 32, 3) and batch.means2d.shape == (2, 40 + 10, 2)
    batch.rgb.sum().backward()
    batch_grad = batch.means2d.grad.clone()
    for c in range(2):
        single = rasterize(**base, viewmat=views[c], K=Ks[c], backend="torch")
        torch.testing.assert_close(batch.rgb[c], single.rgb, atol=1e-12, rtol=0)
        torch.testing.assert_close(batch.radii[c], single.radii)
        single.rgb.sum().backward()
        torch.testing.assert_close(batch_grad[c], single.means2d.grad, atol=1e-10, rtol=1e-9)


def test_chunks_bound_the_pair_count():
    scene = make_scene(10, n=300, width=64, height=48, special=False)
    proj = project_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                             scene["viewmat"], scene["K"], 64, 48)
    budget = 512
    plan = plan_rows(proj.means2d, proj.radii, proj.depths, proj.visible, 64, 48, tile_size=4, chunk_pairs=budget)
    assert len(plan.chunk_bounds) > 3
    tile_rows = torch.bincount(plan.row_tile, minlength=plan.tiles_x * plan.tiles_y)
    for r0, r1, t0, t1 in plan.chunk_bounds:
        # a chunk exceeds the budget only when it is one tile holding more rows than the budget
        assert (r1 - r0) * 16 <= budget or (t1 - t0 == 1 and tile_rows[t0] * 16 > budget)
    assert plan.chunk_bounds[-1][1] == plan.row_gaussian.numel()


# ----------------------------------------------------------------------------- validation and backends
def _valid_scene():
    return make_scene(11, n=5, width=8, height=8, special=False)


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("means", lambda s: s["means"].index_fill(0, torch.tensor([1]), float("nan")), "means"),
        ("scales", lambda s: s["scales"].index_fill(0, torch.tensor([0]), float("inf")), "scales"),
        ("colors", lambda s: s["colors"].index_fill(0, torch.tensor([2]), float("nan")), "colors"),
        ("viewmat", lambda s: s["viewmat"].index_fill(0, torch.tensor([0]), float("nan")), "viewmat"),
        ("quats", lambda s: s["quats"][:, :3], "quats"),
        ("opacities", lambda s: s["opacities"][:, None], "opacities"),
        ("K", lambda s: s["K"][:2], "'K'"),
        ("colors", lambda s: s["colors"][:4], "colors"),
        ("scales", lambda s: -s["scales"], "scales"),
        ("opacities", lambda s: s["opacities"] + 1.5, "opacities"),
        ("quats", lambda s: torch.zeros_like(s["quats"]), "quats"),
        ("width", lambda s: 0, "width"),
        ("height", lambda s: 7.5, "height"),
        ("colors", lambda s: s["colors"].float(), "colors"),
        ("means", lambda s: s["means"].long(), "means"),
    ],
)
def test_bad_inputs_name_the_argument(name, value, message):
    scene = _valid_scene()
    scene[name] = value(scene)
    with pytest.raises((ValueError, TypeError), match=message):
        rasterize(**scene, backend="torch")


def test_mismatched_devices_name_the_argument():
    scene = _valid_scene()
    scene["colors"] = scene["colors"].to("meta")
    with pytest.raises(ValueError, match="'colors' is on device meta"):
        rasterize(**scene)


def test_bad_background_and_backend():
    scene = _valid_scene()
    with pytest.raises(ValueError, match="background"):
        rasterize(**scene, background=torch.zeros(4, dtype=F64))
    with pytest.raises(ValueError, match="backend"):
        rasterize(**scene, backend="cuda")


def test_auto_backend_on_cpu_is_native_or_torch_and_gsplat_is_never_touched():
    scene = _valid_scene()
    imported_before = "gsplat" in sys.modules
    assert rasterize(**scene).backend == ("cpu" if cpu_backend_available() else "torch")
    with pytest.raises((ValueError, RuntimeError), match="gsplat"):
        rasterize(**scene, backend="gsplat")
    if not torch.cuda.is_available() and not imported_before:
        assert "gsplat" not in sys.modules  # importing it is harmless, but rasterize did not even do that


@pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and gsplat (pip install gsplat==1.5.3 packaging)")
def test_parity_with_gsplat_on_cuda():
    scene = make_scene(12, n=400, width=96, height=64, dtype=torch.float32, special=True)
    scene = {k: (v.cuda() if torch.is_tensor(v) else v) for k, v in scene.items()}
    bg = torch.tensor([0.2, 0.3, 0.4], device="cuda")
    w_rgb, w_alpha = (w.float().cuda() for w in _loss_weights(64, 96))
    outs = {}
    for backend in ("torch", "gsplat"):
        s = _with_grad(scene)
        out = rasterize(**s, background=bg, backend=backend)
        assert out.backend == backend
        _loss(out.rgb, out.alpha, w_rgb, w_alpha).backward()
        outs[backend] = (out, s)
    (t_out, t_s), (g_out, g_s) = outs["torch"], outs["gsplat"]
    assert (t_out.rgb - g_out.rgb).abs().max() < 1e-4
    assert (t_out.alpha - g_out.alpha).abs().max() < 1e-4
    assert (t_out.radii - g_out.radii).abs().max() <= 1
    assert (t_out.visible == g_out.visible).float().mean() > 0.99
    for name in PARAMS:
        a, b = t_s[name].grad, g_s[name].grad
        rel = (a - b).norm() / b.norm().clamp_min(1e-12)
        assert rel < 1e-3, f"{name}: relative gradient difference {rel:.2e}"
    rel = (t_out.means2d.grad - g_out.means2d.grad).norm() / g_out.means2d.grad.norm()
    assert rel < 1e-3


def test_value_checks_can_be_sampled_but_shapes_are_always_checked():
    scene = _valid_scene()
    scene["means"] = scene["means"].index_fill(0, torch.tensor([1]), float("nan"))
    with pytest.raises(ValueError, match="'means' contains 3 NaN/Inf"):
        rasterize(**scene, backend="torch")
    rasterize(**scene, backend="torch", check_values=False)  # a loop's unsampled step: no device sync
    scene = _valid_scene()
    scene["colors"] = scene["colors"][:4]
    with pytest.raises(ValueError, match="colors"):
        rasterize(**scene, backend="torch", check_values=False)
