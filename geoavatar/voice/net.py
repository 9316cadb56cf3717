"""The voice network: a window of normalised log-mel frames around a video frame -> that frame's face (standardised).

A small 1-D convolution over time (the mel bands as channels), as Karras et al. 2017's formant analysis network
does over its autocorrelation features, then two dense layers. It sees `past` frames before the video frame and
`ahead` after (the look-ahead that a live microphone waits for), nothing else: offline and live give the same output.

VoiceEnsemble holds a few such networks, started from different weights and trained side by side on the same
batches, each blind to its own validation block of them (voice/train.py); their outputs are averaged. On french.mp4's
validation frames (the last tenth of the training frames) three members' average lifted the lips' opening
correlation from 0.69-0.78 (single networks over the settings and seeds tried) to 0.80 (docs/speech.md).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


class VoiceNet(nn.Module):
    def __init__(self, bands: int, frames: int, outputs: int, width: int = 64, hidden: int = 128,
                 dropout: float = 0.2):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv1d(bands, width, 3, padding=1), nn.GELU()]
        length = frames
        for _ in range(3):  # halve the time axis three times: 31 -> 16 -> 8 -> 4 frames (0.2 s + 0.1 s)
            layers += [nn.Conv1d(width, width, 3, stride=2, padding=1), nn.GELU()]
            length = (length + 1) // 2
        self.conv = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), nn.Dropout(dropout), nn.Linear(width * length, hidden), nn.GELU(),
                                  nn.Linear(hidden, outputs))

    def forward(self, windows: Tensor) -> Tensor:
        """[N, bands, frames] -> [N, outputs]."""
        return self.head(self.conv(windows))


class VoiceEnsemble(nn.Module):
    """`members` VoiceNets; forward gives each member's outputs [K, N, outputs], predict their mean [N, outputs]."""

    def __init__(self, members: int, *args, **kwargs):
        super().__init__()
        self.members = nn.ModuleList(VoiceNet(*args, **kwargs) for _ in range(members))

    def forward(self, windows: Tensor) -> Tensor:
        return torch.stack([member(windows) for member in self.members])

    def predict(self, windows: Tensor) -> Tensor:
        return self(windows).mean(dim=0)


def state_arrays(net: nn.Module) -> dict[str, "object"]:
    """The network's parameters as numpy arrays (saved in an npz: loaded without unpickling anything)."""
    return {f"net.{k}": v.detach().cpu().numpy() for k, v in net.state_dict().items()}


def load_state_arrays(net: nn.Module, arrays: dict) -> None:
    state = {k[len("net."):]: torch.from_numpy(arrays[k]) for k in arrays if k.startswith("net.")}
    net.load_state_dict(state)


__all__ = ["VoiceEnsemble", "VoiceNet", "load_state_arrays", "state_arrays"]
