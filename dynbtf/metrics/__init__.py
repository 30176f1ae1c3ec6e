"""Image-quality metrics: PSNR (linear), DSSIM and FLIP (clamped sRGB).

See :mod:`dynbtf.metrics.image_metrics`.
"""

from .image_metrics import check_image_pair, dssim, flip, flip_map, psnr

__all__ = ["psnr", "dssim", "flip", "flip_map", "check_image_pair"]
