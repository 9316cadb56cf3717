"""Configs: paper defaults, the ablation presets A-I (paper Tables 3, 6, 7) and schedule scaling."""

import dataclasses
import json

import pytest

from geoavatar.config import (ABLATIONS, STEP_FIELDS, TrainConfig, config_values, preset, preset_components,
                              presets_table, with_values)

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
    assert c.densify.stop == 67_000  # ours (#40): a third of the run; GaussianAvatars densifies to the end
    assert c.densify.grad_threshold == 2e-4 and c.densify.prune_opacity == 0.005 and c.densify.percent_dense == 0.01
    assert (c.lr.position, c.lr.position_final, c.lr.features, c.lr.opacity, c.lr.scaling, c.lr.rotation) == (
        5e-3, 5e-5, 2.5e-3, 0.05, 0.017, 1e-3)
    assert c.lr.adam_eps == 1e-15 and c.refine_tracking


@pytest.mark.parametrize("name", sorted(PAPER))
def test_every_preset_has_normal_shading_and_image_colours_and_can_turn_them_off(name):
    """#18 third round: on by default (front and novel views better on two generated subjects and two videos);
    the paper's / GaussianAvatars' model stays one option away."""
    config = preset(name)
    assert config.model.normal_shading and config.model.init_colour == "images"
    off = with_values(config, {"model.normal_shading": False, "model.init_colour": "grey"}).validate()
    assert not off.model.normal_shading and off.model.init_colour == "grey"


def test_a_stored_configuration_from_before_the_options_reads_as_trained():
    """Runs written before model.normal_shading / init_colour existed were trained without them: loading (and
    --resume / --extend) must not give them today's defaults."""
    from geoavatar.train.checkpoint import FIELDS_ADDED_LATER, config_from_json, config_to_dict

    stored = config_to_dict(preset("E"))
    assert set(FIELDS_ADDED_LATER["model"]) <= set(stored["model"])
    for key in FIELDS_ADDED_LATER["model"]:
        del stored["model"][key]
    old = config_from_json(json.dumps(stored))
    assert not old.model.normal_shading and old.model.init_colour == "grey"
    assert dataclasses.replace(old, model=preset("E").model) == preset("E")  # nothing else changes
    assert config_from_json(json.dumps(config_to_dict(preset("E")))) == preset("E")  # written today: as stored


def test_scaled_to_keeps_every_milestone_proportional():
    c = preset("E").scaled_to(2_000)
    assert c.steps == 2_000 and c.aps_step == 1_000
    assert (c.densify.start, c.densify.stop, c.densify.every, c.densify.reset_opacity_every) == (100, 670, 20, 600)
    assert c.lr.position_decay_steps == 6_000  # GaussianAvatars' span: 3x the run
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


def test_scaled_to_leaves_the_kept_milestones_and_scales_the_rest():
    base = with_values(preset("E"), {"aps_step": 700, "densify.every": 7})
    c = base.scaled_to(2_000, keep=("aps_step", "densify.every"))
    assert (c.steps, c.aps_step, c.densify.every) == (2_000, 700, 7)  # as set: steps of this run
    assert (c.densify.start, c.densify.stop, c.densify.reset_opacity_every, c.lr.position_decay_steps) == (
        100, 670, 600, 6_000)  # the others scale as always
    assert base.scaled_to(2_000).aps_step == 7 and base.scaled_to(2_000).densify.every == 1  # scaled: 700/100, 7/100
    with pytest.raises(ValueError, match="keep names no step-based field: loss.tau_rigid"):
        base.scaled_to(2_000, keep=("loss.tau_rigid",))
    assert set(STEP_FIELDS) <= set(config_values(TrainConfig()))


def test_extended_adds_steps_and_keeps_every_milestone():
    c = preset("E", steps=400)
    longer = c.extended(100)
    assert longer.steps == 500
    assert dataclasses.replace(longer, steps=400) == c  # nothing else changes
    assert longer.densify.stop == 134 and longer.lr.position_decay_steps == 1_200  # no densification after 134
    with pytest.raises(ValueError, match="extra_steps must be positive"):
        c.extended(0)


def test_config_values_and_with_values_by_dotted_name():
    values = config_values(preset("A"))
    assert values["model.face_sets"] == "gaussianavatars" and values["loss.use_angle"] is False
    assert values["model.mouth_deform.enabled"] is False and "model.mouth_deform" not in values
    changed = with_values(preset("A"), {"loss.lambda_angle": 0.5, "model.mouth_deform.hidden_width": 64})
    assert changed.loss.lambda_angle == 0.5 and changed.model.mouth_deform.hidden_width == 64
    assert config_values(changed) == {**values, "loss.lambda_angle": 0.5, "model.mouth_deform.hidden_width": 64}
    for bad in ("loss.nope", "loss", "aps_step.x"):
        with pytest.raises(ValueError, match="has no field"):
            with_values(preset("A"), {bad: 1})
