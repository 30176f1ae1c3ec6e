"""Image-quality metrics used to compare a representation with the measured BTF.

Conventions (as in the BTF compression literature and the paper):

* :func:`psnr` -- on **linear** values, against the **reference image's own peak** (its
  maximum over texels and channels): "PSNR (per-image peak)". BTF values are reflectance
  factors whose range depends on the material (about 0-0.25 on a matte gravel, up to ~11 on
  glossy lacquer), so a fixed peak adds decibels to dark materials and takes them from glossy
  ones; the per-image peak makes numbers comparable across materials, and scaling a pair of
  images by a constant leaves it unchanged. :func:`psnr_fixed_range` is the older form with a
  fixed peak (``data_range``, 1.0: a white Lambertian surface), "PSNR (fixed peak 1)".
* :func:`dssim` ``= (1 - SSIM) / 2`` and :func:`flip` -- on **clamped,
  sRGB-encoded** images (what a viewer sees), computed from linear inputs here.

All functions take linear RGB images ``(H, W, 3)`` (NumPy arrays or anything
``np.asarray`` accepts) and validate them: a wrong shape, mismatched sizes or
non-finite values raise :class:`dynbtf.errors.InputError` naming the argument.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..io import linear_to_srgb

__all__ = ["psnr", "psnr_fixed_range", "PSNR_LABEL", "PSNR_FIXED_LABEL", "dssim", "flip", "flip_map", "flip_magma",
           "check_image_pair"]

#: How outputs name the two PSNR forms.
PSNR_LABEL = "PSNR (dB, per-image peak)"
PSNR_FIXED_LABEL = "PSNR (dB, fixed peak 1)"


def check_image_pair(reference, test) -> tuple[np.ndarray, np.ndarray]:
    """Validate two linear RGB images; return them as float32 ``(H, W, 3)`` arrays."""
    out = []
    for name, img in (("reference", reference), ("test", test)):
        arr = np.asarray(img)
        if not np.issubdtype(arr.dtype, np.floating):
            raise InputError(f"{name}: expected linear float values, got dtype {arr.dtype} (decode 8-bit sRGB "
                             "images with dynbtf.io.srgb_to_linear(x / 255) first)")
        arr = arr.astype(np.float32, copy=False)
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise InputError(f"{name}: expected a linear RGB image of shape (H, W, 3), got shape {arr.shape}")
        if not np.isfinite(arr).all():
            raise InputError(f"{name}: contains NaN or infinite values")
        out.append(arr)
    if out[0].shape != out[1].shape:
        raise InputError(f"reference and test images differ in shape: {out[0].shape} vs {out[1].shape}")
    return out[0], out[1]


def psnr(reference, test) -> float:
    """PSNR in dB on linear values against the reference's peak: ``10 log10(max(reference)^2 / MSE)``.

    The peak is the reference image's maximum over all texels and channels, so the value is
    unchanged when both images are scaled by the same constant. Identical images give ``inf``;
    an all-black (or negative) reference has no peak and gives ``nan``.

    >>> import numpy as np
    >>> ref = np.full((2, 2, 3), 0.5)
    >>> round(psnr(ref, ref + 0.05), 3)  # 10 log10(0.5^2 / 0.05^2)
    20.0
    >>> round(psnr(4 * ref, 4 * (ref + 0.05)), 3)
    20.0
    """
    ref, tst = check_image_pair(reference, test)
    peak = float(ref.max())
    mse = float(np.mean((ref.astype(np.float64) - tst.astype(np.float64)) ** 2))
    if mse == 0.0:
        return float("inf")
    if peak <= 0.0:
        return float("nan")
    return float(10.0 * np.log10(peak ** 2 / mse))


def psnr_fixed_range(reference, test, *, data_range: float = 1.0) -> float:
    """PSNR in dB on linear values with a fixed peak: ``10 log10(data_range^2 / MSE)`` ("fixed peak 1").

    The form dynbtf reported before per-image peaks; it depends on the material's brightness.

    >>> import numpy as np
    >>> round(psnr_fixed_range(np.zeros((2, 2, 3)), np.full((2, 2, 3), 0.1)), 6)
    20.0
    """
    if not (np.isfinite(data_range) and data_range > 0):
        raise InputError(f"data_range: expected a positive peak value, got {data_range!r}")
    ref, tst = check_image_pair(reference, test)
    mse = float(np.mean((ref.astype(np.float64) - tst.astype(np.float64)) ** 2))
    if mse == 0.0:
        return float("inf")
    return float(10.0 * np.log10(data_range ** 2 / mse))


def dssim(reference, test) -> float:
    """Structural dissimilarity ``(1 - SSIM) / 2`` of the clamped sRGB-encoded images.

    SSIM is scikit-image's ``structural_similarity`` (7x7 uniform window,
    ``data_range=1``, averaged over the three channels). 0 for identical images,
    at most 1. Images smaller than 7x7 use the largest odd window that fits.
    """
    from skimage.metrics import structural_similarity

    ref, tst = check_image_pair(reference, test)
    win = min(7, ref.shape[0], ref.shape[1])
    win -= 1 - win % 2
    if win < 3:
        raise InputError(f"dssim: images must be at least 3x3 texels, got {ref.shape[:2]}")
    ssim = structural_similarity(linear_to_srgb(ref), linear_to_srgb(tst), channel_axis=-1, data_range=1.0,
                                 win_size=win)
    return float((1.0 - ssim) / 2.0)


def flip_map(reference, test) -> tuple[np.ndarray, float]:
    """NVIDIA FLIP (LDR) of the clamped sRGB-encoded images: ``(error map (H, W) in [0, 1], mean)``.

    The map is the raw per-pixel error (no colour map applied; :func:`flip_magma` gives FLIP's display). Uses the ``flip-evaluator`` package, which silently misreads uint8 or
    channels-first input; this function always passes it contiguous float32
    ``(H, W, 3)`` sRGB values in ``[0, 1]``.
    """
    import flip_evaluator

    ref, tst = check_image_pair(reference, test)
    ref_srgb = np.ascontiguousarray(linear_to_srgb(ref), dtype=np.float32)
    tst_srgb = np.ascontiguousarray(linear_to_srgb(tst), dtype=np.float32)
    error_map, mean, _ = flip_evaluator.evaluate(ref_srgb, tst_srgb, "LDR", inputsRGB=True, applyMagma=False)
    error_map = np.asarray(error_map, dtype=np.float32)
    if error_map.ndim == 3:
        error_map = error_map[..., 0]
    return error_map, float(mean)


def flip_magma(reference, test) -> np.ndarray:
    """FLIP's display of the error map: its magma colour map, ``(H, W, 3)`` sRGB values in ``[0, 1]``
    (black: no error; light yellow: error 1), as ``flip-evaluator`` draws it."""
    import flip_evaluator

    ref, tst = check_image_pair(reference, test)
    ref_srgb = np.ascontiguousarray(linear_to_srgb(ref), dtype=np.float32)
    tst_srgb = np.ascontiguousarray(linear_to_srgb(tst), dtype=np.float32)
    display, _, _ = flip_evaluator.evaluate(ref_srgb, tst_srgb, "LDR", inputsRGB=True, applyMagma=True)
    return np.clip(np.asarray(display, dtype=np.float32), 0.0, 1.0)


def flip(reference, test) -> float:
    """Mean NVIDIA FLIP error (LDR, on clamped sRGB) in ``[0, 1]``; 0 for identical images."""
    return flip_map(reference, test)[1]
