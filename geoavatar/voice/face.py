"""The face a voice moves, measured on the head model: lip and upper-face vertices, the lips' opening, and the linear
map from the voice model's outputs to them.

    probe = FaceProbe(head, identity)                     # the avatar's head model and its shape / static offset
    probe.lips(expr, jaw) -> [B, K, 3]                    # lip vertices in the head's own frame (no head pose), metres
    probe.upper(expr, jaw) -> [B, U, 3]                   # forehead and eye-region vertices (FaceFormer's upper face)
    probe.opening(expr, jaw) -> [B]                       # mean gap between the inner lip rings' middle points, metres

Everything is in the head's canonical frame (rotation, neck, translation and eyes at zero): what speech changes, as
the field's metrics (VOCA / FaceFormer: registered meshes) measure it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

LIP_REGIONS = ("lips",)
UPPER_REGIONS = ("forehead", "eye_region", "left_eye_region", "right_eye_region")
RING_MIDDLE = slice(5, 10)  # the middle 5 of the inner lip rings' 15 points: the opening, not the corners


def _region_ids(head, names: tuple[str, ...]) -> np.ndarray:
    regions = head.data.regions
    ids = [np.asarray(regions[name]) for name in names if name in regions]
    if not ids:
        raise ValueError(f"head model '{head.data.name}' has none of the regions {names}")
    return np.unique(np.concatenate(ids))


class FaceProbe:
    """Canonical lip / upper-face vertices of a head with a fixed identity, batched over frames."""

    def __init__(self, head, identity: dict[str, Tensor]):
        self.head = head
        self.shape = identity["shape"].reshape(-1).float().cpu()  # [S]
        offset = identity.get("static_offset")
        self.static_offset = None if offset is None else offset.reshape(1, -1, 3).float().cpu()
        data = head.data
        self.lip_ids = torch.as_tensor(_region_ids(head, LIP_REGIONS), dtype=torch.long)
        self.upper_ids = torch.as_tensor(_region_ids(head, UPPER_REGIONS), dtype=torch.long)
        if data.lip_ring_upper is None or data.lip_ring_lower is None:
            raise ValueError(f"head model '{data.name}' has no inner lip rings")
        self.ring_upper = torch.as_tensor(np.asarray(data.lip_ring_upper)[RING_MIDDLE], dtype=torch.long)
        self.ring_lower = torch.as_tensor(np.asarray(data.lip_ring_lower)[RING_MIDDLE], dtype=torch.long)
        self.num_expr = int(head.num_expr)

    def vertices(self, expr: Tensor, jaw: Tensor, ids: Tensor) -> Tensor:
        """[B, K, 3] the vertices `ids` for expressions [B, E'] and jaw rotations [B, 3] (head pose at zero)."""
        batch = expr.shape[0]
        zeros3 = expr.new_zeros(batch, 3)
        offset = None if self.static_offset is None else self.static_offset.to(expr.device)
        return self.head.forward(self.shape.to(expr.device), expr[:, :self.num_expr], zeros3, zeros3, jaw,
                                 expr.new_zeros(batch, 6), zeros3, offset, vertex_ids=ids.to(expr.device)).vertices

    def lips(self, expr: Tensor, jaw: Tensor) -> Tensor:
        return self.vertices(expr, jaw, self.lip_ids)

    def upper(self, expr: Tensor, jaw: Tensor) -> Tensor:
        return self.vertices(expr, jaw, self.upper_ids)

    def opening(self, expr: Tensor, jaw: Tensor) -> Tensor:
        """[B] the lips' opening: mean distance between the middle points of the upper and lower inner rings."""
        ring = self.vertices(expr, jaw, torch.cat([self.ring_upper, self.ring_lower]))  # [B, 10, 3]
        half = len(self.ring_upper)
        return (ring[:, :half] - ring[:, half:]).norm(dim=-1).mean(dim=-1)


__all__ = ["FaceProbe", "LIP_REGIONS", "UPPER_REGIONS"]
