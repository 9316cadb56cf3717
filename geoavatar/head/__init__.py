"""Head models: FLAME (user-supplied) and OpenHead (generated, openly licensed), one interface.

    head = load_head_model("openhead", mouth="geoavatar")
    out = head.forward_params(head.zero_params(batch=4))   # out.vertices [4, V, 3]
"""

from __future__ import annotations

from geoavatar.head.base import JOINT_NAMES, REGION_NAMES, HeadModel, HeadModelData, HeadOutput
from geoavatar.head.params import SUBJECT_KEYS, HeadParams, npz_frame

HEAD_MODELS = ("openhead", "flame")
MOUTH_KINDS = ("geoavatar", "gaussianavatars", "none")


def load_head_data(name: str, mouth: str = "none", **options) -> HeadModelData:
    """The arrays of head model `name` ('openhead' or 'flame'), with the mouth structure `mouth`.

    options go to the model's loader (for FLAME: flame_dir=...).
    """
    if name == "openhead":
        from geoavatar.head.openhead import build_openhead

        data = build_openhead(**options)
    elif name == "flame":
        from geoavatar.head.flame import load_flame

        data = load_flame(**options)
    else:
        raise ValueError(f"unknown head model '{name}'; choose one of {', '.join(HEAD_MODELS)}")
    if mouth not in MOUTH_KINDS:
        raise ValueError(f"unknown mouth structure '{mouth}'; choose one of {', '.join(MOUTH_KINDS)}")
    if mouth != "none":
        from geoavatar.head.mouth import add_mouth_structure

        data = add_mouth_structure(data, kind=mouth)
    return data


def load_head_model(name: str, mouth: str = "none", **options) -> HeadModel:
    """A ready HeadModel (torch module on CPU; move it with .to(device))."""
    return HeadModel(load_head_data(name, mouth=mouth, **options))


__all__ = [
    "HEAD_MODELS", "MOUTH_KINDS", "JOINT_NAMES", "REGION_NAMES", "HeadModel", "HeadModelData", "HeadOutput",
    "HeadParams", "SUBJECT_KEYS", "npz_frame",
    "load_head_data", "load_head_model",
]
