"""The spherical-harmonics baseline: per texel and per measured view, SH in the light direction.

The paper's SH baseline (after Kawasaki et al. 2005) stores, for every texel
and every measured view direction, the least-squares fit of the 2-D light slice
``w_light -> rgb`` with the first 3 SH bands (9 real basis functions) per RGB
channel: 27 coefficients per (texel, view).

Model
-----
    rgb_c(uv, view, light) = sum_v a_v(view) sum_j coef_{v,c,j}(uv) Y_j(light)

* ``Y_j`` -- the real spherical harmonics of :func:`real_sh_basis` (orthonormal
  on the sphere; ``j = l^2 + l + m``, ``l < bands``). The light directions of a
  BTF cover only the upper hemisphere: the fit is a plain least-squares fit
  there (the lower hemisphere is unconstrained and never queried).
* **Positional plane** -- *everything*: ``(H, W, n_views * 3 * bands^2)``,
  view-major (``[view][channel][basis]``). Large (the paper's point: storage
  grows with the number of views); synthesis consumes it like any plane.
* ``a_v(view)`` -- the weights of the ``neighbours`` measured views nearest to
  ``view`` (inverse squared distance, exact at measured views;
  :mod:`dynbtf.representations.measured_directions`).

Fitting (:func:`fit_sh`) streams the BTF view by view and image by image: the
least-squares solution is ``pinv(Y_v) @ images`` with ``Y_v`` the SH values at
the view's fitted lights, accumulated one image at a time (memory = the
coefficients). Held-out pairs are simply not used; views with no fitted light
at all take the inverse-distance blend of the nearest fitted views.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn
from ..progress import progress_bar
from ..data.base import BTFSource
from ..errors import InputError
from .base import MAX_DIRECTIONS, MAX_NEIGHBOURS, MAX_SIDE, Representation, config_int, register
from .measured_directions import check_pairs, nearest_direction_weights

__all__ = ["SphericalHarmonics", "fit_sh", "real_sh_basis", "SH_NORMALIZATION"]

#: Normalization constants of the real SH up to band 2 (orthonormal on the unit sphere).
SH_NORMALIZATION = {
    "l0": 0.5 * math.sqrt(1.0 / math.pi),  # 0.282095
    "l1": math.sqrt(3.0 / (4.0 * math.pi)),  # 0.488603
    "l2_xy": 0.5 * math.sqrt(15.0 / math.pi),  # 1.092548
    "l2_z2": 0.25 * math.sqrt(5.0 / math.pi),  # 0.315392
    "l2_x2y2": 0.25 * math.sqrt(15.0 / math.pi),  # 0.546274
}


def real_sh_basis(w, bands: int = 3):
    """Real spherical harmonics ``Y_j(w)`` for ``j < bands^2`` (``bands`` in 1..3).

    Ordering ``j = l^2 + l + m``: ``Y_00; Y_1-1 ~ y, Y_10 ~ z, Y_11 ~ x;
    Y_2-2 ~ xy, Y_2-1 ~ yz, Y_20 ~ 3z^2 - 1, Y_21 ~ xz, Y_22 ~ x^2 - y^2`` --
    the real form ``sqrt(2) (-1)^m Re/Im Y_l^|m|`` of the complex SH with the
    Condon-Shortley phase. Accepts NumPy arrays or torch tensors ``(..., 3)``
    (unit vectors) and returns the same kind, ``(..., bands^2)``.

    Examples
    --------
    >>> import numpy as np
    >>> np.round(real_sh_basis(np.array([0.0, 0.0, 1.0])), 6)
    array([0.282095, 0.      , 0.488603, 0.      , 0.      , 0.      ,
           0.630783, 0.      , 0.      ])
    """
    if bands not in (1, 2, 3):
        raise InputError(f"bands: expected 1, 2 or 3 SH bands, got {bands!r}")
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    c = SH_NORMALIZATION
    cols = [c["l0"] + 0.0 * x]
    if bands >= 2:
        cols += [c["l1"] * y, c["l1"] * z, c["l1"] * x]
    if bands >= 3:
        cols += [c["l2_xy"] * x * y, c["l2_xy"] * y * z, c["l2_z2"] * (3.0 * z * z - 1.0),
                 c["l2_xy"] * x * z, c["l2_x2y2"] * (x * x - y * y)]
    if isinstance(w, torch.Tensor):
        return torch.stack(cols, dim=-1)
    return np.stack(cols, axis=-1)


@register("sh")
class SphericalHarmonics(Representation):
    """Per-texel, per-view SH fit of the light slice (the paper's SH baseline).

    Parameters
    ----------
    height, width : int
        Spatial resolution (texels).
    n_views : int
        Measured view directions (one coefficient set each).
    bands : int, default 3
        SH bands (3 -> 9 basis functions, 27 coefficients per texel and view with RGB).
    neighbours : int, default 3
        Measured views blended for a view direction off the grid.

    Notes
    -----
    A fresh instance holds zeros; :func:`fit_sh` or a model file fills it.
    """

    def __init__(self, height: int, width: int, n_views: int, bands: int = 3, neighbours: int = 3) -> None:
        super().__init__()
        owner = "SphericalHarmonics"
        height, width = (config_int(owner, name, value, 1, MAX_SIDE) for name, value in
                         (("height", height), ("width", width)))
        n_views = config_int(owner, "n_views", n_views, 1, MAX_DIRECTIONS)
        bands = config_int(owner, "bands", bands, 1, 3)
        neighbours = config_int(owner, "neighbours", neighbours, 1, MAX_NEIGHBOURS)
        self._config = dict(height=height, width=width, n_views=n_views, bands=bands, neighbours=neighbours)
        self.coefficients = nn.Parameter(torch.zeros(height, width, n_views * 3 * bands * bands),
                                         requires_grad=False)
        self.register_buffer("views", torch.zeros(n_views, 3))

    # ------------------------------------------------------------ Representation API
    def config(self) -> dict[str, Any]:
        return dict(self._config)

    @property
    def n_basis(self) -> int:
        return self._config["bands"] ** 2

    def positional_plane(self) -> torch.Tensor:
        """All coefficients per texel, ``(H, W, n_views * 3 * bands^2)``, view-major."""
        return self.coefficients

    def angular_weights(self, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """``a_v(view) * Y_j(light)``, ``(..., n_views, bands^2)``: the decode is linear in these.

        Zero except on the ``neighbours`` measured views nearest to ``w_view``.
        """
        dtype = self.coefficients.dtype
        index, weight = nearest_direction_weights(w_view.to(dtype), self.views, self._config["neighbours"])
        a = torch.zeros(*index.shape[:-1], self.views.shape[0], dtype=dtype, device=index.device)
        a = a.scatter_add(-1, index, weight)
        return a[..., :, None] * real_sh_basis(w_light.to(dtype), self._config["bands"])[..., None, :]

    def decode_with_angular(self, features: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from coefficients ``(..., V * 3 * n)`` and :meth:`angular_weights` ``(..., V, n)``."""
        coef = features.to(weights.dtype).unflatten(-1, (self.views.shape[0], 3, self.n_basis))
        return (coef * weights[..., :, None, :]).sum((-3, -1))

    def decode(self, features: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from coefficients and directions ``(..., 3)`` (broadcasting)."""
        return self.decode_with_angular(features, self.angular_weights(w_view, w_light))

    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Whole images at texel centres, ``(B, N, 3)``, for ``B`` pairs ``w_view, w_light (B, 3)``."""
        plane = self.coefficients.reshape(-1, self.views.shape[0], 3, self.n_basis)
        coef = plane if texels is None else plane.index_select(0, texels)
        return torch.einsum("nvcj,bvj->bnc", coef, self.angular_weights(w_view, w_light))


def fit_sh(btf: BTFSource, *, pairs=None, bands: int = 3, neighbours: int = 3, progress: bool = True
           ) -> SphericalHarmonics:
    """Least-squares SH fit of every texel's light slice, view by view, using only ``pairs``.

    Parameters
    ----------
    btf : BTFSource
        The measured BTF (streamed one image at a time).
    pairs : int ``(P, 2)``, optional
        Training (view, light) pairs (default: all).
    bands, neighbours : see :class:`SphericalHarmonics`.
    progress : bool
        tqdm bar over the images read.

    Returns
    -------
    SphericalHarmonics
        On the CPU, float32.
    """
    pairs = check_pairs(btf, pairs)
    n = bands * bands
    model = SphericalHarmonics(btf.height, btf.width, btf.n_views, bands, neighbours)
    t = btf.height * btf.width
    coef = np.zeros((t, btf.n_views, 3, n), dtype=np.float64)
    fitted = np.zeros(btf.n_views, dtype=bool)
    with progress_bar(total=len(pairs), desc="SH: least squares per view", unit="img", disable=not progress) as bar:
        for v in range(btf.n_views):
            lights = pairs[pairs[:, 0] == v, 1]
            if len(lights) == 0:
                continue
            pinv = np.linalg.pinv(real_sh_basis(btf.lights[lights], bands))  # (n, L_v)
            for j, l in enumerate(lights):
                img = btf.image(v, int(l)).reshape(t, 3).astype(np.float64)
                coef[:, v] += img[:, :, None] * pinv[None, None, :, j]
                bar.update(1)
            fitted[v] = True
    if not fitted.all():
        idx, wt = nearest_direction_weights(torch.from_numpy(btf.views), torch.from_numpy(btf.views[fitted]),
                                            neighbours)
        src = np.flatnonzero(fitted)
        for v in np.flatnonzero(~fitted):
            coef[:, v] = np.tensordot(coef[:, src[idx[v].numpy()]], wt[v].numpy(), axes=([1], [0]))
    with torch.no_grad():
        model.coefficients.copy_(torch.from_numpy(coef.reshape(btf.height, btf.width, -1)))
        model.views.copy_(torch.from_numpy(btf.views))
    return model
