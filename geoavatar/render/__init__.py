"""Renderer layer: differentiable Gaussian splatting (`rasterize`, backends "torch" and "gsplat")."""

from geoavatar.render.rasterize import RasterizeResult, rasterize

__all__ = ["RasterizeResult", "rasterize"]
