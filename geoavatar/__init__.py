"""GeoAvatar: adaptive geometrical Gaussian splatting for 3D head avatars (ICCV 2025).

Layers, bottom to top (see docs/ARCHITECTURE.md):
head -> avatar -> render -> train -> eval/apps, with data and prep feeding the trainer.
"""

__version__ = "0.1.0"
