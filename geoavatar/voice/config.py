"""The voice model's settings, with the defaults `geoavatar train` uses (measured on french.mp4: docs/speech.md)."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class VoiceConfig:
    # seconds of sound before a video frame that the model hears: on french.mp4's held-out frames (two preparations,
    # three seeds each) 0.2 s gave a lip-opening r of 0.67-0.69, 0.3 s 0.61-0.72, 0.5 s 0.54-0.60: a longer window
    # overfits 40 s of speech (docs/speech.md)
    past: float = 0.20
    ahead: float = 0.10  # seconds after it: the look-ahead, which a live microphone waits for
    width: int = 48  # channels of the convolutions
    hidden: int = 128  # units of the dense layer
    dropout: float = 0.4
    members: int = 3  # networks averaged (net.VoiceEnsemble): trained side by side from different initial weights
    steps: int = 1000  # optimisation steps, each with a new recording condition
    batch: int = 128  # frames per step, in runs of `run_length` consecutive frames
    run_length: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-3
    velocity_weight: float = 1.0  # how much the frame-to-frame change counts beside the frame itself
    upper_weight: float = 0.5  # upper-face vertices against lip vertices in the loss
    augment: float = 0.8  # share of steps with a random recording condition (inputs.Augmentation)
    # the share of the training frames that chooses the step kept: each member of the ensemble holds out its own
    # block of it (member k's ends at (k + 1) / members of the frames, in time) and learns from the rest, so the
    # ensemble learns from every frame; on french.mp4 held-out r 0.68 -> 0.72 and LVE -8 % against one shared last
    # block (three seeds, docs/speech.md)
    validation: float = 0.1
    validate_every: int = 50
    max_minutes: float = 3.0  # a wall-clock cap on the training (the steps normally end first)
    threads: int = 1  # small tensors: on a busy 2-core machine a second thread made every step several times slower
    seed: int = 0

    def validate(self) -> None:
        if self.past < 0 or self.ahead < 0 or self.past + self.ahead <= 0:
            raise ValueError(f"past {self.past} and ahead {self.ahead}: the model must hear some sound")
        for name in ("width", "hidden", "members", "steps", "batch", "run_length", "threads", "validate_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.validation < 0.5:
            raise ValueError(f"validation must be in [0, 0.5), got {self.validation}")

    def to_dict(self) -> dict:
        return asdict(self)


__all__ = ["VoiceConfig"]
