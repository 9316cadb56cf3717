"""Per-pixel appearance of a synthetic actor: procedural albedo that sticks to the skin, and shading.

Every visible sample carries the actor's canonical (rest-pose, subject-shaped) position of the
surface point it sees, its material weights (interpolated from per-vertex one-hot labels, so the
borders between materials are soft) and its camera-space normal. The albedo is a function of the
canonical position, so pores, freckles, eyebrows, iris and hair strands move with the surface:
the iris follows the gaze because the eyeball's canonical coordinates rotate with it.

Materials (columns of the weight matrix, in this order):
    skin, lips, eyeball, teeth, gums, tongue, hair, beard, glasses
Hair and beard cover the skin beneath them by how far the sample is from the border of their shell
(an interpolated per-vertex distance), with a noisy threshold: the hairline is a smooth, irregular
curve rather than the staircase of the shell's triangle border.
Shading: Lambert from two lights fixed to the room (given in the dataset camera's axes) + ambient + a Blinn-Phong highlight whose
strength depends on the material (wet eyes and teeth shine, skin a little, hair and beard little).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from geoavatar.data.synth.noise import SolidNoise
from geoavatar.data.synth.subjects import Subject
from geoavatar.render.mesh import Lighting, shade

MATERIALS: tuple[str, ...] = ("skin", "lips", "eyeball", "teeth", "gums", "tongue", "hair", "beard", "glasses")
MATERIAL_INDEX = {name: i for i, name in enumerate(MATERIALS)}

# Highlight strength per material (Blinn-Phong, key light).
_SPECULAR = {"skin": 0.07, "lips": 0.14, "eyeball": 0.55, "teeth": 0.25, "gums": 0.12, "tongue": 0.15,
             "hair": 0.06, "beard": 0.03, "glasses": 0.45}

LIGHTING = Lighting(
    directions=((-0.5, -0.6, -1.0), (0.8, -0.1, -0.6)), intensities=(0.72, 0.28), ambient=0.28,
    specular=0.0, two_sided=True,
)
HIGHLIGHT = Lighting(directions=((-0.5, -0.6, -1.0),), intensities=(0.0,), ambient=0.0, specular=1.0,
                     shininess=40.0, two_sided=True)


@dataclass
class FaceLandmarks:
    """Canonical positions (metres, head frame) that place the procedural features."""

    eye_centres: np.ndarray  # [2, 3] left (+x) then right eyeball centre
    eye_radius: float  # eyeball radius
    mouth_centre: np.ndarray  # [3] centre of the inner lip contour
    mouth_arch_centre: np.ndarray  # [3] centre of the teeth arch (for tooth gaps)
    head_centre: np.ndarray  # [3] centre of the skull (for hair strand directions)
    nose_tip: np.ndarray  # [3]


class Appearance:
    """Albedo and shading of one subject: call `shade_samples` on the visible samples of a frame."""

    def __init__(self, subject: Subject, landmarks: FaceLandmarks):
        self.subject = subject
        self.marks = landmarks
        seed = subject.texture_seed
        self.noise_a = SolidNoise(seed * 7 + 1)
        self.noise_b = SolidNoise(seed * 7 + 2)
        self.noise_c = SolidNoise(seed * 7 + 3, smoothing=0.7)
        self._specular = torch.tensor([_SPECULAR[m] for m in MATERIALS])  # [M]

    # --- albedo per material (each on its own subset of samples) -------------------------------
    def _tensor(self, values, like: Tensor) -> Tensor:
        return torch.as_tensor(np.asarray(values, dtype=np.float32), dtype=like.dtype, device=like.device)

    def skin(self, p: Tensor) -> Tensor:
        """Skin albedo [P, 3] at canonical points p [P, 3]: tone variation, redness, pores, freckles, brows."""
        s = self.subject
        base = self._tensor(s.skin_rgb, p)
        tone = 1.0 + s.skin_variation * self.noise_a.fbm(p, 25.0, octaves=2)  # [P] blotches of ~2-4 cm
        albedo = base * tone[:, None]
        # Redness on the cheeks, the nose tip and the ears (Gaussian blobs in canonical space).
        eyes = self._tensor(self.marks.eye_centres, p)
        cheek_y = eyes[:, 1].mean() - 0.03
        red = torch.zeros_like(tone)
        for side in (0, 1):
            cheek = torch.stack([eyes[side, 0] * 1.05, cheek_y, eyes[side, 2] + 0.005])
            red = red + torch.exp(-((p - cheek) ** 2).sum(-1) / (2 * 0.018**2))
        nose = self._tensor(self.marks.nose_tip, p)
        red = red + 0.7 * torch.exp(-((p - nose) ** 2).sum(-1) / (2 * 0.012**2))
        red = (s.cheek_red * red).clamp(0.0, 1.0)
        flushed = base * self._tensor((1.05, 0.78, 0.78), p)
        albedo = albedo + red[:, None] * (flushed - base)
        # Pores and fine roughness: two octaves at 1-2 mm, a few percent.
        pores = self.noise_b.fbm(p, 700.0, octaves=2)
        albedo = albedo * (1.0 + 0.035 * pores)[:, None]
        if s.freckles > 0:
            spots = self.noise_c(p, 260.0)
            front = torch.sigmoid((p[:, 2] - (eyes[:, 2].mean() - 0.03)) / 0.005)  # face front only
            amount = s.freckles * front * torch.sigmoid((spots - 1.2) * 6.0)
            albedo = albedo * (1.0 - 0.35 * amount[:, None] * self._tensor((0.6, 0.9, 1.1), p))
        albedo = self._eyebrows(p, albedo)
        return albedo.clamp(0.0, 1.0)

    def _eyebrows(self, p: Tensor, albedo: Tensor) -> Tensor:
        """A hairy band above each eye: arched, thick at the inner end, tapering outwards."""
        eyes = self._tensor(self.marks.eye_centres, p)
        r = self.marks.eye_radius
        amount = torch.zeros(p.shape[0], dtype=p.dtype, device=p.device)
        for side in (0, 1):
            centre = eyes[side]
            sign = 1.0 if float(centre[0]) > 0 else -1.0
            along = sign * (p[:, 0] - centre[0])  # [P] + outwards
            t = ((along + 0.018) / 0.045).clamp(0.0, 1.0)  # 0 inner end .. 1 outer end
            arch = 0.02 + 0.004 * torch.sin(math.pi * t) - 0.003 * t  # height above the eye centre
            thickness = 0.0085 * (1.0 - 0.6 * t)
            dy = (p[:, 1] - centre[1] - arch).abs()
            inside = torch.sigmoid((thickness / 2 - dy) / 0.0012)
            inside = inside * torch.sigmoid((0.018 + along) / 0.002) * torch.sigmoid((0.027 - along) / 0.003)
            inside = inside * torch.sigmoid((p[:, 2] - (centre[2] - 0.2 * r)) / 0.003)  # only on the front
            amount = torch.maximum(amount, inside)
        if float(amount.max()) <= 0.0:
            return albedo
        strokes = self.noise_c(p, torch.tensor([120.0, 900.0, 600.0]))  # short strands running sideways
        density = (amount * (0.65 + 0.35 * torch.sigmoid(strokes * 2.0))).clamp(0.0, 1.0)
        brow = self._tensor(self.subject.brow_rgb, p)
        return albedo + density[:, None] * (brow - albedo)

    def lips(self, p: Tensor) -> Tensor:
        lip = self._tensor(self.subject.lip_rgb, p)
        lines = self.noise_b(p, torch.tensor([1500.0, 120.0, 400.0]))  # vertical lip lines
        tone = 1.0 + 0.05 * self.noise_a(p, 200.0) + 0.04 * lines
        return (lip * tone[:, None]).clamp(0.0, 1.0)

    def eyeball(self, p: Tensor) -> Tensor:
        """Sclera, iris (radial streaks, dark limbal ring) and pupil, around the eyeball's +z pole."""
        eyes = self._tensor(self.marks.eye_centres, p)
        side = (p[:, 0] < 0).long()  # left eye has +x
        d = F.normalize(p - eyes[side], dim=-1)  # [P, 3]
        angle = torch.acos(d[:, 2].clamp(-1.0, 1.0))  # [P] from the gaze axis
        r = self.marks.eye_radius
        iris_angle = math.asin(min(0.0058 / r, 0.95))
        pupil_angle = math.asin(min(0.0022 / r, 0.9))
        sclera = self._tensor((0.93, 0.90, 0.87), p) * (1.0 - 0.1 * (angle / math.pi))[:, None]
        sclera = sclera + (angle / math.pi).clamp(0.3, 0.6)[:, None] * self._tensor((0.0, -0.08, -0.08), p)
        azimuth = torch.atan2(d[:, 1], d[:, 0])
        streaks = self.noise_b(torch.stack([azimuth * 0.05, angle * 0.2, torch.zeros_like(angle)], -1), 400.0)
        iris = self._tensor(self.subject.iris_rgb, p) * (1.0 + 0.25 * streaks)[:, None]
        limbal = torch.sigmoid((angle - 0.8 * iris_angle) / 0.02)[:, None]
        iris = iris * (1.0 - 0.5 * limbal)
        in_iris = torch.sigmoid((iris_angle - angle) / 0.015)[:, None]
        in_pupil = torch.sigmoid((pupil_angle - angle) / 0.01)[:, None]
        colour = sclera + in_iris * (iris - sclera)
        colour = colour + in_pupil * (self._tensor((0.02, 0.02, 0.025), p) - colour)
        return colour.clamp(0.0, 1.0)

    def teeth(self, p: Tensor) -> Tensor:
        """Ivory teeth with dark gaps every ~7 mm along the arch."""
        centre = self._tensor(self.marks.mouth_arch_centre, p)
        rel = p - centre
        arc = torch.atan2(rel[:, 0], rel[:, 2]) * rel[:, [0, 2]].norm(dim=-1)  # [P] arc length along the arch
        phase = torch.frac(arc / 0.0072 + 0.5)
        gap = torch.exp(-((phase - 0.5) ** 2) / (2 * 0.05**2))  # [P]
        base = self._tensor((0.94, 0.91, 0.83), p) * (1.0 + 0.03 * self.noise_a(p, 500.0))[:, None]
        return (base * (1.0 - 0.45 * gap)[:, None]).clamp(0.0, 1.0)

    def gums(self, p: Tensor) -> Tensor:
        return (self._tensor((0.80, 0.44, 0.46), p) * (1.0 + 0.05 * self.noise_a(p, 300.0))[:, None]).clamp(0, 1)

    def tongue(self, p: Tensor) -> Tensor:
        bumps = self.noise_c(p, 900.0)
        return (self._tensor((0.76, 0.33, 0.34), p) * (1.0 + 0.07 * bumps)[:, None]).clamp(0, 1)

    def hair(self, p: Tensor, beard: bool = False) -> Tensor:
        """Hair colour with strands: fine across the strand direction, long along it; curls isotropic."""
        s = self.subject
        centre = self._tensor(self.marks.head_centre, p)
        rel = p - centre
        azimuth = torch.atan2(rel[:, 0], rel[:, 2])  # around the vertical axis
        polar = torch.acos((rel[:, 1] / rel.norm(dim=-1).clamp_min(1e-6)).clamp(-1, 1))
        radius = 0.1
        strand_coords = torch.stack([azimuth * radius, polar * radius, rel.norm(dim=-1) * 0.2], -1)
        straight = self.noise_b(strand_coords, torch.tensor([2200.0, 90.0, 50.0]))
        if beard:  # short, dense stubble: fine isotropic grain, low contrast, a little darker
            grain = self.noise_b(p, 1600.0) + 0.5 * self.noise_c(p, 700.0)
            tone = 0.85 + 0.12 * grain + 0.05 * self.noise_a(p, 60.0)
            return (self._tensor(s.hair_rgb, p) * tone[:, None]).clamp(0.0, 1.0)
        curly = self.noise_c(p, 450.0) + 0.5 * self.noise_b(p, 1100.0)
        curl = s.hair.curl
        texture = (1.0 - curl) * straight + curl * curly
        tone = 1.0 + 0.3 * texture + 0.12 * self.noise_a(p, 40.0)
        return (self._tensor(s.hair_rgb, p) * tone[:, None]).clamp(0.0, 1.0)

    def glasses(self, p: Tensor) -> Tensor:
        return self._tensor((0.05, 0.05, 0.06), p).expand(p.shape[0], 3)

    def covering(self, p: Tensor, edge: Tensor, beard: bool) -> Tensor:
        """How much hair [P] (0..1) covers the skin at distance `edge` (metres) inside the shell border."""
        start, width = (0.002, 0.005) if beard else (0.004, 0.006)
        jitter = (0.001 if beard else 0.003) * self.noise_c(p, 180.0)
        return torch.clamp((edge - start + jitter) / width, 0.0, 1.0)

    # --- the whole sample ------------------------------------------------------------------------
    def albedo(self, canonical: Tensor, weights: Tensor, edge: Tensor) -> Tensor:
        """Blend the material albedos [P, 3] by weights [P, M] (each computed where its weight > 0).

        edge [P]: distance to the hair/beard shell border (metres) for samples on a shell.
        """
        out = torch.zeros(canonical.shape[0], 3, dtype=canonical.dtype, device=canonical.device)
        total = weights.sum(-1, keepdim=True).clamp_min(1e-6)

        def covered(beard: bool):
            def func(q: Tensor, e: Tensor) -> Tensor:
                amount = self.covering(q, e, beard)[:, None]  # [P, 1]
                colour = self.hair(q, beard=beard)
                bare = torch.nonzero(amount[:, 0] < 1.0).squeeze(1)  # skin shows through here
                if bare.numel():
                    skin = self.skin(q[bare])
                    colour[bare] = skin + amount[bare] * (colour[bare] - skin)
                return colour
            return func

        functions = {
            "skin": self.skin, "lips": self.lips, "eyeball": self.eyeball, "teeth": self.teeth,
            "gums": self.gums, "tongue": self.tongue, "hair": covered(False), "beard": covered(True),
            "glasses": self.glasses,
        }
        for name, func in functions.items():
            w = weights[:, MATERIAL_INDEX[name]]
            idx = torch.nonzero(w > 1e-3).squeeze(1)
            if idx.numel() == 0:
                continue
            q = canonical[idx]
            colour = func(q, edge[idx]) if name in ("hair", "beard") else func(q)
            out.index_add_(0, idx, colour * (w[idx] / total[idx, 0])[:, None])
        return out

    def shade_samples(
        self,
        canonical: Tensor,  # [P, 3] canonical positions
        weights: Tensor,  # [P, M] material weights
        edge: Tensor,  # [P] distance to the hair/beard shell border (metres)
        normals: Tensor,  # [P, 3] camera-space normals
        view_dirs: Tensor,  # [P, 3] unit vectors surface -> camera
        back_facing: Tensor,  # [P] bool: the sample sees the inside of the surface (mouth cavity)
        occlusion: Tensor,  # [P] 0..1 ambient occlusion (mouth interior)
        highlight: bool = True,  # False: diffuse only (what a view-independent model could match; analysis)
    ) -> Tensor:
        """Shaded colour [P, 3] in [0, 1]."""
        albedo = self.albedo(canonical, weights, edge)
        colour = shade(albedo, normals, view_dirs, LIGHTING) * occlusion[:, None]
        if highlight:
            spec_strength = weights @ self._specular.to(weights) / weights.sum(-1).clamp_min(1e-6)
            shine = shade(torch.zeros_like(albedo), normals, view_dirs, HIGHLIGHT)
            colour = colour + shine * (spec_strength * occlusion)[:, None]
        # The inside of the head seen through the open mouth: a dark, reddish cavity.
        cavity = self._tensor((0.16, 0.05, 0.05), colour)
        colour = torch.where(back_facing[:, None], cavity * occlusion[:, None], colour)
        return colour.clamp(0.0, 1.0)


__all__ = ["MATERIALS", "MATERIAL_INDEX", "Appearance", "FaceLandmarks", "LIGHTING"]
