"""Four changes to the voice model that no setting of VoiceConfig makes, each learned over several seeds and scored
on the run's held-out frames by `benchmarks/voice_variants.py` (which this script runs with the change patched in).

    LEVER=mfcc20 .venv/bin/python benchmarks/voice_levers.py RUN --seeds 0,1,2
    LEVER=context .venv/bin/python benchmarks/voice_levers.py RUN --set '{"past": 1.0}' --seeds 0,1,2

LEVER:
    mfcc20    the network hears the 20 first cepstral coefficients of its log-mel frames (a DCT over the 40 bands,
              truncated): a smoother spectral envelope and half the input channels
    subframe  each training run of frames starts at a random fraction of a frame: its windows sit between the video
              frames' 10-ms positions and its targets are interpolated there (more distinct windows from the same
              seconds of speech)
    conv2d    two 2-D convolutions over (band, time) before today's network, which halve the bands twice: filters
              shared across frequency, as a vocal tract's formants move from speaker to speaker
    context   with `past` 1.0: today's network on the last 0.2 s and the look-ahead, plus the 0.8 s before that
              pooled into four 0.2-s means of each band through a 16-unit layer (a long context with few weights)
"""

from __future__ import annotations

import math
import os
import runpy
import sys
from pathlib import Path

import torch
from torch import nn

import geoavatar.voice.model as voice_model
import geoavatar.voice.net as voice_net
import geoavatar.voice.train as voice_train
from geoavatar.sound import FRAME_RATE, N_MELS

NEAR = 31  # feature frames today's network hears: 0.2 s before, the frame, 0.1 s after
POOL = 20  # feature frames in each pooled mean of the long context (0.2 s)


def cepstra(count: int) -> None:
    """The networks hear `count` cepstral coefficients instead of the log-mel bands."""
    bands = torch.arange(N_MELS, dtype=torch.float64)
    dct = torch.stack([torch.cos(math.pi * c * (bands + 0.5) / N_MELS) for c in range(count)])  # [C, M]
    dct = (dct / dct.norm(dim=1, keepdim=True)).float()
    mel_windows = voice_train.windows

    def windows(features, centres, past, ahead):
        return torch.einsum("cm,nmw->ncw", dct, mel_windows(features, centres, past, ahead))  # [N, C, W]

    def build_net(config, outputs):
        frames = int(round(config.past * FRAME_RATE)) + 1 + int(round(config.ahead * FRAME_RATE))
        return voice_net.VoiceEnsemble(config.members, count, frames, outputs, config.width, config.hidden,
                                       config.dropout)

    voice_train.windows = voice_model.windows = windows
    voice_model.VoiceModel.build_net = staticmethod(build_net)


def subframe_step(self) -> float:
    """_Trainer.step with each run of frames moved by a random fraction of a frame, its targets interpolated."""
    self.net.train()
    rows = voice_train._runs(len(self.z), self.config, self.rng)  # [R, L]
    following = (rows + 1).clamp_max(len(self.z) - 1)
    start, end = self.data.centres[rows].float(), self.data.centres[following].float()  # [R, L] feature frames
    fraction = torch.as_tensor(self.rng.uniform(0, 1, rows.shape[0]), dtype=torch.float32)[:, None]  # [R, 1]
    fraction = torch.where(end - start < 10, fraction.expand_as(start), torch.zeros_like(start))  # not across a cut
    centres = torch.round(start + fraction * (end - start)).long()
    target = (1 - fraction)[..., None] * self.z[rows] + fraction[..., None] * self.z[following]  # [R, L, D]
    learns = self.learns[:, rows] & self.learns[:, following]
    predicted = self.net(voice_train.windows(self._features(), centres.reshape(-1), self.past, self.ahead))
    loss = self._loss(predicted.reshape(predicted.shape[0], *rows.shape, -1), target, learns)
    self.optimiser.zero_grad(set_to_none=True)
    loss.backward()
    self.optimiser.step()
    self.schedule.step()
    return float(loss.detach())


class BandConvNet(nn.Module):
    """Two 2-D convolutions over (band, time), each halving the bands, then today's VoiceNet."""

    def __init__(self, bands, frames, outputs, width=48, hidden=128, dropout=0.4):
        super().__init__()
        self.front = nn.Sequential(nn.Conv2d(1, 8, (5, 3), stride=(2, 1), padding=(2, 1)), nn.GELU(),
                                   nn.Conv2d(8, 8, (5, 3), stride=(2, 1), padding=(2, 1)), nn.GELU())
        self.back = voice_net.VoiceNet(8 * ((bands + 3) // 4), frames, outputs, width, hidden, dropout)

    def forward(self, windows):
        return self.back(self.front(windows[:, None]).flatten(1, 2))  # [N, 1, M, W] -> [N, 8 M/4, W]


class ContextNet(nn.Module):
    """Today's VoiceNet on the last NEAR frames, beside the earlier frames pooled into POOL-frame means."""

    def __init__(self, bands, frames, outputs, width=48, hidden=128, dropout=0.4):
        super().__init__()
        self.near = voice_net.VoiceNet(bands, NEAR, hidden, width, hidden, dropout)
        self.chunks = (frames - NEAR) // POOL
        self.far = nn.Sequential(nn.Flatten(), nn.Dropout(dropout), nn.Linear(bands * self.chunks, 16), nn.GELU())
        self.out = nn.Sequential(nn.GELU(), nn.Linear(hidden + 16, outputs))

    def forward(self, windows):
        far = windows[..., :-NEAR]
        far = far[..., far.shape[-1] - POOL * self.chunks:].reshape(*windows.shape[:2], self.chunks, POOL).mean(-1)
        return self.out(torch.cat([self.near(windows[..., -NEAR:]), self.far(far)], 1))


def ensemble_of(net_class) -> type:
    class Ensemble(voice_net.VoiceEnsemble):
        def __init__(self, members, *args, **kwargs):
            nn.Module.__init__(self)
            self.members = nn.ModuleList(net_class(*args, **kwargs) for _ in range(members))

    return Ensemble


def main() -> None:
    lever = os.environ.get("LEVER", "")
    if lever == "mfcc20":
        cepstra(20)
    elif lever == "subframe":
        voice_train._Trainer.step = subframe_step
    elif lever == "conv2d":
        voice_model.VoiceEnsemble = ensemble_of(BandConvNet)
    elif lever == "context":
        voice_model.VoiceEnsemble = ensemble_of(ContextNet)
    elif lever:
        raise SystemExit(f"LEVER={lever}: one of mfcc20, subframe, conv2d, context (or unset: today's voice)")
    script = Path(__file__).with_name("voice_variants.py")
    sys.argv = [str(script)] + sys.argv[1:]
    runpy.run_path(str(script), run_name="__main__")


if __name__ == "__main__":
    main()
