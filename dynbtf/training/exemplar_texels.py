"""The exemplar's texel count, chosen before a fit: ``dynbtf fit --texels``.

A fit learns one positional feature per texel of the BTF. ``--texels HxW`` fits the BTF resampled to ``H`` rows and
``W`` columns over the same repeat (:class:`~dynbtf.data.resampled.ResampledBTF`; ``uv`` keeps its meaning, so a
model of either size covers the same surface). ``--texels whole`` chooses that size for a structured material:
it finds the elements ``struct`` would find (:func:`~dynbtf.synthesis.cell_quilting.elements_of`), here in a few
of the BTF's own images, and resamples to the nearest size at which an element and a row are whole texels
(:func:`~dynbtf.synthesis.elements.whole_element_size`): a running bond of 3 bricks across 64 texels (21.33 each)
becomes 66 texels (22 each). ``struct``'s lattice copies are shifted by whole texels; only then can each of them
carry whole bricks onto whole bricks. A BTF without an element lattice, or whose elements are whole already,
keeps its size.

Examples
--------
>>> parse_texels("66x64"), parse_texels("whole"), parse_texels(" 48 ")
((66, 64), 'whole', (48, 48))
"""

from __future__ import annotations

import numpy as np

from ..data.base import BTFSource
from ..data.resampled import ResampledBTF
from ..errors import InputError

__all__ = ["parse_texels", "whole_element_texels", "resample_for_fit", "WHOLE", "APPEARANCE_IMAGES"]

#: ``--texels`` value that chooses the size at which the elements are whole texels.
WHOLE = "whole"
#: Images of the BTF (evenly over its (view, light) pairs) in which ``--texels whole`` looks for the elements.
APPEARANCE_IMAGES = 8

_EXPECTED = f"'{WHOLE}', a texel count N (N x N) or HxW (rows x columns), e.g. 66x66"


def parse_texels(text) -> str | tuple[int, int]:
    """``"whole"``, or ``(rows, columns)`` from ``"HxW"`` or ``"N"``; an :class:`InputError` naming ``--texels``
    otherwise."""
    value = str(text).strip().lower()
    if value == WHOLE:
        return WHOLE
    parts = value.split("x")
    if len(parts) in (1, 2) and all(p.strip().isdigit() and int(p) > 0 for p in parts):
        numbers = [int(p) for p in parts]
        return numbers[0], numbers[-1]
    raise InputError(f"--texels: expected {_EXPECTED}, got {text!r}")


def _appearance(source: BTFSource, images: int) -> np.ndarray:
    """``(H, W, 3 images)`` float64: ``images`` of the source's images, evenly over its pairs, as channels."""
    rows = np.unique(np.linspace(0, source.n_pairs - 1, max(1, int(images))).round().astype(np.int64))
    return np.concatenate([np.asarray(source.image(int(r) // source.n_lights, int(r) % source.n_lights),
                                      dtype=np.float64) for r in rows], axis=-1)


def whole_element_texels(source: BTFSource, images: int = APPEARANCE_IMAGES) -> tuple[tuple[int, int], str]:
    """``((rows, columns), sentence)``: the texel size at which the elements ``struct`` finds in ``source`` are
    whole texels (its own size when it has no element lattice, or when they are whole already), and a sentence
    that says what was found."""
    from ..synthesis.cell_quilting import elements_of
    from ..synthesis.elements import whole_element_size
    from ..synthesis.structure import STRUCTURE_THRESHOLD

    h, w = source.height, source.width
    grid, strength = elements_of(_appearance(source, images))
    if strength < STRUCTURE_THRESHOLD:
        return (h, w), (f"--texels {WHOLE}: no element lattice in {source.name} (structure strength {strength:.2f}, "
                        f"below {STRUCTURE_THRESHOLD:g}): kept at {h} x {w} texels")
    columns, rows, p, q = (int(v) for v in grid[:4])
    size = whole_element_size(grid, h, w)
    found = (f"{columns} x {rows} elements per repeat ({w / columns:.4g} x {h / rows:.4g} texels"
             + (f", rows shifted {p}/{q} of an element" if p else "") + ")")
    if size == (h, w):
        return size, f"--texels {WHOLE}: {found}, whole already: kept at {h} x {w} texels"
    return size, (f"--texels {WHOLE}: {found}: resampled from {h} x {w} to {size[0]} x {size[1]} texels "
                  f"({size[1] // columns} x {size[0] // rows} each)")


def resample_for_fit(source: BTFSource, texels) -> tuple[BTFSource, str | None]:
    """``source`` at the texel count ``texels`` asks for (:func:`parse_texels`'s forms; None: as it is) and a
    sentence saying what was done (None when nothing was asked)."""
    if texels is None:
        return source, None
    wanted = parse_texels(texels)
    sentence = None
    if wanted == WHOLE:
        wanted, sentence = whole_element_texels(source)
    if wanted == (source.height, source.width):
        return source, sentence or f"--texels: {source.name} has {wanted[0]} x {wanted[1]} texels already"
    try:
        resampled = ResampledBTF(source, *wanted)
    except InputError as error:
        raise InputError(f"--texels {texels}: {error}") from None
    return resampled, sentence or (f"--texels: resampled {source.name} from {source.height} x {source.width} to "
                                   f"{wanted[0]} x {wanted[1]} texels")
