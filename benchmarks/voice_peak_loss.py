"""The voice's loss with an LVE-shaped term beside its mean vertex error: per frame, the largest squared error over
the head model's lip vertices (FaceFormer's LVE is that maximum, averaged over frames), weighted by PEAK_WEIGHT
(0: today's loss). Runs benchmarks/voice_variants.py with the trainer's loss patched (measured, not kept: docs/REJECTED.md).

    PEAK_WEIGHT=0.3 .venv/bin/python benchmarks/voice_peak_loss.py RUN --seeds 0,1,2
"""

from __future__ import annotations

import os
import runpy
import sys
from pathlib import Path

import torch

import geoavatar.voice.train as voice_train

WEIGHT = float(os.environ.get("PEAK_WEIGHT", "0"))
_jacobians, _init, _loss = voice_train.face_jacobians, voice_train._Trainer.__init__, voice_train._Trainer._loss
_lips: dict[str, torch.Tensor] = {}


def face_jacobians(probe, targets, expr_dims):
    lips, upper = _jacobians(probe, targets, expr_dims)
    _lips["jacobian"] = lips  # [Kl*3, D] how each lip vertex moves with each output
    return lips, upper


def init(self, data, config, net, metric, mean, std, blocks):
    _init(self, data, config, net, metric, mean, std, blocks)
    self.peak_jacobian = (_lips["jacobian"] * std.double()[None]).float()  # [Kl*3, D] standardised outputs -> metres


def loss(self, predicted, target, learns):
    """Today's loss plus WEIGHT x each frame's largest squared lip-vertex error (m^2), per member on its own rows."""
    base = _loss(self, predicted, target, learns)
    if WEIGHT == 0:
        return base
    moved = (predicted - target) @ self.peak_jacobian.T  # [K, R, L, Kl*3]
    peak = moved.reshape(*moved.shape[:-1], -1, 3).square().sum(-1).amax(-1)  # [K, R, L]
    weight = learns.float()
    return base + WEIGHT * ((peak * weight).sum((1, 2)) / weight.sum((1, 2)).clamp_min(1.0)).sum()


voice_train.face_jacobians, voice_train._Trainer.__init__, voice_train._Trainer._loss = face_jacobians, init, loss
if __name__ == "__main__":
    sys.argv[0] = str(Path(__file__).with_name("voice_variants.py"))
    runpy.run_path(sys.argv[0], run_name="__main__")
