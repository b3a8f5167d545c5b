"""tacsplat.reconstruction: Gaussians, the rasterizer (:mod:`.raster`), losses, the trainer, evaluation.

Importing the package loads nothing heavy; torch comes with the modules that need it.
"""
