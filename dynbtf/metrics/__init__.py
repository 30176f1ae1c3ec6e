"""Image-quality metrics: PSNR (linear; per-image peak, or a fixed peak), DSSIM and FLIP (clamped sRGB).

See :mod:`dynbtf.metrics.image_metrics`.
"""

from .image_metrics import (PSNR_FIXED_LABEL, PSNR_LABEL, check_image_pair, dssim, flip, flip_magma, flip_map, psnr,
                            psnr_fixed_range)

__all__ = ["psnr", "psnr_fixed_range", "PSNR_LABEL", "PSNR_FIXED_LABEL", "dssim", "flip", "flip_map", "flip_magma",
           "check_image_pair"]
