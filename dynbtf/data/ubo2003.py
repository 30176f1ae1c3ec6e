"""UBO2003 BTFs: a zip of 8-bit sRGB images named by their angles; reader and writer.

Each image is named ``'tl{tl:03} pl{pl:03} tv{tv:03} pv{pv:03}.jpg'``: theta and phi
of the light, then of the view, in integer degrees (e.g.
``tl015 pl060 tv000 pv000.jpg``). The database has 81 x 81 directions (see
:func:`dynbtf.data.directions.ubo2003_directions`) and 256 x 256 texels.

Reader conventions
------------------
* Entries may sit in a folder inside the zip; folders, hidden files and
  ``__MACOSX`` entries are ignored; every other entry must be a ``.jpg``,
  ``.jpeg`` or ``.png`` with a well-formed name.
* Views are the distinct ``(tv, pv)``, lights the distinct ``(tl, pl)``, each
  sorted by ``(theta, phi)``; every (view, light) pair must be present exactly once.
* Image row 0 is the top row of the file (``v = 0``); pixels are 8-bit sRGB,
  decoded to linear float32 with :func:`dynbtf.io.srgb_to_linear`. Images are
  decoded lazily, one at a time, from the zip. All image sizes are checked from
  the file headers when opening.

Examples
--------
>>> import numpy as np, tempfile, os
>>> from dynbtf.data.array import ArrayBTF
>>> src = ArrayBTF(np.full((1, 2, 3, 4, 3), 0.2), [[0, 0, 1.0]], [[0, 0, 1.0], [0.5, 0, 0.8660254]])
>>> path = write_ubo2003(os.path.join(tempfile.mkdtemp(), "grey.zip"), src, image_format="png")
>>> btf = UBO2003BTF(path)
>>> btf.shape, sorted(btf.entry_names())[1]
((1, 2, 3, 4), 'tl030 pl000 tv000 pv000.png')
>>> bool(np.allclose(btf.image(0, 1), 0.2, atol=2e-3))
True
"""

from __future__ import annotations

import io
import re
import struct
import warnings
import zipfile
import zlib
from pathlib import Path, PurePosixPath

import numpy as np

from ..conventions import direction_to_spherical, spherical_to_direction
from ..errors import FormatError, InputError
from ..io import atomic_path, require_file, srgb_to_linear, to_uint8_srgb
from .base import BTFSource

__all__ = ["UBO2003BTF", "read_ubo2003", "write_ubo2003", "ubo2003_entry_name", "UBO2003_NAME"]

#: Pattern of an image name (light angles first, integer degrees).
UBO2003_NAME = re.compile(r"^tl(\d{3}) pl(\d{3}) tv(\d{3}) pv(\d{3})\.(jpg|jpeg|png)$", re.IGNORECASE)
_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")


def ubo2003_entry_name(theta_light: int, phi_light: int, theta_view: int, phi_view: int,
                       extension: str = "jpg") -> str:
    """The file name of one image, e.g. ``'tl015 pl060 tv000 pv000.jpg'`` (integer degrees)."""
    return f"tl{theta_light:03d} pl{phi_light:03d} tv{theta_view:03d} pv{phi_view:03d}.{extension}"


def _ignored(name: str) -> bool:
    parts = PurePosixPath(name).parts
    return name.endswith("/") or any(p.startswith(".") or p == "__MACOSX" for p in parts)


class UBO2003BTF(BTFSource):
    """A UBO2003 zip of angle-named sRGB images, decoded lazily.

    Parameters
    ----------
    path : str or Path
        The ``.zip`` file.

    Raises
    ------
    FormatError
        Not a zip file, malformed entry names, angles out of range (below the
        horizon, phi >= 360), duplicate or missing (view, light) images (the set
        must be a full views x lights grid), images of differing size or
        undecodable images.
    """

    def __init__(self, path):
        super().__init__()
        self.path = require_file(path, "a UBO2003 .zip of images")
        try:
            self._zip = zipfile.ZipFile(self.path)
        except (zipfile.BadZipFile, OSError, NotImplementedError, ValueError, EOFError) as e:
            raise FormatError(self.path, f"not a zip file ({e}); expected a UBO2003 .zip of images") from None
        entries: dict[tuple[int, int, int, int], str] = {}
        for name in self._zip.namelist():
            if _ignored(name):
                continue
            base = PurePosixPath(name).name
            m = UBO2003_NAME.match(base)
            if m is None:
                raise FormatError(self.path, f"malformed entry name {name!r}: expected "
                                             f"'tl<theta_l> pl<phi_l> tv<theta_v> pv<phi_v>.jpg' with 3-digit "
                                             f"integer degrees, e.g. 'tl015 pl060 tv000 pv000.jpg'")
            tl, pl, tv, pv = (int(g) for g in m.groups()[:4])
            for what, theta, phi in (("light", tl, pl), ("view", tv, pv)):
                if theta > 90:
                    raise FormatError(self.path, f"entry {name!r}: {what} theta = {theta} deg is below the horizon "
                                                 f"(expected 0..90)")
                if phi >= 360:
                    raise FormatError(self.path, f"entry {name!r}: {what} phi = {phi} deg; expected 0..359")
            key = (tl, pl, tv, pv)
            if key in entries:
                raise FormatError(self.path, f"entries {entries[key]!r} and {name!r} have the same angles")
            entries[key] = name
        if not entries:
            raise FormatError(self.path, "contains no images named 'tl... pl... tv... pv....jpg'")
        self._lights_deg = sorted({(k[0], k[1]) for k in entries})
        self._views_deg = sorted({(k[2], k[3]) for k in entries})
        n_expected = len(self._lights_deg) * len(self._views_deg)
        if len(entries) != n_expected:
            missing = [ubo2003_entry_name(tl, pl, tv, pv) for (tv, pv) in self._views_deg
                       for (tl, pl) in self._lights_deg if (tl, pl, tv, pv) not in entries]
            raise FormatError(self.path, f"{len(missing)} images missing: {len(self._views_deg)} views x "
                                         f"{len(self._lights_deg)} lights need {n_expected} images but the zip has "
                                         f"{len(entries)} (first missing: {missing[0]!r})")
        self._names = [[entries[(tl, pl, tv, pv)] for (tl, pl) in self._lights_deg] for (tv, pv) in self._views_deg]
        self.views = spherical_to_direction(*np.array(self._views_deg, dtype=np.float64).T)
        self.lights = spherical_to_direction(*np.array(self._lights_deg, dtype=np.float64).T)
        self.height, self.width = self._check_sizes()
        self.name = self.path.name
        self.metadata = {"format": "ubo2003-zip", "path": str(self.path), "images": len(entries),
                         "encoding": "8-bit sRGB"}

    def _open_entry(self, name: str, *, decode: bool):
        """Image size ``(H, W)`` from the header (``decode=False``) or the ``(H, W, 3)`` uint8 pixels.

        Every way a damaged zip member or image can fail (bad CRC, broken
        deflate stream, unsupported zip feature, truncated or absurd image data)
        becomes a FormatError naming the entry.
        """
        from PIL import Image

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", Image.DecompressionBombWarning)
                if not decode:
                    with self._zip.open(name) as f, Image.open(f) as im:
                        return im.height, im.width
                with Image.open(io.BytesIO(self._zip.read(name))) as im:
                    return np.asarray(im.convert("RGB"))
        except (OSError, ValueError, EOFError, RuntimeError, NotImplementedError, KeyError, struct.error,
                zipfile.BadZipFile, zlib.error, Image.DecompressionBombWarning, Image.DecompressionBombError) as e:
            what = "cannot be decoded" if decode else "is not a readable image"
            raise FormatError(self.path, f"entry {name!r} {what} ({type(e).__name__}: {e})") from None

    def _check_sizes(self) -> tuple[int, int]:
        """Read every image's size from its header; all must agree."""
        first = None
        for row in self._names:
            for name in row:
                size = self._open_entry(name, decode=False)
                if first is None:
                    first = (size, name)
                elif size != first[0]:
                    raise FormatError(self.path, f"entry {name!r} is {size[1]}x{size[0]} pixels but "
                                                 f"{first[1]!r} is {first[0][1]}x{first[0][0]}: all images must "
                                                 f"have the same size")
        # an image file of H x W pixels is at most about its raw size (uncompressed RGBA, plus headers);
        # an entry declaring far more would be read whole into memory before decoding fails
        height, width = first[0]
        limit = 2 * height * width * 4 + 2 ** 20
        for row in self._names:
            for name in row:
                declared = self._zip.getinfo(name).file_size
                if declared > limit:
                    raise FormatError(self.path, f"entry {name!r} declares {declared:,} bytes, far more than an image "
                                                 f"of {width}x{height} pixels needs (at most {limit:,}): refused "
                                                 "(damaged or not a UBO2003 zip)")
        return first[0]

    def entry_names(self) -> list[str]:
        """All image entry names, view-major."""
        return [n for row in self._names for n in row]

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        name = self._names[view_index][light_index]
        pixels = self._open_entry(name, decode=True)
        if pixels.shape[:2] != (self.height, self.width):
            raise FormatError(self.path, f"entry {name!r} decodes to {pixels.shape[1]}x{pixels.shape[0]} pixels; "
                                         f"expected {self.width}x{self.height}")
        return srgb_to_linear(pixels.astype(np.float32) / 255.0)

    def close(self) -> None:
        self._zip.close()


def read_ubo2003(path) -> UBO2003BTF:
    """Open a UBO2003 zip (see :class:`UBO2003BTF`)."""
    return UBO2003BTF(path)


def _integer_degrees(w: np.ndarray, what: str) -> list[tuple[int, int]]:
    theta, phi = direction_to_spherical(np.asarray(w, dtype=np.float64))
    out = []
    for k, (t, p) in enumerate(zip(np.atleast_1d(theta), np.atleast_1d(phi))):
        ti, pi = int(round(float(t))), int(round(float(p))) % 360
        if abs(t - round(float(t))) > 1e-3 or abs((p - round(float(p)) + 180) % 360 - 180) > 1e-3:
            raise InputError(f"{what} {k} has (theta, phi) = ({t:.4g}, {p:.4g}) deg: UBO2003 names hold integer "
                             f"degrees only")
        if ti > 90:
            raise InputError(f"{what} {k} is below the horizon (theta = {t:.4g} deg)")
        out.append((ti, pi))
    if len(set(out)) != len(out):
        raise InputError(f"{what}s: two directions have the same integer-degree angles")
    return out


def write_ubo2003(path, source: BTFSource, *, image_format: str = "jpg", quality: int = 95,
                  progress: bool = False) -> Path:
    """Write ``source`` as a UBO2003 zip of angle-named 8-bit sRGB images, atomically.

    Parameters
    ----------
    path : str or Path
        Output ``.zip``.
    source : BTFSource
        Its directions must have integer (theta, phi) degrees (as UBO2003's do).
        Read image by image.
    image_format : ``"jpg"`` or ``"png"``
        JPEG (lossy, as the database; 4:4:4, ``quality``) or PNG (lossless 8-bit).
    quality : int
        JPEG quality 1..100 (default 95).
    progress : bool
        Show a tqdm progress bar (images, rate, ETA).

    Returns
    -------
    Path : the file written. Values are clamped to ``[0, 1]`` and sRGB-encoded.
    """
    if image_format not in ("jpg", "png"):
        raise InputError(f"image_format: expected 'jpg' or 'png', got {image_format!r}")
    if not 1 <= int(quality) <= 100:
        raise InputError(f"quality: expected 1..100, got {quality!r}")
    from PIL import Image

    views = _integer_degrees(source.views, "view")
    lights = _integer_degrees(source.lights, "light")
    path = Path(path)
    compression = zipfile.ZIP_STORED if image_format == "jpg" else zipfile.ZIP_DEFLATED
    from ..progress import progress_bar
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", compression=compression) as zf, \
            progress_bar(total=source.n_pairs, unit="img", desc=f"writing {path.name}", disable=not progress) as bar:
        for v, (tv, pv) in enumerate(views):
            for l, (tl, pl) in enumerate(lights):
                buf = io.BytesIO()
                im = Image.fromarray(to_uint8_srgb(source.image(v, l)))
                if image_format == "jpg":
                    im.save(buf, format="JPEG", quality=int(quality), subsampling=0)
                else:
                    im.save(buf, format="PNG")
                zf.writestr(ubo2003_entry_name(tl, pl, tv, pv, image_format), buf.getvalue())
                bar.update(1)
    return path
