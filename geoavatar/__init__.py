"""GeoAvatar: adaptive geometrical Gaussian splatting for 3D head avatars (ICCV 2025).

Layers, bottom to top (docs/ARCHITECTURE.md; pyproject.toml's import-linter contract checks them):
errors -> config, imaging, io, geometry, native, runtime -> head -> render -> avatar -> data
-> train | prep | web -> eval -> apps -> cli.
"""

__version__ = "0.1.0"
