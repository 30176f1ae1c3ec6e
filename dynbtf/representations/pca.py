"""The PCA baseline: a rank-k factorization of the BTF's texel x (view, light) matrix.

Classical BTF compression (Koudelka et al. 2003 and the Bonn DFMF files) writes
the BTF of one colour channel ``c`` as a matrix ``A_c`` with one **row per
texel** (``T = H * W`` rows) and one **column per measured (view, light) pair**
(``P`` columns; an image is a column) and keeps its best rank-``k``
approximation. The paper's baseline keeps ``k = 5`` components per RGB channel
(15 in all).

Model
-----
    rgb_c(uv, view, light) = mean_c(view, light) + sum_k coef_{c,k}(uv) * basis_{c,k}(view, light)

* **Centring** (our choice, documented): each column is centred on its mean
  over the texels, ``mean_c(view, light)`` -- the material's average BRDF --
  and the SVD factorizes the centred matrix. The mean costs ``P x 3`` floats
  (angular storage, no positional storage) and lets all ``k`` components
  describe spatial variation. ``centered=False`` gives the plain truncated SVD
  of ``A_c``.
* **Positional plane** = ``coef``, ``(H, W, 3 k)``, channel-major
  (``[R_1..R_k, G_1..G_k, B_1..B_k]``), **scaled by the singular values**
  (``coef = U_k S_k``) so that the angular basis is orthonormal -- the DFMF
  files' ``SxV`` layout. Its bilinear periodic fetch is what synthesis replaces.
* **Angular basis** ``basis (n_views, n_lights, 3, k)`` and ``mean
  (n_views, n_lights, 3)``, tabulated on the measured direction grid. At a
  measured (view, light) pair the decode is the exact rank-k reconstruction. At
  other directions the table is blended over the ``neighbours`` nearest
  measured views times the nearest measured lights with inverse-squared-distance
  weights (:mod:`dynbtf.representations.measured_directions`). Pairs that were
  held out of the fit are filled from the nearest fitted pairs the same way
  (distance = chord distance of the views squared + of the lights squared).

Fitting (:func:`fit_pca`) streams the BTF image by image through a randomized
SVD (Halko, Martinsson & Tropp 2011, Alg. 4.4 with power iterations): the BTF
never has to fit in memory, only ``T x (k + oversampling)`` accumulators per
channel; every pass decodes each fitted image once.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn
from ..progress import progress_bar
from ..data.base import BTFSource
from ..errors import InputError
from .base import (MAX_CHANNELS, MAX_DIRECTIONS, MAX_NEIGHBOURS, MAX_SIDE, Representation, config_flag, config_int,
                   register)
from .measured_directions import check_pairs, nearest_direction_weights

__all__ = ["PCA", "fit_pca", "streamed_randomized_svd"]


@register("pca")
class PCA(Representation):
    """Per-channel rank-k PCA of the BTF with tabulated angular basis.

    Parameters
    ----------
    height, width : int
        Spatial resolution (texels).
    n_views, n_lights : int
        Size of the measured direction grid the angular basis is tabulated on.
    components : int, default 5
        Components ``k`` per RGB channel.
    centered : bool, default True
        Whether columns were centred on their texel mean (``mean`` is then the
        average BRDF; otherwise it is zero).
    neighbours : int, default 3
        Measured views (and lights) blended for directions off the grid.

    Notes
    -----
    A fresh instance holds zeros; :func:`fit_pca` or a model file fills it.
    """

    def __init__(self, height: int, width: int, n_views: int, n_lights: int, components: int = 5,
                 centered: bool = True, neighbours: int = 3) -> None:
        super().__init__()
        height, width = (config_int("PCA", name, value, 1, MAX_SIDE) for name, value in
                         (("height", height), ("width", width)))
        n_views, n_lights = (config_int("PCA", name, value, 1, MAX_DIRECTIONS) for name, value in
                             (("n_views", n_views), ("n_lights", n_lights)))
        components = config_int("PCA", "components", components, 1, MAX_CHANNELS)
        neighbours = config_int("PCA", "neighbours", neighbours, 1, MAX_NEIGHBOURS)
        self._config = dict(height=height, width=width, n_views=n_views, n_lights=n_lights,
                            components=components, centered=config_flag("PCA", "centered", centered),
                            neighbours=neighbours)
        frozen = dict(requires_grad=False)
        self.coefficients = nn.Parameter(torch.zeros(height, width, 3 * components), **frozen)
        self.basis = nn.Parameter(torch.zeros(n_views, n_lights, 3, components), **frozen)
        self.mean = nn.Parameter(torch.zeros(n_views, n_lights, 3), **frozen)
        self.register_buffer("views", torch.zeros(n_views, 3))
        self.register_buffer("lights", torch.zeros(n_lights, 3))
        self.register_buffer("singular_values", torch.zeros(3, components))

    # ------------------------------------------------------------ Representation API
    def config(self) -> dict[str, Any]:
        return dict(self._config)

    @property
    def components(self) -> int:
        return self._config["components"]

    def positional_plane(self) -> torch.Tensor:
        """Coefficients ``U_k S_k`` per texel, ``(H, W, 3 k)``, channel-major."""
        return self.coefficients

    def angular_table(self, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """Blended ``[basis | mean]`` at the directions: ``(..., 3, k + 1)``.

        Exact table entries at measured (view, light) pairs; inverse-squared-distance
        blend of ``neighbours x neighbours`` measured pairs elsewhere.
        """
        table = torch.cat([self.basis, self.mean[..., None]], dim=-1)  # (V, L, 3, k+1)
        k = self._config["neighbours"]
        vi, vw = nearest_direction_weights(w_view.to(table.dtype), self.views, k)
        li, lw = nearest_direction_weights(w_light.to(table.dtype), self.lights, k)
        out = None
        for a in range(vi.shape[-1]):
            for b in range(li.shape[-1]):
                term = table[vi[..., a], li[..., b]] * (vw[..., a] * lw[..., b])[..., None, None]
                out = term if out is None else out + term
        return out

    def decode(self, features: torch.Tensor, w_view: torch.Tensor, w_light: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from coefficients ``(..., 3 k)`` and directions ``(..., 3)`` (broadcasting)."""
        return self.decode_with_angular(features, self.angular_table(w_view, w_light))

    def decode_with_angular(self, features: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
        """RGB ``(..., 3)`` from coefficients ``(..., 3 k)`` and :meth:`angular_table` ``(..., 3, k + 1)``."""
        k = self.components
        coef = features.to(table.dtype).unflatten(-1, (3, k))
        return (coef * table[..., :k]).sum(-1) + table[..., k]

    def predict_texel_images(self, w_view: torch.Tensor, w_light: torch.Tensor,
                             texels: torch.Tensor | None = None) -> torch.Tensor:
        """Whole images at texel centres, ``(B, N, 3)``, for ``B`` pairs ``w_view, w_light (B, 3)``."""
        plane = self.coefficients.reshape(-1, self.coefficients.shape[-1])
        features = plane if texels is None else plane.index_select(0, texels)
        return self.decode_with_angular(features[None], self.angular_table(w_view, w_light)[:, None])


# ---------------------------------------------------------------------- fitting
def _image_blocks(btf: BTFSource, pairs: np.ndarray, block: int, centered: bool, bar, cache: np.ndarray | None,
                  cached: bool):
    """Yield ``(slice, A (3, T, b) float64, column means (b, 3))`` over the pairs, in order.

    With a ``cache`` array ``(P, T, 3)`` float32 the images are stored into it
    (``cached=False``, first pass) or read from it (``cached=True``) instead of
    being decoded again.
    """
    t = btf.height * btf.width
    for start in range(0, len(pairs), block):
        chunk = pairs[start:start + block]
        a = np.empty((3, t, len(chunk)), dtype=np.float64)
        for j, (v, l) in enumerate(chunk):
            if cached:
                image = cache[start + j]
            else:
                image = btf.image(int(v), int(l)).reshape(t, 3)
                if cache is not None:
                    cache[start + j] = image
            a[:, :, j] = image.T
        means = a.mean(axis=1).T if centered else np.zeros((len(chunk), 3))
        if centered:
            a -= means.T[:, None, :]
        bar.update(len(chunk))
        yield slice(start, start + len(chunk)), a, means


def streamed_randomized_svd(btf: BTFSource, pairs, rank: int, *, centered: bool = True, oversampling: int = 10,
                            power_iterations: int = 2, seed: int = 0, block: int = 64, progress: bool = True,
                            cache_mb: float = 1024.0):
    """Top-``rank`` SVD of each colour channel's texel x pair matrix, streamed image by image.

    Parameters
    ----------
    btf : BTFSource
        Read with :meth:`BTFSource.image`, one (view, light) image at a time.
    pairs : int ``(P, 2)`` or None
        (view, light) pairs forming the columns, in this order (all, view-major, if None).
    rank : int
        Singular triplets kept per channel.
    centered : bool
        Subtract each column's (image's) texel mean first.
    oversampling, power_iterations : int
        Randomized range finder parameters (Halko et al.: ``rank + oversampling``
        random probes, ``power_iterations`` passes of ``A A^T``).
    seed : int
        Seed of the Gaussian test matrix.
    block : int
        Images per matrix product (memory ``3 x T x block`` float64).
    progress : bool
        Show a tqdm bar over the ``(2 + power_iterations) x P`` image reads.
    cache_mb : float
        If the fitted images fit in this many MB as float32, the first pass keeps
        them and the later passes read them from memory instead of decoding the
        BTF again (same result); otherwise every pass streams from ``btf``.

    Returns
    -------
    U : float64 ``(3, T, rank)``, S : ``(3, rank)``, Vt : ``(3, rank, P)``, means : ``(P, 3)``
        Per channel ``A_c ~= U[c] @ diag(S[c]) @ Vt[c]`` (plus ``means[:, c]`` per column
        when ``centered``). Signs are fixed so that each right singular vector's
        largest-magnitude entry is positive.
    """
    pairs = check_pairs(btf, pairs)
    t, p = btf.height * btf.width, len(pairs)
    if not isinstance(rank, int) or rank < 1:
        raise InputError(f"rank: expected a positive integer, got {rank!r}")
    if rank > min(t, p):
        raise InputError(f"rank {rank} exceeds min(texels, pairs) = min({t}, {p}) of {btf.name}")
    width = min(rank + max(int(oversampling), 0), t, p)
    rng = np.random.default_rng(seed)
    omega = rng.standard_normal((3, p, width))
    bar = progress_bar(total=(2 + power_iterations) * p, desc="PCA: randomized SVD", unit="img", disable=not progress)
    means = np.zeros((p, 3))
    cache = np.empty((p, t, 3), dtype=np.float32) if p * t * 3 * 4 <= cache_mb * 1024 ** 2 else None
    try:
        # range finder: Y = A Omega
        y = np.zeros((3, t, width))
        for sl, a, m in _image_blocks(btf, pairs, block, centered, bar, cache, False):
            y += a @ omega[:, sl]
            means[sl] = m
        q = np.linalg.qr(y)[0]
        # power iterations: Y = A (A^T Q), one pass each
        for _ in range(power_iterations):
            y = np.zeros((3, t, width))
            for sl, a, _m in _image_blocks(btf, pairs, block, centered, bar, cache, cache is not None):
                y += a @ (a.transpose(0, 2, 1) @ q)
            q = np.linalg.qr(y)[0]
        # projection: B^T = A^T Q
        bt = np.zeros((3, p, width))
        for sl, a, _m in _image_blocks(btf, pairs, block, centered, bar, cache, cache is not None):
            bt[:, sl] = a.transpose(0, 2, 1) @ q
    finally:
        bar.close()
    ub, s, vt = np.linalg.svd(bt.transpose(0, 2, 1), full_matrices=False)  # B = Q^T A, (3, width, P)
    u = q @ ub[:, :, :rank]
    s, vt = s[:, :rank], vt[:, :rank]
    sign = np.sign(np.take_along_axis(vt, np.abs(vt).argmax(-1, keepdims=True), -1))  # (3, rank, 1)
    sign[sign == 0] = 1.0
    return u * sign.transpose(0, 2, 1), s, vt * sign, means


def _fill_missing_pairs(table: np.ndarray, known: np.ndarray, views: np.ndarray, lights: np.ndarray,
                        neighbours: int) -> None:
    """Fill ``table[v, l]`` where ``~known[v, l]`` from the nearest known pairs (in place).

    Distance between pairs = squared chord distance of the views + of the lights;
    inverse-squared-distance weights over the ``neighbours`` nearest known pairs.
    """
    missing = np.argwhere(~known)
    if len(missing) == 0:
        return
    kv, kl = np.nonzero(known)
    dv = ((views[:, None, :] - views[None, :, :]) ** 2).sum(-1)
    dl = ((lights[:, None, :] - lights[None, :, :]) ** 2).sum(-1)
    n = min(neighbours, len(kv))
    for v, l in missing:
        d = dv[v, kv] + dl[l, kl]
        near = np.argpartition(d, n - 1)[:n]
        w = 1.0 / np.maximum(d[near], 1e-12)
        table[v, l] = np.tensordot(w / w.sum(), table[kv[near], kl[near]], axes=1)


def fit_pca(btf: BTFSource, *, pairs=None, components: int = 5, centered: bool = True, neighbours: int = 3,
            oversampling: int = 10, power_iterations: int = 2, seed: int = 0, block: int = 64,
            progress: bool = True, cache_mb: float = 1024.0) -> PCA:
    """Fit the PCA baseline to ``btf`` using only the (view, light) ``pairs`` given.

    Parameters
    ----------
    btf : BTFSource
        The measured BTF (streamed; never loaded whole).
    pairs : int ``(P, 2)``, optional
        Training (view, light) pairs (default: all). Held-out pairs get their
        angular basis by interpolation from the fitted ones (see module docs).
    components : int, default 5
        Components per RGB channel (the paper: 5, i.e. 15 in all).
    centered, neighbours : see :class:`PCA`.
    oversampling, power_iterations, seed, block, progress, cache_mb : see :func:`streamed_randomized_svd`.

    Returns
    -------
    PCA
        On the CPU, float32.
    """
    pairs = check_pairs(btf, pairs)
    u, s, vt, means = streamed_randomized_svd(btf, pairs, components, centered=centered, oversampling=oversampling,
                                              power_iterations=power_iterations, seed=seed, block=block,
                                              progress=progress, cache_mb=cache_mb)
    model = PCA(btf.height, btf.width, btf.n_views, btf.n_lights, components, centered, neighbours)
    coef = (u * s[:, None, :]).transpose(1, 0, 2).reshape(btf.height, btf.width, 3 * components)
    table = np.zeros((btf.n_views, btf.n_lights, 3, components + 1))
    table[pairs[:, 0], pairs[:, 1], :, :components] = vt.transpose(2, 0, 1)
    table[pairs[:, 0], pairs[:, 1], :, components] = means
    known = np.zeros((btf.n_views, btf.n_lights), dtype=bool)
    known[pairs[:, 0], pairs[:, 1]] = True
    _fill_missing_pairs(table, known, btf.views, btf.lights, neighbours)
    with torch.no_grad():
        model.coefficients.copy_(torch.from_numpy(coef))
        model.basis.copy_(torch.from_numpy(table[..., :components]))
        model.mean.copy_(torch.from_numpy(table[..., components]))
        model.views.copy_(torch.from_numpy(btf.views))
        model.lights.copy_(torch.from_numpy(btf.lights))
        model.singular_values.copy_(torch.from_numpy(s))
    return model
