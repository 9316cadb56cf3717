"""Synthetic subjects with known ground truth: the project's embedded default dataset.

    from geoavatar.data.synth import SynthConfig, generate_dataset
    generate_dataset(Path("data/synth0"), SynthConfig(subject=0, frames=300, size=512, seed=0))

A ground-truth actor (OpenHead with a subject's identity, plus hair volume, changed ears, glasses or
a beard that the head model cannot express) performs a DynamicFace-like motion script, is rendered
with the mesh rasterizer, and is written in the VHAP / GaussianAvatars layout with tracker-like
parameter error (the exact ground truth beside it). Modules:

    subjects.py    the three actors (skin, hair, eyes, ears, accessories)
    actor.py       the rigged actor geometry (hair/beard shells, ears, glasses)
    appearance.py  per-pixel procedural albedo (canonical-space textures) and shading
    noise.py       solid noise for those textures
    motion.py      the motion script (talking, held expressions with head turns, blinks, gaze; novel test part)
    tracking.py    the tracker error model
    render.py      cameras and the frame renderer
    generate.py    the dataset generator and its preview contact sheet
"""

from geoavatar.data.synth.generate import SynthConfig, generate_dataset, is_synth_dataset
from geoavatar.data.synth.motion import Motion, script_motion, held_out_frame_count
from geoavatar.data.synth.subjects import NUM_SUBJECTS, SUBJECTS, get_subject
from geoavatar.data.synth.tracking import TrackingNoise, apply_tracking_noise

__all__ = [
    "NUM_SUBJECTS", "SUBJECTS", "Motion", "SynthConfig", "TrackingNoise", "apply_tracking_noise",
    "generate_dataset", "get_subject", "is_synth_dataset", "script_motion", "held_out_frame_count",
]
