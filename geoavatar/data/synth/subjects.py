"""The synthetic actors: what makes subject 0, 1 and 2 different people.

A subject is fixed by its index alone (the same person whatever `--seed`; the seed drives the
motion and the tracker error). Each one differs from the others in identity (shape coefficients),
skin tone, eye colour, hair colour and style (volume standing 1-3 cm off the scalp), ear shape, and
accessories (glasses or a beard), so that some of its parts need large offsets from the head model
(flexible: hair, ears, glasses frame, beard) and others none (rigid: forehead, nose, cheeks).

    subject 0  medium skin, dark-brown straight hair with a side part (1.2-2.6 cm), brown eyes,
               protruding ears (scaled x1.15, turned out 18 deg), no accessories
    subject 1  dark skin, black curly hair with big volume (2.0-3.0 cm), dark-brown eyes,
               small close-set ears (x0.88, turned back 8 deg), thin dark glasses
    subject 2  light freckled skin, auburn hair (1.3-2.4 cm), green-blue eyes,
               ears set lower and further back (x1.05, 6 mm down), a short beard on the jaw and chin
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geoavatar.errors import OptionError

NUM_SUBJECTS = 3


@dataclass(frozen=True)
class HairStyle:
    min_cm: float  # volume at the hairline edge of the shell (after the taper), cm off the scalp
    max_cm: float  # volume on the crown / back, cm off the scalp
    curl: float  # 0 straight strands .. 1 tight curls (texture and lumpy volume)
    lumpiness: float  # relative amplitude of low-frequency volume variation
    part_x: float | None  # x (metres, head frame) of a side parting line, or None
    hairline_drop_cm: float  # how far the hair reaches below the scalp region's front edge


@dataclass(frozen=True)
class EarChange:
    scale: float  # uniform scale about the ear's centre
    turn_out_deg: float  # rotation about the vertical axis at the ear root (+ = protrude)
    shift_cm: tuple[float, float, float]  # translation (x mirrored per side), cm


@dataclass(frozen=True)
class Subject:
    index: int
    description: str
    shape_seed: int
    shape_scale: float  # std of the identity coefficients drawn for this subject
    skin_rgb: tuple[float, float, float]  # base albedo (linear-ish sRGB 0..1)
    skin_variation: float  # low-frequency tone variation amplitude
    cheek_red: float  # redness on cheeks, nose, ears
    freckles: float  # density 0..1
    lip_rgb: tuple[float, float, float]
    brow_rgb: tuple[float, float, float]
    iris_rgb: tuple[float, float, float]
    hair_rgb: tuple[float, float, float]
    hair: HairStyle
    ears: EarChange
    glasses: bool
    beard: bool
    background_rgb: tuple[float, float, float]  # plain background (multiples of 1/255: exact in 8-bit images)
    texture_seed: int = 0
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """What the dataset's geoavatar.json records about the actor."""
        return {
            "index": self.index,
            "description": self.description,
            "skin_rgb": list(self.skin_rgb),
            "hair_rgb": list(self.hair_rgb),
            "iris_rgb": list(self.iris_rgb),
            "hair_volume_cm": [self.hair.min_cm, self.hair.max_cm],
            "hair_curl": self.hair.curl,
            "ears": {"scale": self.ears.scale, "turn_out_deg": self.ears.turn_out_deg,
                     "shift_cm": list(self.ears.shift_cm)},
            "glasses": self.glasses,
            "beard": self.beard,
            "background_rgb": list(self.background_rgb),
        }


def _u8(r: int, g: int, b: int) -> tuple[float, float, float]:
    return (r / 255.0, g / 255.0, b / 255.0)


SUBJECTS: tuple[Subject, ...] = (
    Subject(
        index=0,
        description="medium skin, dark-brown straight hair with a side part, brown eyes, protruding ears",
        shape_seed=101, shape_scale=0.8,
        skin_rgb=(0.78, 0.58, 0.46), skin_variation=0.05, cheek_red=0.35, freckles=0.0,
        lip_rgb=(0.70, 0.36, 0.36), brow_rgb=(0.17, 0.11, 0.07), iris_rgb=(0.36, 0.22, 0.10),
        hair_rgb=(0.20, 0.13, 0.08),
        hair=HairStyle(min_cm=1.2, max_cm=2.6, curl=0.0, lumpiness=0.15, part_x=0.025, hairline_drop_cm=0.6),
        ears=EarChange(scale=1.15, turn_out_deg=18.0, shift_cm=(0.0, 0.0, 0.0)),
        glasses=False, beard=False,
        background_rgb=_u8(140, 150, 161), texture_seed=11,
    ),
    Subject(
        index=1,
        description="dark skin, black curly hair with big volume, dark-brown eyes, small ears, glasses",
        shape_seed=202, shape_scale=0.9,
        skin_rgb=(0.42, 0.27, 0.19), skin_variation=0.06, cheek_red=0.12, freckles=0.0,
        lip_rgb=(0.36, 0.19, 0.18), brow_rgb=(0.06, 0.04, 0.03), iris_rgb=(0.20, 0.11, 0.05),
        hair_rgb=(0.05, 0.04, 0.035),
        hair=HairStyle(min_cm=2.0, max_cm=3.0, curl=1.0, lumpiness=0.35, part_x=None, hairline_drop_cm=0.3),
        ears=EarChange(scale=0.88, turn_out_deg=-8.0, shift_cm=(0.0, 0.3, 0.0)),
        glasses=True, beard=False,
        background_rgb=_u8(192, 182, 162), texture_seed=22,
    ),
    Subject(
        index=2,
        description="light freckled skin, auburn hair, green-blue eyes, low-set ears, short beard",
        shape_seed=303, shape_scale=0.8,
        skin_rgb=(0.90, 0.72, 0.62), skin_variation=0.05, cheek_red=0.5, freckles=0.6,
        lip_rgb=(0.78, 0.42, 0.42), brow_rgb=(0.42, 0.20, 0.10), iris_rgb=(0.22, 0.42, 0.40),
        hair_rgb=(0.50, 0.22, 0.09),
        hair=HairStyle(min_cm=1.3, max_cm=2.4, curl=0.3, lumpiness=0.2, part_x=-0.02, hairline_drop_cm=0.4),
        ears=EarChange(scale=1.05, turn_out_deg=6.0, shift_cm=(0.0, -0.6, -0.4)),
        glasses=False, beard=True,
        background_rgb=_u8(104, 136, 118), texture_seed=33,
    ),
)


def get_subject(index: int) -> Subject:
    """Subject `index` (0..NUM_SUBJECTS-1); OptionError naming --subject otherwise."""
    if not isinstance(index, (int, np.integer)) or not 0 <= int(index) < NUM_SUBJECTS:
        raise OptionError(f"--subject must be an integer in 0..{NUM_SUBJECTS - 1}, got {index!r}")
    return SUBJECTS[int(index)]


def identity_coefficients(subject: Subject, num_shape: int) -> np.ndarray:
    """The subject's identity (shape) coefficients [num_shape]: leading modes larger, as PCA spectra."""
    rng = np.random.default_rng([subject.shape_seed, 0x1D])
    falloff = 1.0 / np.sqrt(1.0 + np.arange(num_shape) / 4.0)
    return (subject.shape_scale * falloff * rng.standard_normal(num_shape)).astype(np.float32)


__all__ = ["NUM_SUBJECTS", "SUBJECTS", "Subject", "HairStyle", "EarChange", "get_subject", "identity_coefficients"]
