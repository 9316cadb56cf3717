"""Every random draw of a training run, and the generator states a checkpoint keeps for an exact resume.

Two kinds of randomness:
- Per-step draws that are pure functions of (seed, what they are for, step): the frame order (one permutation per
  epoch), the random background colour and the warped view's turned camera. A resumed run draws what the
  uninterrupted one would have without saving anything; `stream_generator` is the one formula behind them.
- The global generators (torch, CUDA, numpy, python) and the trainer's own densification generator, which advance
  with use: `rng_state` captures them as checkpoint-safe values (tensors, numbers, lists: loadable with
  `torch.load(weights_only=True)`), `restore_rng` sets them back.
"""

from __future__ import annotations

import random

import numpy as np
import torch
from torch import Tensor

# The per-step streams. Their keys keep the formulas runs were trained with, so a saved run replays its draws.
FRAME_ORDER, BACKGROUND, TURNED_CAMERA = "frame_order", "background", "turned_camera"
_STREAM_OFFSET = {BACKGROUND: 1, TURNED_CAMERA: 2}
_SEED_STRIDE = 1_000_003  # seeds s and s + 1 share no stream
_STEP_STRIDE = 7_919


def stream_generator(seed: int, stream: str, counter: int) -> torch.Generator:
    """A CPU generator that is a pure function of (seed, stream, counter); `counter` is the epoch for FRAME_ORDER
    and the step (1-based) for the other streams."""
    if stream == FRAME_ORDER:
        key = counter
    elif stream in _STREAM_OFFSET:
        key = _STEP_STRIDE * counter + _STREAM_OFFSET[stream]
    else:
        raise ValueError(f"unknown random stream '{stream}'")
    return torch.Generator().manual_seed(seed * _SEED_STRIDE + key)


def frame_index(step: int, count: int, seed: int) -> int:
    """Training frame of `step` (1-based): a seeded permutation per epoch, stateless for resuming."""
    epoch, position = divmod(step - 1, count)
    return int(torch.randperm(count, generator=stream_generator(seed, FRAME_ORDER, epoch))[position])


def step_background(dataset_background: Tensor, mode: str, seed: int, step: int) -> Tensor:
    """[3] the training background of `step` (TrainConfig.background): the dataset's colour, or a uniform
    random colour that is a pure function of (seed, step), so a resumed run draws the same ones."""
    if mode == "dataset":
        return dataset_background
    return torch.rand(3, generator=stream_generator(seed, BACKGROUND, step)).to(dataset_background)


def turned_angles(max_yaw: float, max_pitch: float, seed: int, step: int) -> tuple[float, float]:
    """(yaw, pitch) in degrees of `step`'s turned camera: uniform in [-max_yaw, max_yaw] x [-max_pitch, max_pitch], a
    pure function of (seed, step) so that a resumed run draws the same ones."""
    u = torch.rand(2, generator=stream_generator(seed, TURNED_CAMERA, step), dtype=torch.float64).tolist()
    return (2.0 * u[0] - 1.0) * max_yaw, (2.0 * u[1] - 1.0) * max_pitch


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def rng_state(generator: torch.Generator) -> dict:
    """The global generators' states and `generator`'s, as checkpoint-safe values."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": {"kind": str(kind), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "python": {"version": int(version), "internal": [int(v) for v in internal], "gauss_next": gauss_next},
        "generator": generator.get_state(),
    }


def restore_rng(state: dict, generator: torch.Generator) -> None:
    """Set the global generators and `generator` back to a `rng_state`."""
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    n = state["numpy"]
    np.random.set_state((n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
    saved = state["generator"].cpu()
    if saved.numel() == generator.get_state().numel():
        generator.set_state(saved)
    else:  # saved on another kind of device (a CUDA run resumed on CPU or back): its states do not carry over
        generator.manual_seed(int.from_bytes(bytes(saved[:8].tolist()), "little") % 2**63)


__all__ = ["BACKGROUND", "FRAME_ORDER", "TURNED_CAMERA", "frame_index", "restore_rng", "rng_state", "seed_everything",
           "step_background", "stream_generator", "turned_angles"]
