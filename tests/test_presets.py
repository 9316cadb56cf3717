"""Configs: paper defaults, the ablation presets A-I (paper Tables 3, 6, 7) and schedule scaling."""

import dataclasses

import pytest

from geoavatar.config import ABLATIONS, TrainConfig, preset, preset_components, presets_table

# (face sets, mouth structure, part-wise deformation, L_angle), read off the paper:
# Table 3: A baseline GaussianAvatars_0; B +APS; C +FLAME mouth; D +part-wise deformation; E +L_angle.
# Table 6: F rigid / G flexible baselines; H / I add the mouth modification and deformation
#          (I = Table 7's "Ours w/o APS", so L_angle stays on).
PAPER = {
    "A": ("gaussianavatars", "gaussianavatars", False, False),
    "B": ("aps", "gaussianavatars", False, False),
    "C": ("aps", "geoavatar", False, False),
    "D": ("aps", "geoavatar", True, False),
    "E": ("aps", "geoavatar", True, True),
    "F": ("rigid", "gaussianavatars", False, False),
    "G": ("flexible", "gaussianavatars", False, False),
    "H": ("rigid", "geoavatar", True, True),
    "I": ("flexible", "geoavatar", True, True),
    "E-no-mouth": ("aps", "gaussianavatars", True, True),
    "E-no-deform": ("aps", "geoavatar", False, True),
}


@pytest.mark.parametrize("name", sorted(PAPER))
def test_preset_switches_exactly_the_papers_components(name):
    config = preset(name)
    got = preset_components(config)
    assert (got.face_sets, got.mouth, got.mouth_deform, got.angle_loss) == PAPER[name]
    # nothing else differs from GeoAvatar's defaults
    default = TrainConfig()
    assert config.steps == default.steps and config.aps_step == default.aps_step
    assert config.densify == default.densify and config.lr == default.lr
    assert dataclasses.replace(config.loss, use_angle=True) == default.loss
    assert config.model.sh_degree == 0


def test_cumulative_chain_a_to_e_adds_one_component_per_step():
    chain = [preset_components(preset(n)) for n in "ABCDE"]
    for before, after in zip(chain, chain[1:]):
        changed = sum(getattr(before, f) != getattr(after, f) for f in ("face_sets", "mouth", "mouth_deform", "angle_loss"))
        assert changed == 1
    assert set(ABLATIONS) == set(PAPER)
    assert "GeoAvatar" in presets_table()


def test_paper_defaults():
    c = preset()  # E = GeoAvatar
    assert c.steps == 200_000 and c.aps_step == 100_000
    assert (c.loss.tau_rigid, c.loss.tau_flexible, c.loss.tau_mouth_value, c.loss.tau_angle) == (0.1, 2.0, 0.1, 0.78)
    assert c.loss.lambda_dssim == 0.2
    assert c.densify.start == 10_000 and c.densify.every == 2_000 and c.densify.reset_opacity_every == 60_000
    assert c.densify.grad_threshold == 2e-4 and c.densify.prune_opacity == 0.005 and c.densify.percent_dense == 0.01
    assert (c.lr.position, c.lr.position_final, c.lr.features, c.lr.opacity, c.lr.scaling, c.lr.rotation) == (
        5e-3, 5e-5, 2.5e-3, 0.05, 0.017, 1e-3)
    assert c.lr.adam_eps == 1e-15 and c.refine_tracking


def test_scaled_to_keeps_every_milestone_proportional():
    c = preset("E").scaled_to(2_000)
    assert c.steps == 2_000 and c.aps_step == 1_000
    assert (c.densify.start, c.densify.stop, c.densify.every, c.densify.reset_opacity_every) == (100, 2_000, 20, 600)
    assert c.lr.position_decay_steps == 2_000
    tiny = preset("E", steps=10)
    assert tiny.densify.every >= 1 and tiny.densify.reset_opacity_every >= 1 and tiny.aps_step == 5
    # scaling back and forth is stable
    assert preset("E").scaled_to(2_000).scaled_to(200_000) == preset("E")


def test_bad_values_name_the_option():
    with pytest.raises(ValueError, match="unknown preset 'Z'"):
        preset("Z")
    with pytest.raises(ValueError, match="steps"):
        TrainConfig().scaled_to(0)
    bad = dataclasses.replace(TrainConfig(), aps_step=300_000)
    with pytest.raises(ValueError, match="aps_step"):
        bad.validate()
    bad = TrainConfig()
    bad.model.sh_degree = 3
    with pytest.raises(ValueError, match="sh_degree"):
        bad.validate()
    bad = TrainConfig()
    bad.model.mouth = "none"
    with pytest.raises(ValueError, match="mouth_deform"):
        bad.validate()
