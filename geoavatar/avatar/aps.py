"""Adaptive Pre-allocation Stage (paper Sec. 3.1) and the per-face regulariser sets.

Until step N every non-mouth face is rigid. At N, per part k:
    Distance(k) = mean over the faces of part k of (mean |mu| of that face's Gaussians)
    tau_part    = mean over parts of Distance(k)
and the parts with Distance(k) > tau_part become flexible (ties stay rigid). Distances are in the
local face-scale units of the means. Parts without faces are left out of tau_part and stay rigid.

The partition comes from `geoavatar.head.regions.face_parts(data)`: part_of_face [F], -1 for the
mouth structure F_m. Each face gets one set id: RIGID, FLEXIBLE, MOUTH, or BASELINE (GaussianAvatars'
single position threshold, for preset A), which `geoavatar.train.losses` maps to its threshold.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

RIGID, FLEXIBLE, MOUTH, BASELINE = 0, 1, 2, 3
SET_NAMES = ("rigid", "flexible", "mouth", "gaussianavatars")
FACE_SET_MODES = ("aps", "rigid", "flexible", "gaussianavatars")


def part_distances(
    local_means: Tensor,  # [N, 3]
    binding: Tensor,  # [N] face ids
    part_of_face: Tensor,  # [F] part ids, -1 = mouth (ignored)
    num_parts: int,
) -> Tensor:
    """Distance(k) for every part: [num_parts], NaN for a part with no face holding a Gaussian."""
    part_of_face = torch.as_tensor(part_of_face, device=local_means.device).long()
    binding = binding.to(local_means.device).long()
    num_faces = part_of_face.shape[0]
    if binding.numel() and int(binding.max()) >= num_faces:
        raise ValueError(f"part_distances: binding refers to face {int(binding.max())}, part_of_face has {num_faces}")
    r = torch.linalg.vector_norm(local_means.detach(), dim=-1)  # [N]
    per_face_sum = torch.zeros(num_faces, dtype=r.dtype, device=r.device).index_add_(0, binding, r)
    per_face_count = torch.bincount(binding, minlength=num_faces).to(r.dtype)
    has_gaussians = (per_face_count > 0) & (part_of_face >= 0)
    face_mean = per_face_sum / per_face_count.clamp_min(1)  # [F]
    faces = torch.nonzero(has_gaussians).squeeze(-1)
    parts = part_of_face[faces]
    if parts.numel() and int(parts.max()) >= num_parts:
        raise ValueError(f"part_distances: part id {int(parts.max())} >= num_parts {num_parts}")
    sums = torch.zeros(num_parts, dtype=r.dtype, device=r.device).index_add_(0, parts, face_mean[faces])
    counts = torch.bincount(parts, minlength=num_parts).to(r.dtype)
    return torch.where(counts > 0, sums / counts.clamp_min(1), torch.full_like(sums, float("nan")))


def assign_parts(
    local_means: Tensor, binding: Tensor, part_of_face: Tensor, num_parts: int
) -> tuple[Tensor, Tensor, float]:
    """APS: (flexible [num_parts] bool, Distance [num_parts], tau_part)."""
    distances = part_distances(local_means, binding, part_of_face, num_parts)
    valid = ~torch.isnan(distances)
    if not bool(valid.any()):
        raise ValueError("assign_parts: no part has any face with Gaussians")
    threshold = float(distances[valid].mean())
    flexible = valid & (distances > threshold)
    return flexible, distances, threshold


def face_set_ids(part_of_face: Tensor | np.ndarray, mode: str, flexible_parts: Tensor | None = None,
                 mouth_set: bool = False) -> Tensor:
    """The regulariser set of every face: [F] int64 of RIGID / FLEXIBLE / MOUTH / BASELINE.

    mode "aps": mouth faces MOUTH, other faces RIGID, or FLEXIBLE when their part is in
    flexible_parts [num_parts] (None before the APS step); "rigid" / "flexible": every face, and the
    mouth faces too unless `mouth_set`, which keeps them MOUTH (tau_mouth): GeoAvatar's F_m comes with
    its mouth structure, not with APS, so the paper's H / I ("mouth modification" added to F / G; I is
    Table 7's "Ours w/o APS") keep tau_m = tau_r on it while F / G, with GaussianAvatars' teeth, treat
    every Gaussian alike; "gaussianavatars": BASELINE.
    """
    part_of_face = torch.as_tensor(part_of_face).long()
    if mode == "aps":
        sets = torch.full_like(part_of_face, RIGID)
        if flexible_parts is not None:
            flexible_parts = torch.as_tensor(flexible_parts, device=part_of_face.device).bool()
            body = part_of_face >= 0
            if body.any() and int(part_of_face[body].max()) >= flexible_parts.shape[0]:
                raise ValueError("face_set_ids: part_of_face has more parts than flexible_parts")
            is_flexible = torch.zeros_like(body)
            is_flexible[body] = flexible_parts[part_of_face[body]]
            sets[is_flexible] = FLEXIBLE
        sets[part_of_face < 0] = MOUTH
        return sets
    fill = {"rigid": RIGID, "flexible": FLEXIBLE, "gaussianavatars": BASELINE}.get(mode)
    if fill is None:
        raise ValueError(f"face_set_ids: unknown face-set mode '{mode}'; choose one of {', '.join(FACE_SET_MODES)}")
    sets = torch.full_like(part_of_face, fill)
    if mouth_set and mode != "gaussianavatars":
        sets[part_of_face < 0] = MOUTH
    return sets


@dataclass
class APSState:
    """What APS decided, as plain values (JSON-able for checkpoints and reports)."""

    part_names: list[str]
    done: bool = False
    step: int | None = None  # the step APS ran at
    distances: list[float] = field(default_factory=list)  # Distance(k); NaN for empty parts
    threshold: float | None = None  # tau_part
    flexible: list[bool] = field(default_factory=list)

    def run(self, local_means: Tensor, binding: Tensor, part_of_face: Tensor, step: int) -> "APSState":
        """Run APS now and record the decision (returns self)."""
        flexible, distances, threshold = assign_parts(local_means, binding, part_of_face, len(self.part_names))
        self.done, self.step, self.threshold = True, int(step), threshold
        self.distances = [float(d) for d in distances.cpu()]
        self.flexible = [bool(f) for f in flexible.cpu()]
        return self

    def flexible_parts(self) -> Tensor | None:
        """[num_parts] bool once APS ran, else None (everything rigid)."""
        return torch.tensor(self.flexible, dtype=torch.bool) if self.done else None

    def face_sets(self, part_of_face: Tensor | np.ndarray, mode: str = "aps", mouth_set: bool = False) -> Tensor:
        return face_set_ids(part_of_face, mode, self.flexible_parts() if mode == "aps" else None, mouth_set)

    def to_dict(self) -> dict:
        return {"part_names": list(self.part_names), "done": self.done, "step": self.step,
                "distances": list(self.distances), "threshold": self.threshold, "flexible": list(self.flexible)}

    @classmethod
    def from_dict(cls, data: dict) -> "APSState":
        try:
            state = cls(
                part_names=[str(n) for n in data["part_names"]], done=bool(data["done"]),
                step=None if data.get("step") is None else int(data["step"]),
                distances=[float(d) for d in data.get("distances", [])],
                threshold=None if data.get("threshold") is None else float(data["threshold"]),
                flexible=[bool(f) for f in data.get("flexible", [])],
            )
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"APS state in checkpoint is malformed: {error}") from error
        if state.done and not (len(state.distances) == len(state.flexible) == len(state.part_names)):
            raise ValueError("APS state in checkpoint is malformed: part_names, distances and flexible differ in length")
        return state

    def report(self) -> str:
        """A short text table: each part, its Distance and the set it went to."""
        if not self.done:
            return "APS: not run yet (every non-mouth face is rigid)"
        lines = [f"APS at step {self.step}: tau_part = {self.threshold:.4f}",
                 f"  {'part':<14} {'Distance':>9}  set"]
        for name, dist, flex in zip(self.part_names, self.distances, self.flexible):
            shown = "      n/a" if np.isnan(dist) else f"{dist:9.4f}"
            lines.append(f"  {name:<14} {shown}  {'flexible' if flex else 'rigid'}")
        return "\n".join(lines)
