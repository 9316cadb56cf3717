"""File formats of the field that GeoAvatar writes and reads (the standard 3DGS PLY)."""

from geoavatar.io.ply import GaussianPly, PLY_PROPERTIES, read_gaussian_ply, write_gaussian_ply

__all__ = ["GaussianPly", "PLY_PROPERTIES", "read_gaussian_ply", "write_gaussian_ply"]
