"""HeadParams (the typed FLAME npz layout) and the T rule of the mouth deformer."""

from __future__ import annotations

import pytest
import torch

from geoavatar.avatar import frame_timestep
from geoavatar.head.params import SUBJECT_KEYS, HeadParams, as_head_params, npz_frame


def batch_npz(frames: int = 4, vertices: int = 6) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    rand = lambda *shape: torch.randn(*shape, generator=generator)  # noqa: E731
    return {"shape": rand(10), "expr": rand(frames, 5), "rotation": rand(frames, 3), "neck_pose": rand(frames, 3),
            "jaw_pose": rand(frames, 3), "eyes_pose": rand(frames, 6), "translation": rand(frames, 3),
            "static_offset": rand(1, vertices, 3), "eyelids": rand(frames, 2)}


def test_frame_keeps_the_subject_keys_and_slices_the_rest():
    npz = batch_npz()
    params = HeadParams.from_npz(npz)
    assert params.batch == 4
    third = params.frame(2)
    assert third.batch == 1 and torch.equal(third.expr, npz["expr"][2:3]) and torch.equal(third.eyes_pose, npz["eyes_pose"][2:3])
    assert third.shape is params.shape and third.static_offset is params.static_offset
    assert torch.equal(params.frame(-1).translation, npz["translation"][3:4])
    with pytest.raises(IndexError):
        params.frame(4)
    # the dict rule is the same one, extras (eyelids) being per-frame
    row = npz_frame(npz, 2)
    assert all(torch.equal(row[key], value) for key, value in third.to_npz().items())
    assert torch.equal(row["eyelids"], npz["eyelids"][2:3]) and all(row[key] is npz[key] for key in SUBJECT_KEYS)


def test_npz_round_trip_and_conversions():
    npz = batch_npz()
    params = HeadParams.from_npz(npz)
    back = params.to_npz()
    assert set(back) == set(npz) - {"eyelids"} and all(torch.equal(back[k], npz[k]) for k in back)
    without = HeadParams.from_npz({k: v for k, v in npz.items() if k != "static_offset"})
    assert without.static_offset is None and "static_offset" not in without.to_npz()
    assert without.to("cpu").static_offset is None and as_head_params(params) is params
    assert torch.equal(as_head_params(npz).expr, npz["expr"])
    assert params.detach().expr.requires_grad is False
    with pytest.raises(KeyError, match="jaw_pose"):
        HeadParams.from_npz({k: v for k, v in npz.items() if k != "jaw_pose"})


def test_t_rule_training_frames_use_their_own_t_others_t0():
    trained = {0, 1, 2, 5}
    assert frame_timestep(5, trained) == 5
    assert frame_timestep(7, trained) is None  # a test frame: T = 0
    assert frame_timestep(5, trained, "zero") is None
    assert frame_timestep(7, trained, "frame") == 7
    with pytest.raises(ValueError, match="auto, zero or frame"):
        frame_timestep(7, trained, "last")
