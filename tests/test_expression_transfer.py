"""Expression transfer modes of #30 (animation/expression_transfer.py through driven_params): statistics maps the
driver's range onto the avatar's, subspace keeps the avatar inside the expressions it was trained on, the options
resolve as documented. Plain tensors: no run, no rendering."""

from __future__ import annotations

import pytest
import torch

from geoavatar.animation.expression_transfer import (DEFAULT_TRANSFER, PRIOR_FRAMES, TRANSFER_MODES,
                                                     TransferStatistics, expression_statistics, expression_subspace,
                                                     resolve_transfer, statistics_transfer, subspace_projection)
from geoavatar.animation.transfer import driven_params
from geoavatar.apps import reenact as reenact_app
from geoavatar.errors import OptionError

FRAMES, MODES = 200, 10


def sequence(expr: torch.Tensor, jaw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Per-frame parameters [T, ...] with the given expression (and jaw x-rotation)."""
    count = expr.shape[0]
    jaw_pose = torch.zeros(count, 3)
    if jaw is not None:
        jaw_pose[:, 0] = jaw
    return {"expr": expr, "jaw_pose": jaw_pose, "eyes_pose": torch.zeros(count, 6), "rotation": torch.zeros(count, 3),
            "neck_pose": torch.zeros(count, 3), "translation": torch.zeros(count, 3)}


def learned_from(avatar: dict, driver: dict) -> TransferStatistics:
    statistics = expression_statistics(avatar)
    return TransferStatistics(statistics, expression_subspace(avatar["expr"], statistics.mean["expr"]),
                              expression_statistics(driver))


@pytest.fixture(scope="module")
def avatar() -> dict:
    """An avatar trained on expressions in a 2-D subspace of 10 modes, jaw opening 0..0.2 rad."""
    generator = torch.Generator().manual_seed(0)
    basis = torch.linalg.qr(torch.randn(MODES, 2, generator=generator)).Q  # [10, 2]
    expr = 0.3 + torch.randn(FRAMES, 2, generator=generator) @ basis.T  # [T, 10]
    return sequence(expr, 0.2 * torch.rand(FRAMES, generator=generator))


def test_statistics_maps_the_driver_range_onto_the_avatars(avatar):
    # the avatar's own sequence drives it unchanged
    same = statistics_transfer(avatar, learned_from(avatar, avatar))
    assert torch.allclose(same["expr"], avatar["expr"], atol=1e-5)
    assert torch.allclose(same["jaw_pose"], avatar["jaw_pose"], atol=1e-6)
    # a driver moving twice as much about another mean is mapped back onto the avatar's mean and spread
    driver = sequence(-1.0 + 2.0 * (avatar["expr"] - avatar["expr"].mean(0)), 0.1 + 2.0 * avatar["jaw_pose"][:, 0])
    out = statistics_transfer(driver, learned_from(avatar, driver))
    assert torch.allclose(out["expr"].mean(0), avatar["expr"].mean(0), atol=1e-5)
    spread, wanted = out["expr"].std(0, unbiased=False), avatar["expr"].std(0, unbiased=False)
    shrunk = wanted * 2.0 / ((FRAMES * 4.0 + PRIOR_FRAMES) / (FRAMES + PRIOR_FRAMES)) ** 0.5  # the prior's pull
    assert torch.allclose(spread, shrunk, rtol=1e-4) and (spread > wanted).all() and (spread < 1.1 * wanted).all()
    assert out["jaw_pose"][:, 0].max() < 1.1 * avatar["jaw_pose"][:, 0].max()  # the mouth opens as the avatar's did


def test_a_coefficient_the_avatar_never_moved_stays_at_its_mean(avatar):
    driver = sequence(torch.randn(50, MODES + 5))  # a driver with more modes than the avatar
    out = statistics_transfer(driver, learned_from(avatar, driver))
    assert out["expr"].shape == (50, MODES + 5) and torch.equal(out["expr"][:, MODES:], torch.zeros(50, 5))
    assert torch.equal(out["eyes_pose"], torch.zeros(50, 6))  # the avatar's eyes never turned


def test_subspace_stays_inside_the_avatars_training_expressions(avatar):
    driver = sequence(3.0 * torch.randn(80, MODES, generator=torch.Generator().manual_seed(2)),
                      torch.linspace(-0.5, 0.8, 80))
    learned = learned_from(avatar, driver)
    assert learned.subspace.basis.shape == (MODES, 2)  # the training expressions span two directions
    out = subspace_projection(driver, learned)
    offset = (out["expr"] - avatar["expr"].mean(0)).double()  # [T, 10]
    basis = learned.subspace.basis
    assert torch.allclose(offset - offset @ basis @ basis.T, torch.zeros_like(offset), atol=1e-5)  # in the span
    coordinates = offset @ basis
    assert (coordinates >= learned.subspace.low - 1e-5).all() and (coordinates <= learned.subspace.high + 1e-5).all()
    jaw = out["jaw_pose"][:, 0]
    assert jaw.min() >= avatar["jaw_pose"][:, 0].min() - 1e-6 and jaw.max() <= avatar["jaw_pose"][:, 0].max() + 1e-6
    assert not torch.allclose(driver["expr"].double(), out["expr"].double())  # an expression outside is moved in
    inside = subspace_projection(out, learned)  # what is inside stays, the avatar's own expressions too
    assert all(torch.allclose(inside[k], out[k], atol=1e-5) for k in out)
    own = subspace_projection(avatar, learned)
    assert torch.allclose(own["expr"], avatar["expr"], atol=1e-5) and torch.equal(own["jaw_pose"], avatar["jaw_pose"])


def test_driven_params_in_each_mode(avatar):
    identity = {"shape": torch.zeros(5)}
    driver = sequence(torch.randn(6, MODES), torch.linspace(0.0, 0.3, 6))
    driver["rotation"][:, 1] = torch.linspace(0.0, 0.2, 6)
    avatar_ref = {k: v[:1] for k, v in avatar.items()}
    driver_ref = {k: v[:1] for k, v in driver.items()}
    learned = learned_from(avatar, driver)
    out = {mode: driven_params(identity, avatar_ref, driver, driver_ref, mode, learned=learned)
           for mode in TRANSFER_MODES}
    assert torch.equal(out["absolute"]["expr"], driver["expr"])
    for mode in ("statistics", "subspace"):  # the head turns as in relative transfer; the expression is mapped
        assert torch.allclose(out[mode]["rotation"], out["relative"]["rotation"])
    assert torch.allclose(out["statistics"]["expr"], statistics_transfer(driver, learned)["expr"])
    assert torch.allclose(out["subspace"]["expr"], subspace_projection(out["relative"], learned)["expr"])
    assert torch.allclose(out["subspace"]["jaw_pose"], subspace_projection(out["relative"], learned)["jaw_pose"])
    with pytest.raises(ValueError, match="needs the statistics"):
        driven_params(identity, avatar_ref, driver, driver_ref, "subspace")


def test_transfer_options():
    assert resolve_transfer(None, False) == DEFAULT_TRANSFER and resolve_transfer(None, True) == "relative"
    assert resolve_transfer("subspace", False) == "subspace" and resolve_transfer("relative", True) == "relative"
    with pytest.raises(OptionError, match="--relative means --transfer relative"):
        resolve_transfer("statistics", True)
    with pytest.raises(OptionError, match="--transfer must be one of"):
        resolve_transfer("copy", False)
    # the commands' help names the default the code uses
    from geoavatar.apps import drive as drive_app

    for command in (reenact_app.reenact, drive_app.drive):
        assert f"Default: {DEFAULT_TRANSFER}" in " ".join(command.__doc__.split()), command.__name__
