"""Training losses: L_rgb (L1 + D-SSIM), L_reg by set, L_angle, GaussianAvatars' scale loss."""

import math

import pytest
import torch
import torch.nn.functional as F

from geoavatar.avatar.aps import BASELINE, FLEXIBLE, MOUTH, RIGID
from geoavatar.config import LossConfig
from geoavatar.imaging import ssim
from geoavatar.imaging.quality import load_extension as load_ssim_extension
from geoavatar.train.losses import (
    angle_loss, avatar_loss, position_loss, regularization_losses, rgb_loss, scale_loss,
)


def reference_ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """3DGS's loss_utils.ssim written out: a full 2D 11x11 Gaussian window (sigma 1.5), zero padding 5."""
    x, y = x.permute(2, 0, 1)[None].double(), y.permute(2, 0, 1)[None].double()
    g = torch.tensor([math.exp(-((i - 5) ** 2) / (2 * 1.5**2)) for i in range(11)], dtype=torch.float64)
    g = g / g.sum()
    w = (g[:, None] @ g[None, :]).expand(3, 1, 11, 11)
    conv = lambda t: F.conv2d(t, w, padding=5, groups=3)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx, syy, sxy = conv(x * x) - mx**2, conv(y * y) - my**2, conv(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean()


def test_ssim_matches_the_3dgs_formula_and_is_one_for_identical_images():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(40, 48, 3, generator=g)
    b = (a + 0.1 * torch.randn(40, 48, 3, generator=g)).clamp(0, 1)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-5)
    assert ssim(a, b).item() == pytest.approx(reference_ssim(a, b).item(), abs=1e-5)
    assert ssim(a, b).item() < 0.99
    batched = ssim(torch.stack([a, a]), torch.stack([b, b]))
    assert batched.item() == pytest.approx(ssim(a, b).item(), abs=1e-6)
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(a, b[:-1])


@pytest.mark.skipif(load_ssim_extension() is None, reason="the native SSIM did not build (no compiler)")
@pytest.mark.parametrize("shape", [(40, 48, 3), (2, 17, 23, 3), (9, 7, 1)])
def test_the_native_ssim_and_its_gradient_equal_the_convolutions(shape):
    g = torch.Generator().manual_seed(2)
    a = torch.rand(*shape, generator=g, requires_grad=True)
    b = (a.detach() + 0.2 * torch.randn(*shape, generator=g)).clamp(0, 1)
    values, grads = [], []
    for native in (True, False):
        value = ssim(a, b, native=native)
        (grad,) = torch.autograd.grad(value, a)
        values.append(value.item())
        grads.append(grad)
    assert values[0] == pytest.approx(values[1], abs=1e-6)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-9)
    assert grads[0].abs().max() > 1e-6  # a gradient to compare, not zeros on both sides
    a64 = a.detach().double()[..., :6, :5, :].contiguous().requires_grad_()
    b64 = b.double()[..., :6, :5, :].contiguous()
    assert torch.autograd.gradcheck(lambda t: ssim(t, b64), (a64,))


def test_a_target_that_needs_a_gradient_gets_one():
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(12, 12, 3, generator=g), torch.rand(12, 12, 3, generator=g, requires_grad=True)
    (grad,) = torch.autograd.grad(ssim(a, b), b)  # the native kernels differentiate the image only: convolutions
    (expected,) = torch.autograd.grad(ssim(a, b, native=False), b)
    torch.testing.assert_close(grad, expected)


def test_rgb_loss_weights_l1_and_dssim():
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(16, 16, 3, generator=g), torch.rand(16, 16, 3, generator=g)
    total, l1, dssim = rgb_loss(a, b, 0.2)
    assert l1.item() == pytest.approx((a - b).abs().mean().item())
    assert dssim.item() == pytest.approx(1 - ssim(a, b).item(), abs=1e-6)
    assert total.item() == pytest.approx(0.8 * l1.item() + 0.2 * dssim.item(), abs=1e-6)
    zero, _, _ = rgb_loss(a, a)
    assert zero.item() == pytest.approx(0.0, abs=1e-5)


def test_angle_loss_is_zero_inside_tau_rigid_and_positive_for_a_far_tilted_gaussian():
    cfg = LossConfig()
    phi = torch.tensor([3.0, 3.0, 0.5, 1.5])
    r = torch.tensor([0.05, cfg.tau_rigid, 1.5, 1.5])
    per = [angle_loss(r[i:i + 1], phi[i:i + 1], cfg.tau_rigid, cfg.tau_angle).item() for i in range(4)]
    assert per[0] == 0.0 and per[1] == 0.0  # r <= tau_rigid: any angle is fine
    assert per[2] == 0.0  # far but inside the 45 degree cone
    assert per[3] == pytest.approx(1.5 - 0.78)


def test_position_loss_uses_the_threshold_of_each_gaussians_set():
    cfg = LossConfig(lambda_reg=1.0, use_angle=False, lambda_scale=0.0)
    face_sets = torch.tensor([RIGID, FLEXIBLE, MOUTH, BASELINE])
    means = torch.zeros(4, 3)
    means[:, 0] = 1.5  # r = 1.5 on every face, along a tangent axis
    losses = regularization_losses(means, torch.zeros(4, 3), torch.arange(4), face_sets, cfg)
    expected = torch.tensor([1.5 - 0.1, 0.0, 1.5 - 0.1, 1.5 - 1.0]).mean()
    assert losses["reg"].item() == pytest.approx(expected.item(), abs=1e-6)
    assert set(losses) == {"reg"}
    # visibility mask: the mean runs over visible Gaussians only
    visible = torch.tensor([False, True, False, False])
    assert regularization_losses(means, torch.zeros(4, 3), torch.arange(4), face_sets, cfg, visible)["reg"].item() == 0.0
    assert position_loss(torch.tensor([0.5]), torch.tensor([0.1])).item() == pytest.approx(0.4)


def test_angle_term_in_the_regulariser_and_its_gradient():
    cfg = LossConfig(lambda_scale=0.0)
    # a flexible-set Gaussian at r = 1.5 lying in the face plane: phi = pi/2 > 0.78
    means = torch.tensor([[1.5, 0.0, 0.0], [0.0, 1.5, 0.0], [0.0, 0.0, 0.0]], requires_grad=True)
    face_sets = torch.tensor([FLEXIBLE, FLEXIBLE, RIGID])
    losses = regularization_losses(means, torch.zeros(3, 3), torch.arange(3), face_sets, cfg)
    assert losses["angle"].item() == pytest.approx(cfg.lambda_angle * (math.pi / 2 - 0.78) / 3, rel=1e-5)
    sum(losses.values()).backward()
    assert torch.isfinite(means.grad).all()
    assert means.grad[0, 1] < 0  # the tilted one is pulled towards the +normal (gradient descent raises y)
    assert torch.equal(means.grad[2], torch.zeros(3))  # at the origin: no push


def test_scale_loss_matches_gaussianavatars_form():
    s = torch.log(torch.tensor([[0.3, 0.3, 0.3], [1.0, 0.6, 2.0]]))
    expected = (torch.tensor([0.0, math.hypot(0.4, 1.4)])).mean()
    assert scale_loss(s, 0.6).item() == pytest.approx(expected.item(), abs=1e-6)


def test_avatar_loss_total_is_the_sum_of_terms():
    g = torch.Generator().manual_seed(2)
    img, gt = torch.rand(12, 12, 3, generator=g), torch.rand(12, 12, 3, generator=g)
    means = torch.randn(5, 3, generator=g) * 2
    terms = avatar_loss(img, gt, means, torch.zeros(5, 3), torch.tensor([0, 0, 1, 1, 1]),
                        torch.tensor([RIGID, FLEXIBLE]), LossConfig())
    assert set(terms) >= {"rgb", "reg", "angle", "scale", "l1", "dssim", "total"}
    assert terms["total"].item() == pytest.approx(sum(terms[k].item() for k in ("rgb", "reg", "angle", "scale")), rel=1e-6)
