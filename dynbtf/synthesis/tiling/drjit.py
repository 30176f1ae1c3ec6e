"""Plain tiling in Dr.Jit: the exemplar fetched bilinearly and periodically (:class:`~dynbtf.synthesis.tiling.Tiling`).
"""

from __future__ import annotations

from ...jit import fetch_wrap, flat_array, gather_channels, mi_module, wrap01
from ..drjit_blocks import DrLevelOfDetail, accumulate, filtering_tables, level_shares

class DrTiling:
    """Plain periodic tiling: a bilinear, wrapped fetch of the exemplar plane ``(H, W, C)``.

    ``pyramid_source`` (optional) returns the plane's pyramid (``levels``, ``lod``) for
    :meth:`filtered_latent`, on its first call.
    """

    def __init__(self, plane, pyramid_source=None) -> None:
        mi = mi_module()
        self.pyramid_source = pyramid_source
        self._filtering = None
        plane = plane.detach().float().cpu().numpy() if hasattr(plane, "detach") else plane
        self.size = (int(plane.shape[0]), int(plane.shape[1]))
        self.channels = int(plane.shape[2])
        self.plane = flat_array(mi, plane)

    def features(self, u, v, active=True):
        """The plane's features at ``(u, v)`` (``mi.Float`` or ``mi.Float64``): list of ``C`` mi.Float."""
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active)

    def channel(self, u, v, index: int, active=True):
        """One feature channel (``mi.Float``) at ``(u, v)``."""
        return fetch_wrap(self.plane, self.size, self.channels, u, v, active, which=[index])[0]

    def _pyramid(self):
        """``(DrPyramid, DrLevelOfDetail, None)``, built on first use from ``pyramid_source``."""
        if self._filtering is None:
            self._filtering = filtering_tables(self.pyramid_source)
        return self._filtering

    def level_of_detail(self) -> DrLevelOfDetail:
        """The exemplar pyramid's :class:`DrLevelOfDetail` (builds the pyramid on first use)."""
        return self._pyramid()[1]

    def texel_positions(self, u, v, active=True):
        """Where the point query at ``(u, v)`` reads the plane: level-0 texel positions ``x, y`` (``mi.Float64``,
        in ``[0, W) x [0, H)``); footprint queries read the pyramid there (:meth:`filtered_latent`)."""
        mi = mi_module()
        h, w = self.size
        return mi.Float64(wrap01(mi.Float64(u))) * w, mi.Float64(wrap01(mi.Float64(v))) * h

    def filtered_latent(self, u, v, lower, t=None, active=True):
        """The plane averaged over a footprint (``lower`` level, next level's weight ``t``: :meth:`level_of_detail`;
        as :meth:`DrLatticeBlending.filtered_latent`).

        :func:`dynbtf.synthesis.mip.trilinear_fetch` at :meth:`texel_positions`: list of ``C`` mi.Float.
        """
        pyramid, lod, _ = self._pyramid()
        x, y = self.texel_positions(u, v, active)
        out = None
        for level, share, mask in level_shares(lower, t, lod.top, active):
            out = accumulate(out, gather_channels(pyramid.flat, pyramid.channels, pyramid.taps(level, x, y), mask),
                              share)
        return out




def form(synthesizer) -> DrTiling:
    """The Dr.Jit kernel of a :class:`~dynbtf.synthesis.tiling.Tiling` (its exemplar and pyramid)."""
    return DrTiling(synthesizer.exemplar, pyramid_source=synthesizer.pyramid)
