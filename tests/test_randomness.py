"""train/randomness.py: the per-step draws are pure functions of (seed, step) and keep the formulas runs were trained
with (a saved run must replay its frame order, backgrounds and turned cameras after a resume)."""

from __future__ import annotations

import pytest
import torch

from geoavatar.train.randomness import (
    BACKGROUND, FRAME_ORDER, TURNED_CAMERA, frame_index, restore_rng, rng_state, stream_generator, turned_angles,
)


def test_the_streams_keep_the_seeds_saved_runs_were_drawn_with():
    # the literal formulas of the trainer before the streams shared one function (#29)
    assert torch.equal(torch.randperm(10, generator=stream_generator(3, FRAME_ORDER, 4)),
                       torch.randperm(10, generator=torch.Generator().manual_seed(3 * 1_000_003 + 4)))
    assert torch.equal(torch.rand(3, generator=stream_generator(3, BACKGROUND, 17)),
                       torch.rand(3, generator=torch.Generator().manual_seed(3 * 1_000_003 + 7_919 * 17 + 1)))
    assert torch.equal(torch.rand(2, generator=stream_generator(3, TURNED_CAMERA, 17)),
                       torch.rand(2, generator=torch.Generator().manual_seed(3 * 1_000_003 + 7_919 * 17 + 2)))
    with pytest.raises(ValueError, match="unknown random stream"):
        stream_generator(0, "noise", 1)


def test_frame_order_is_a_permutation_per_epoch():
    first, second = ([frame_index(step, 7, 5) for step in range(start, start + 7)] for start in (1, 8))
    assert sorted(first) == sorted(second) == list(range(7)) and first != second
    assert first == [frame_index(step, 7, 5) for step in range(1, 8)]


def test_turned_angles_are_seeded_and_within_range():
    drawn = [turned_angles(45.0, 10.0, 3, step) for step in range(1, 200)]
    assert drawn == [turned_angles(45.0, 10.0, 3, step) for step in range(1, 200)]
    assert all(abs(y) <= 45.0 and abs(p) <= 10.0 for y, p in drawn)
    assert max(y for y, _ in drawn) > 30.0 and min(y for y, _ in drawn) < -30.0
    assert turned_angles(45.0, 10.0, 4, 7) != turned_angles(45.0, 10.0, 3, 7)



def test_a_cuda_runs_generator_state_resumes_on_cpu_reproducibly():
    """A checkpoint of a CUDA run holds a 16-byte generator state; resuming it on CPU (another size) seeds the
    CPU generator from it, the same way each time, instead of failing in set_state."""
    state = rng_state(torch.Generator().manual_seed(3))
    state["generator"] = torch.arange(16, dtype=torch.uint8)  # the size of a CUDA Philox state
    draws = []
    for _ in range(2):
        generator = torch.Generator()
        restore_rng(state, generator)
        draws.append(torch.rand(4, generator=generator))
    assert torch.equal(draws[0], draws[1])
