"""tacsplat.reconstruction (see DESIGN.md)."""

from tacsplat.reconstruction.rasterization import rasterization

__all__ = ["rasterization"]
