"""`geoavatar prepare`'s stage cache: a stage's key is a hash of its config, its version and its upstream
stages' keys. The stages are replaced by recorders here, so only the cache logic runs."""

from __future__ import annotations

from dataclasses import fields, replace

import pytest

from geoavatar.prep import pipeline
from geoavatar.prep.pipeline import DEPENDS_ON, STAGES, UNKEYED, PrepareConfig, run_prepare, stage_configs


@pytest.fixture
def ran(monkeypatch):
    """The list of stages run_prepare actually ran (each recorder writes nothing but its marker's info)."""
    calls: list[str] = []
    for stage in STAGES:
        monkeypatch.setitem(pipeline._RUNNERS, stage, lambda config, work, pool, stage=stage: calls.append(stage) or {})
    return calls


@pytest.fixture
def config(tmp_path):
    video = tmp_path / "talk.mp4"
    video.write_bytes(b"not decoded: the stages are recorders")
    return PrepareConfig(video=video, out=tmp_path / "out", progress=False, log=lambda message: None)


def rerun(config, ran) -> list[str]:
    ran.clear()
    run_prepare(config)
    return list(ran)


def test_a_changed_field_redoes_its_stage_and_the_dependants_only(config, ran):
    assert rerun(config, ran) == list(STAGES)
    assert rerun(config, ran) == []  # everything cached
    changed = config
    for change, redone in [
        ({"test_fraction": 0.3}, ["write", "sound"]),
        ({"mask_backend": "other"}, ["masks", "photometric", "write", "sound"]),  # the tracking does not read masks
        ({"tracking_steps": (10, 20)}, ["tracking", "photometric", "write", "sound"]),
        ({"static_offset": False}, ["tracking", "photometric", "write", "sound"]),
        ({"missing": "drop"}, ["landmarks", "masks", "tracking", "photometric", "write", "sound"]),
        ({"photometric_epochs": (1, 1)}, ["photometric", "write", "sound"]),
        ({"crop_sigma": 3.0}, list(STAGES)),
    ]:
        changed = replace(changed, **change)
        assert rerun(changed, ran) == redone, change
        assert rerun(changed, ran) == []
    assert rerun(config, ran) == list(STAGES)  # back to the first options: the markers hold other keys now
    assert rerun(config, ran) == []
    # Progress, logging, the worker count and where the dataset goes are not part of any key.
    assert rerun(replace(config, progress=True, log=print, workers=3), ran) == []


def test_no_photometric_ignores_the_photometric_settings(config, ran):
    """--no-photometric skips the stage: its settings (e.g. a changed default) redo nothing, and turning it on
    over such a folder redoes the photometric stage and the write only (what a user who upgrades does)."""
    plain = replace(config, photometric=False)
    assert rerun(plain, ran) == list(STAGES)
    assert rerun(replace(plain, photometric_epochs=(1, 1)), ran) == []
    assert rerun(config, ran) == ["photometric", "write", "sound"]
    assert rerun(plain, ran) == ["photometric", "write", "sound"]


def test_an_interrupted_stage_redoes_its_dependants(config, ran):
    run_prepare(config)
    (config.out / pipeline.WORK / "landmarks.json").unlink()  # killed while the landmarks were being redone
    assert rerun(config, ran) == ["landmarks", "masks", "tracking", "photometric", "write", "sound"]


def test_a_changed_tracking_default_or_stage_version_is_not_reused(config, ran, monkeypatch):
    run_prepare(config)
    original = pipeline.tracking_config
    monkeypatch.setattr(pipeline, "tracking_config", lambda c: replace(original(c), offset_decay=0.2))
    assert rerun(config, ran) == ["tracking", "photometric", "write", "sound"]
    monkeypatch.setitem(pipeline.STAGE_VERSIONS, "masks", pipeline.STAGE_VERSIONS["masks"] + 1)
    assert rerun(config, ran) == ["masks", "photometric", "write", "sound"]


def test_a_changed_video_file_redoes_everything(config, ran):
    run_prepare(config)
    config.video.write_bytes(b"another video, of another length")
    assert rerun(config, ran) == list(STAGES)


def test_every_config_field_belongs_to_one_stage_key(config):
    stages = {f.name: f.metadata["stage"] for f in fields(PrepareConfig)}
    assert set(stages.values()) <= set(STAGES) | {UNKEYED}
    assert {name for name, stage in stages.items() if stage == UNKEYED} == {"out", "progress", "log", "workers"}
    configs = stage_configs(config)
    for name, stage in stages.items():
        if stage != UNKEYED:
            assert name in configs[stage]
    assert "offset_decay" in configs["tracking"]["tracking_config"]
    assert set(DEPENDS_ON) == set(STAGES)
    assert all(STAGES.index(up) < STAGES.index(stage) for stage, ups in DEPENDS_ON.items() for up in ups)
    with pytest.raises(ValueError, match="unknown prepare stage"):
        pipeline._stage_field("crop")
