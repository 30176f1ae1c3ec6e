"""Pictures of a representation's feature planes (the paper's Fig. 2).

* the positional plane ``(H, W, C)`` -> its first three principal components as RGB
  (each component stretched to its 1st..99th percentile);
* each angular plane ``(R, R, C)`` (representations that expose
  ``angular_planes()``, e.g. the Triple Plane's ``f_H`` and ``f_D``) -> its first three
  principal components as RGB and a grid of its ``C`` channels in grey, rows =
  theta (0 at the top), columns = phi;
* a height field (representations with relief, ``height_field()``, e.g. kind
  ``triple-parallax``) -> grey, lowest black, highest white.

Images are display values in ``[0, 1]`` (not linear radiance).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..io import save_image, srgb_to_linear
from .base import Representation

__all__ = ["principal_components_rgb", "channel_grid", "feature_plane_images", "write_feature_plane_pngs"]


def principal_components_rgb(plane) -> np.ndarray:
    """First three principal components of a ``(H, W, C)`` plane as a ``(H, W, 3)`` image in ``[0, 1]``.

    Components are ordered by variance and their signs fixed so that each
    component's largest-magnitude loading is positive (deterministic colours).
    Planes with fewer than three channels repeat the last component.

    >>> img = principal_components_rgb(np.random.default_rng(0).normal(size=(4, 5, 6)))
    >>> img.shape, float(img.min()) >= 0, float(img.max()) <= 1
    ((4, 5, 3), True, True)
    """
    x = np.asarray(plane.detach().cpu() if isinstance(plane, torch.Tensor) else plane, dtype=np.float64)
    h, w, c = x.shape
    flat = x.reshape(-1, c)
    flat = flat - flat.mean(0)
    _, _, vt = np.linalg.svd(flat, full_matrices=False)
    vt = vt * np.sign(vt[np.arange(len(vt)), np.abs(vt).argmax(1)])[:, None]
    comps = flat @ vt[:3].T
    if comps.shape[1] < 3:
        comps = np.concatenate([comps] + [comps[:, -1:]] * (3 - comps.shape[1]), axis=1)
    lo, hi = np.percentile(comps, 1, axis=0), np.percentile(comps, 99, axis=0)
    img = (comps - lo) / np.where(hi > lo, hi - lo, 1.0)
    return np.clip(img, 0.0, 1.0).reshape(h, w, 3).astype(np.float32)


def channel_grid(plane, scale: int = 8, columns: int = 4) -> np.ndarray:
    """Channels of a ``(R, S, C)`` plane side by side in grey, each upscaled ``scale`` x (nearest).

    Each channel is stretched to its own min..max; one-texel black gaps separate them.
    Returns ``(rows * (R*scale+1) - 1, columns * (S*scale+1) - 1, 3)`` in ``[0, 1]``.
    """
    x = np.asarray(plane.detach().cpu() if isinstance(plane, torch.Tensor) else plane, dtype=np.float64)
    r, s, c = x.shape
    rows = -(-c // columns)
    th, tw = r * scale, s * scale
    out = np.zeros((rows * (th + 1) - 1, columns * (tw + 1) - 1), dtype=np.float32)
    for k in range(c):
        ch = x[..., k]
        ch = (ch - ch.min()) / (ch.max() - ch.min()) if ch.max() > ch.min() else np.zeros_like(ch)
        tile = np.kron(ch, np.ones((scale, scale)))
        i, j = divmod(k, columns)
        out[i * (th + 1):i * (th + 1) + th, j * (tw + 1):j * (tw + 1) + tw] = tile
    return np.repeat(out[..., None], 3, axis=-1)


def feature_plane_images(rep: Representation, angular_scale: int = 8) -> dict[str, np.ndarray]:
    """Display images ``name -> (h, w, 3)`` in ``[0, 1]`` of a representation's feature planes."""
    images = {"positional_pca": principal_components_rgb(rep.positional_plane())}
    if hasattr(rep, "angular_planes"):
        for name, plane in rep.angular_planes().items():
            pcs = principal_components_rgb(plane)
            images[f"{name}_pca"] = np.kron(pcs, np.ones((angular_scale, angular_scale, 1))).astype(np.float32)
            images[f"{name}_channels"] = channel_grid(plane, scale=angular_scale)
    if hasattr(rep, "height_field"):
        height = rep.height_field().detach().float().cpu().numpy()
        grey = (height - height.min()) / max(float(height.max() - height.min()), 1e-12)
        images["height"] = np.repeat(grey[..., None], 3, axis=-1).astype(np.float32)
    return images


def write_feature_plane_pngs(rep: Representation, out_dir) -> list[Path]:
    """Write :func:`feature_plane_images` as ``<out_dir>/<name>.png`` (atomically); return the paths."""
    out_dir = Path(out_dir)
    paths = []
    for name, img in feature_plane_images(rep).items():
        # save_image sRGB-encodes linear input: hand it the linear value of each display value
        paths.append(save_image(out_dir / f"{name}.png", srgb_to_linear(img)))
    return paths
