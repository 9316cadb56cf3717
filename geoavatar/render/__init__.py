"""Renderer layer: differentiable Gaussian splatting (`rasterize`, backends "torch" and "gsplat")."""

from geoavatar.render.camera import Camera
from geoavatar.render.composite import composite_target
from geoavatar.render.rasterize import RasterizeResult, rasterize

__all__ = ["Camera", "RasterizeResult", "composite_target", "rasterize"]
