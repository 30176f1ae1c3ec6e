"""UBO2014 ``.btf`` files (Bonn "DFMF" format): reader and writer.

A DFMF file stores a BTF as one truncated SVD per colour channel: a matrix of
``rows = n_views * n_lights`` (row ``view * n_lights + light``) by
``cols = W * H`` (texels) is factored as ``U (rows x C)`` times ``SxV (cols x C)^T``.
One image is therefore one matrix product ``U[row] @ SxV.T`` per channel; the
reader reads the factors on demand (:mod:`dynbtf.data.file_array`: a file truncated
while it is read is a clean error, not a crash) and decodes images from them, so a
400 x 400 texel, 151 x 151 direction file (44 GB as raw float32) is never materialized.

File layout (little endian)
---------------------------
==========================  ================================================================
``'!' 'DFMF' '08FC'``       magic (9 bytes); an optional ``'R'`` follows (rotations included)
common header               ``u32 size`` (bytes of the header from this field on),
                            ``u32 version``, three ``char[80]`` (measurement setup, image
                            sensor, light source), ``f32 ppmm``, ``3 x f32`` RGB scale;
                            version > 1: ``u32`` cosine flag; > 2: ``u32 n`` + ``n`` bytes
                            of XML; > 3: ``u32`` channel count + per channel ``u32 n`` +
                            ``n`` bytes of name
directions                  ``u32 n_views``; per view ``f32 theta, f32 phi`` (radians),
                            ``u32 n_lights`` and ``n_lights x (f32 theta, f32 phi)`` (the
                            same light list for every view; as btf-extractor, we use the
                            first view's list and check only the later lists' counts)
size                        ``u32 width, u32 height``; with ``'R'``: ``u32 n`` + ``n``
                            3x3 ``f32`` rotation matrices
colour                      ``u32`` components, ``u32`` colour model (0 = RGB,
                            11 = log-YUV), ``3 x f32`` colour mean, ``9 x f32`` transform
per channel (3)             ``u8`` scalar size (2 half, 4 float, 8 double), ``u32 C``,
                            ``u32 rows``, ``u32 cols``, ``C`` singular values, ``U``
                            (rows x C), ``SxV`` (cols x C), row-major; the file ends here
==========================  ================================================================

Colour model 11 decodes the three channel values ``c`` as ``Y = exp(c0) - 1e-5``,
``U = c1 Y + 1e-5``, ``V = c2 Y + 1e-5``, then ``R = Y + 1.13983 V``,
``G = Y - 0.39465 U - 0.5806 V``, ``B = Y + 2.03211 U``, clamped to ``[0, 1]``
(exactly as btf-extractor does; the colour mean and transform are read,
validated and recorded but, as in btf-extractor, not applied).

Relation to btf-extractor (``btf_extractor.Ubo2014``)
-----------------------------------------------------
For light index ``l`` and view index ``v`` (btf-extractor's ``angles_set``
tuples are ``(theta_l, phi_l, theta_v, phi_v)`` in degrees, rounded to 0.1):

* ``our.image(v, l) == btfx.angles_to_image(*angles)[..., ::-1]``: the same
  vertical orientation (both flip the file's rows: our row ``i`` is file texel
  row ``H - 1 - i``), channels reversed (btf-extractor returns BGR, we RGB).
* ``btf_extractor_angles(our, v, l)`` returns that tuple (unrounded);
  ``theta = acos(z)``, ``phi = atan2(y, x) mod 360`` of our unit vectors.
* Deliberate differences: we accept ``n_views != n_lights`` (btf-extractor
  assumes equal counts), and when a file's cosine flag is set we divide by
  ``cos(theta_light)`` so that values exclude it (dynbtf's convention;
  btf-extractor ignores the flag).

Examples
--------
>>> import numpy as np, tempfile, os
>>> from dynbtf.data.array import ArrayBTF
>>> rng = np.random.default_rng(0)
>>> src = ArrayBTF(rng.random((2, 3, 4, 5, 3)), [[0, 0, 1.0], [0.6, 0, 0.8]],
...                [[0, 0, 1.0], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
>>> path = os.path.join(tempfile.mkdtemp(), "tiny.btf")
>>> _ = write_ubo2014(path, src, components=6, scalar="double")
>>> with UBO2014BTF(path) as btf:
...     bool(np.allclose(btf.image(1, 2), src.image(1, 2), atol=1e-6))
True
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..conventions import direction_to_spherical, spherical_to_direction
from ..errors import DynBTFError, FormatError, InputError
from ..io import atomic_path, require_file
from .array import ArrayBTF
from .file_array import OpenFile
from .base import BTFSource

__all__ = ["UBO2014BTF", "DFMFHeader", "read_ubo2014", "write_ubo2014", "write_dfmf_factors", "btf_extractor_angles",
           "DFMF_MAGIC", "DFMF_VERSIONS", "COLOUR_MODELS", "SCALAR_TYPES"]

#: The 9 magic bytes every DFMF file starts with.
DFMF_MAGIC = b"!DFMF08FC"
#: Common-header versions this reader (and the writer) knows: 1; 2 adds the cosine flag, 3 an XML string,
#: 4 channel names.
DFMF_VERSIONS = (1, 2, 3, 4)
#: Supported colour models.
COLOUR_MODELS = {0: "RGB", 11: "log-YUV (Y = exp(c0) - 1e-5, U = c1 Y, V = c2 Y)"}
#: Scalar size in bytes -> little-endian numpy dtype, and the names the writer accepts.
SCALAR_TYPES = {2: np.dtype("<f2"), 4: np.dtype("<f4"), 8: np.dtype("<f8")}
_SCALAR_NAMES = {"half": 2, "float": 4, "double": 8}

_DRR_EPS = 1e-5  # the offset of the log-YUV model
_COMMON_HEADER = struct.Struct("<II80s80s80sf3f")  # size, version, 3 strings, ppmm, rgb
_MAX_COUNT = 1 << 24  # directions, components, names: anything above is absurd
_CHUNK_BYTES = 1 << 25  # decode / validate in chunks of ~32 MB
_TEXELS_PER_PRODUCT = 4096  # texels per factor product of read_texels (a few hundred kB of SxV: cache-sized)
_MIN_COS_LIGHT = float(np.cos(np.radians(89.0)))  # cosine flag: divide by at most this much


@dataclass
class _ChannelLayout:
    """Where one colour channel's factors live in the file (byte offsets)."""

    scalar_size: int
    components: int
    rows: int
    cols: int
    singular_values_offset: int
    u_offset: int
    sxv_offset: int


@dataclass
class DFMFHeader:
    """Every header field of a DFMF file (angles in radians, as stored)."""

    version: int
    rotations_included: bool
    measurement_setup: str
    image_sensor: str
    light_source: str
    ppmm: float
    rgb_scale: tuple[float, float, float]
    cosine_flag: int
    xml: str
    channel_names: list[str]
    view_angles: np.ndarray  # (n_views, 2) theta, phi radians
    light_angles: np.ndarray  # (n_lights, 2)
    width: int
    height: int
    rotations: np.ndarray  # (n, 3, 3)
    components: int
    colour_model: int
    colour_mean: np.ndarray  # (3,)
    colour_transform: np.ndarray  # (3, 3)
    channels: list[_ChannelLayout] = field(default_factory=list)


class _Cursor:
    """Bounds-checked little-endian reads from a byte buffer; errors name the field."""

    def __init__(self, path: Path, buf, size: int):
        self.path, self.buf, self.size, self.pos = path, buf, size, 0

    def fail(self, problem: str):
        raise FormatError(self.path, problem)

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > self.size:
            self.fail(f"truncated: {what} needs {n} bytes at offset {self.pos} but the file has "
                      f"{self.size} bytes")
        out = bytes(self.buf[self.pos:self.pos + n])
        self.pos += n
        return out

    def skip(self, n: int, what: str) -> int:
        if n < 0 or self.pos + n > self.size:
            self.fail(f"truncated: {what} needs {n} bytes at offset {self.pos} but the file has "
                      f"{self.size} bytes")
        start = self.pos
        self.pos += n
        return start

    def u8(self, what: str) -> int:
        return self.take(1, what)[0]

    def u32(self, what: str) -> int:
        return struct.unpack("<I", self.take(4, what))[0]

    def count(self, what: str, *, minimum: int = 0, maximum: int = _MAX_COUNT, item_bytes: int = 1) -> int:
        """A u32 count, checked against a sane range and the bytes left in the file."""
        n = self.u32(what)
        if n < minimum or n > maximum:
            self.fail(f"{what} is {n}; expected {minimum}..{maximum}")
        if n * item_bytes > self.size - self.pos:
            self.fail(f"truncated: {what} is {n} but only {self.size - self.pos} bytes remain after offset {self.pos} "
                      f"(needs {n * item_bytes})")
        return n

    def f32(self, n: int, what: str) -> np.ndarray:
        with np.errstate(invalid="ignore"):  # signalling NaN bit patterns
            values = np.frombuffer(self.take(4 * n, what), dtype="<f4").astype(np.float64)
        if not np.isfinite(values).all():
            self.fail(f"{what} contains NaN or infinite values")
        return values

    def text(self, n: int, what: str) -> str:
        return self.take(n, what).split(b"\0", 1)[0].decode("latin-1")


def _check_angles(cur: _Cursor, angles: np.ndarray, what: str) -> None:
    theta = angles[:, 0]
    bad = (theta < -1e-6) | (theta > np.pi / 2 + 1e-6)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        cur.fail(f"{what} {k} has theta = {np.degrees(theta[k]):.6g} deg: directions must lie in the upper "
                 f"hemisphere (0..90 deg; below the horizon is not a valid measurement)")
    if (np.abs(angles[:, 1]) > 8 * np.pi).any():
        cur.fail(f"{what}: phi outside -1440..1440 deg (corrupt angle values)")


def _check_magic(cur: "_Cursor", buf, size: int) -> bool:
    """Read the magic (a clear error for other BTF variants); returns whether the 'R' (rotations) flag follows."""
    magic = cur.take(min(len(DFMF_MAGIC), size), "magic")
    if magic != DFMF_MAGIC:
        if magic[:1] == b"!" and magic[1:5] in (b"FMF0", b"FMF1", b"PVF0", b"BDIF"):
            cur.fail(f"unsupported BTF variant {magic[1:5].decode()!r}: only DFMF (UBO2014) files are supported")
        cur.fail(f"bad magic {magic!r}: expected {DFMF_MAGIC!r} (a UBO2014 DFMF .btf file)")
    rotations_included = cur.pos < size and bytes(buf[cur.pos:cur.pos + 1]) == b"R"
    if rotations_included:
        cur.pos += 1
    return rotations_included


def _parse_header(path: Path, buf, size: int) -> tuple[DFMFHeader, int]:
    """Parse and validate every header field; returns the header and the end offset of the data."""
    cur = _Cursor(path, buf, size)
    rotations_included = _check_magic(cur, buf, size)

    start = cur.pos
    hsize, version, setup, sensor, light_src, ppmm, r, g, b = _COMMON_HEADER.unpack(
        cur.take(_COMMON_HEADER.size, "common header"))
    if version not in DFMF_VERSIONS:
        cur.fail(f"unsupported DFMF version {version}: this reader supports versions "
                 f"{min(DFMF_VERSIONS)}..{max(DFMF_VERSIONS)} (the common header's layout differs between versions)")
    if not np.isfinite([ppmm, r, g, b]).all():
        cur.fail("common header: ppmm or RGB scale contains NaN or infinite values")
    cosine_flag, xml, names = 0, "", ["R", "G", "B"]
    if version > 1:
        cosine_flag = cur.u32("cosine flag")
    if version > 2:
        n = cur.count("XML string length", item_bytes=1)
        xml = cur.text(n, "XML string")
    if version > 3:
        n_channels = cur.count("channel count", item_bytes=4)
        if n_channels != 3:
            cur.fail(f"channel count is {n_channels}; only 3-channel (colour) files are supported")
        names = []
        for k in range(n_channels):
            n = cur.count(f"length of channel name {k}", item_bytes=1)
            names.append(cur.text(n, f"channel name {k}"))
    if cur.pos - start != hsize:
        cur.fail(f"common header size field says {hsize} bytes but version {version}'s fields take "
                 f"{cur.pos - start} bytes (corrupt header or unsupported version)")

    n_views = cur.count("view count", minimum=1, item_bytes=12)
    view_angles = np.empty((n_views, 2))
    light_angles = None
    for v in range(n_views):
        view_angles[v] = cur.f32(2, f"angles of view {v}")
        n_lights = cur.count(f"light count of view {v}", minimum=1, item_bytes=8)
        if light_angles is None:
            light_angles = cur.f32(2 * n_lights, "light angles").reshape(n_lights, 2)
        elif n_lights != len(light_angles):
            cur.fail(f"light count of view {v} is {n_lights} but view 0 has {len(light_angles)} lights "
                     f"(sizes disagree)")
        else:
            cur.skip(8 * n_lights, f"light angles of view {v}")
    _check_angles(cur, view_angles, "view")
    _check_angles(cur, light_angles, "light")

    width = cur.count("width", minimum=1, maximum=1 << 20)
    height = cur.count("height", minimum=1, maximum=1 << 20)
    rotations = np.zeros((0, 3, 3))
    if rotations_included:
        n = cur.count("rotation count", item_bytes=36)
        rotations = cur.f32(9 * n, "rotations").reshape(n, 3, 3)

    components = cur.u32("component count")
    colour_model = cur.u32("colour model")
    if colour_model not in COLOUR_MODELS:
        cur.fail(f"unsupported colour model {colour_model}; supported: "
                 + ", ".join(f"{k} ({v})" for k, v in COLOUR_MODELS.items()))
    colour_mean = cur.f32(3, "colour mean")
    colour_transform = cur.f32(9, "colour transform").reshape(3, 3)

    rows, cols = n_views * len(light_angles), width * height
    channels = []
    for c in range(len(names)):
        scalar_size = cur.u8(f"scalar size of channel {c}")
        if scalar_size not in SCALAR_TYPES:
            cur.fail(f"scalar size of channel {c} is {scalar_size}; expected 2 (half), 4 (float) or 8 (double)")
        n_comp = cur.count(f"component count of channel {c}", minimum=1)
        n_rows = cur.u32(f"row count of channel {c}")
        n_cols = cur.u32(f"column count of channel {c}")
        if n_rows != rows:
            cur.fail(f"row count of channel {c} is {n_rows} but n_views * n_lights = {n_views} * "
                     f"{len(light_angles)} = {rows} (sizes disagree)")
        if n_cols != cols:
            cur.fail(f"column count of channel {c} is {n_cols} but width * height = {width} * {height} = "
                     f"{cols} (sizes disagree)")
        sv = cur.skip(n_comp * scalar_size, f"singular values of channel {c}")
        u = cur.skip(rows * n_comp * scalar_size, f"U matrix of channel {c} ({rows} x {n_comp})")
        sxv = cur.skip(cols * n_comp * scalar_size, f"SxV matrix of channel {c} ({cols} x {n_comp})")
        channels.append(_ChannelLayout(scalar_size, n_comp, rows, cols, sv, u, sxv))
    if cur.pos != size:
        cur.fail(f"{size - cur.pos} unexpected bytes after the last channel's data (offset {cur.pos}); "
                 f"the header's sizes disagree with the file size")
    header = DFMFHeader(
        version=version, rotations_included=rotations_included,
        measurement_setup=setup.split(b"\0", 1)[0].decode("latin-1"),
        image_sensor=sensor.split(b"\0", 1)[0].decode("latin-1"),
        light_source=light_src.split(b"\0", 1)[0].decode("latin-1"),
        ppmm=float(ppmm), rgb_scale=(float(r), float(g), float(b)), cosine_flag=cosine_flag, xml=xml,
        channel_names=names, view_angles=view_angles, light_angles=light_angles, width=width,
        height=height, rotations=rotations, components=components, colour_model=colour_model,
        colour_mean=colour_mean, colour_transform=colour_transform, channels=channels)
    return header, cur.pos


def _angles_to_vectors(angles: np.ndarray) -> np.ndarray:
    return spherical_to_direction(np.degrees(angles[:, 0]), np.degrees(angles[:, 1]))


class UBO2014BTF(BTFSource):
    """A UBO2014 DFMF ``.btf`` file, its factors read on demand and decoded image by image.

    Parameters
    ----------
    path : str or Path
        The ``.btf`` file.
    check_payload : bool
        Scan the ``U`` and ``SxV`` factors for NaN/Inf when opening (default
        True; reads the factors once, in chunks). Decoded images are always
        checked.
    factor_cache_bytes : int
        The ``SxV`` factors (what every image decode reads in full) are
        converted once to float32 (float64 for double files) and kept in memory
        when they fit in this many bytes (default 1 GiB; ``0`` disables):
        single-image decodes of half files are faster so
        (``benchmarks/btf_decode_speed.py``). Otherwise they are read and
        converted chunk by chunk on every decode. The rows of ``U`` a decode
        needs are read from the file each time.

    Attributes
    ----------
    header : DFMFHeader
        Every header field.
    views, lights : float64 ``(N, 3)``
        Unit vectors from the stored (theta, phi) radians.

    Raises
    ------
    FormatError
        Missing file, bad magic, truncated or inconsistent header, unsupported
        colour model or scalar size, directions below the horizon, NaN/Inf.
    """

    def __init__(self, path, *, check_payload: bool = True, factor_cache_bytes: int = 1 << 30):
        super().__init__()
        self.path = require_file(path, "a UBO2014 .btf file")
        self._file = OpenFile(self.path)
        size = self._file.size
        if size == 0:
            self._file.close()
            raise FormatError(self.path, "empty file (expected a UBO2014 .btf file)")
        try:
            self.header, _ = _parse_header(self.path, self._file, size)
        except BaseException:
            self._file.close()
            raise
        h = self.header
        self.height, self.width = h.height, h.width
        self.views = _angles_to_vectors(h.view_angles)
        self.lights = _angles_to_vectors(h.light_angles)
        self.name = self.path.name
        self._u = [self._file.array(c.u_offset, (c.rows, c.components), SCALAR_TYPES[c.scalar_size])
                   for c in h.channels]
        self._sxv = [self._file.array(c.sxv_offset, (c.cols, c.components), SCALAR_TYPES[c.scalar_size])
                     for c in h.channels]
        if check_payload:
            self._check_payload()
        self._compute = [np.float64 if m.dtype.itemsize == 8 else np.float32 for m in self._sxv]
        cache_bytes = sum(m.size * np.dtype(t).itemsize for m, t in zip(self._sxv, self._compute))
        self._cache_sxv = cache_bytes <= factor_cache_bytes
        self._sxv_cached: list[np.ndarray] | None = None
        self._texel_factor_cache: dict = {}
        self.metadata = {
            "format": "ubo2014-dfmf",
            "path": str(self.path),
            "version": h.version,
            "colour_model": h.colour_model,
            "scalar_bytes": h.channels[0].scalar_size,
            "components": [c.components for c in h.channels],
            "cosine_flag": h.cosine_flag,
            "measurement_setup": h.measurement_setup,
            "image_sensor": h.image_sensor,
            "light_source": h.light_source,
            "ppmm": h.ppmm,
            "colour_mean": h.colour_mean.tolist(),
            "colour_transform": h.colour_transform.tolist(),
            "file_bytes": size,
        }

    def _check_payload(self) -> None:
        for c, (u, sxv) in enumerate(zip(self._u, self._sxv)):
            for what, m in (("U", u), ("SxV", sxv)):
                step = max(1, _CHUNK_BYTES // max(1, m.shape[1] * m.itemsize))
                for a in range(0, len(m), step):
                    if not np.isfinite(m[a:a + step]).all():
                        raise FormatError(self.path, f"{what} matrix of channel {c} contains NaN or infinite "
                                                     f"values (rows {a}..{min(a + step, len(m)) - 1})")

    def close(self) -> None:
        self._u, self._sxv, self._sxv_cached, self._texel_factor_cache = [], [], None, {}
        self._file.close()

    def _u_rows(self, c: int, rows: np.ndarray) -> np.ndarray:
        """Rows ``rows`` of channel ``c``'s ``U`` in the compute dtype ``(len(rows), C)``."""
        return np.asarray(self._u[c][rows], dtype=self._compute[c])

    def _sxv_blocks(self, c: int):
        """``(start, block)`` pieces of channel ``c``'s SxV in the compute dtype."""
        if self._cache_sxv:
            if self._sxv_cached is None:
                self._sxv_cached = [np.asarray(m, dtype=t) for m, t in zip(self._sxv, self._compute)]
            yield 0, self._sxv_cached[c]
            return
        sxv = self._sxv[c]
        step = max(1, _CHUNK_BYTES // max(1, sxv.shape[1] * 4))
        for a in range(0, sxv.shape[0], step):
            yield a, np.asarray(sxv[a:a + step], dtype=self._compute[c])

    # ------------------------------------------------------------------ decoding
    def _decode_rows(self, rows: np.ndarray) -> np.ndarray:
        """Decode file rows (``view * n_lights + light``) -> ``(k, H, W, 3)`` float32."""
        if not self._u:
            raise InputError(f"{self.path}: the file was closed")
        k = len(rows)
        with np.errstate(over="ignore", invalid="ignore"):  # corrupt factors: caught by the check below
            out = np.empty((k, self.height * self.width, 3), dtype=np.float32)
            for c in range(len(self._u)):
                coeff = self._u_rows(c, rows)  # (k, C)
                for a, block in self._sxv_blocks(c):  # block: (n, C)
                    out[:, a:a + len(block), c] = coeff @ block.T
            out = out.reshape(k, self.height, self.width, 3)[:, ::-1]  # file rows bottom-up -> ours top-down
            if self.header.colour_model == 11:
                out = _log_yuv_to_rgb(out)
            if self.header.cosine_flag:
                cos_l = np.maximum(self.lights[rows % self.n_lights, 2], _MIN_COS_LIGHT).astype(np.float32)
                out = out / cos_l[:, None, None, None]
        if not np.isfinite(out).all():
            raise FormatError(self.path, "decoded values are not finite (overflow in the stored factors)")
        return np.ascontiguousarray(out, dtype=np.float32)

    def _read_image(self, view_index: int, light_index: int) -> np.ndarray:
        return self._decode_rows(np.array([view_index * self.n_lights + light_index]))[0]

    def _texel_factors(self, device):
        """Per channel, ``SxV`` with rows in dynbtf's texel order (row 0 at the top) as torch tensors on
        ``device`` in the compute dtype, when the cache is enabled (else None). Built once per device."""
        if not self._cache_sxv:
            return None
        import torch

        key = str(device)
        if key not in self._texel_factor_cache:
            h, w = self.height, self.width
            ours = []
            for m, t in zip(self._sxv, self._compute):
                flipped = np.asarray(m, dtype=t).reshape(h, w, -1)[::-1].reshape(h * w, -1)
                ours.append(torch.from_numpy(np.ascontiguousarray(flipped)).to(device))
            self._texel_factor_cache[key] = ours
        return self._texel_factor_cache[key]

    def _file_texels(self, texels: np.ndarray) -> np.ndarray:
        """dynbtf flat texel indices -> the file's (rows stored bottom-up)."""
        row, col = np.divmod(texels, self.width)
        return (self.height - 1 - row) * self.width + col

    def _read_texels(self, pairs: np.ndarray, texels: np.ndarray, device=None):
        """Texels of images from the factors: per channel ``U[pair rows] @ SxV[texels].T`` (no whole images).

        Runs in torch on ``device`` (default CPU): the matrix product is the whole cost, so on CUDA it runs
        there. Texel runs that are contiguous (blocks) are read as slices of the factor cache.
        """
        import torch

        if not self._u:
            raise InputError(f"{self.path}: the file was closed")
        device = torch.device("cpu") if device is None else torch.device(device)
        groups, b = pairs.shape[:2]
        n = texels.shape[1]
        rows = (pairs[..., 0] * self.n_lights + pairs[..., 1]).reshape(-1)
        factors = self._texel_factors(device)
        channels = []
        for c in range(len(self._u)):
            coeff = torch.from_numpy(self._u_rows(c, rows)).to(device)
            coeff = coeff.reshape(groups, b, -1)
            values = torch.empty((groups, b, n), dtype=coeff.dtype, device=device)
            for g in range(groups):
                for lo, hi, block in self._factor_pieces(c, factors, texels[g], device):
                    torch.matmul(coeff[g], block.T, out=values[g, :, lo:hi])
            channels.append(values)
        out = torch.stack(channels, dim=-1)
        if self.header.colour_model == 11:
            out = _log_yuv_to_rgb(out)
        if self.header.cosine_flag:
            cos_l = np.maximum(self.lights[pairs[..., 1], 2], _MIN_COS_LIGHT)
            out = out / torch.as_tensor(cos_l, dtype=out.dtype, device=device)[..., None, None]
        out = out.to(torch.float32)
        # a NaN or infinity anywhere makes the sum non-finite (one cheap pass); only then is every value checked
        if not bool(torch.isfinite(out.sum())) and not bool(torch.isfinite(out).all()):
            raise FormatError(self.path, "decoded values are not finite (overflow in the stored factors)")
        return out

    def _factor_pieces(self, c: int, factors, texels: np.ndarray, device):
        """``(lo, hi, SxV rows)`` pieces covering ``texels`` (positions ``lo:hi`` of the request): slices of the
        cache for contiguous runs, else gathered rows; bounded chunks from the file when nothing is cached."""
        import torch

        n = len(texels)
        if factors is not None:
            sxv = factors[c]
            cuts = np.flatnonzero(np.diff(texels) != 1) + 1
            if len(cuts) <= 2:  # one block, or one wrapping round the end of the image: slices, no copy
                for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, n]):
                    # in cache-sized pieces: one long product was slower (measured at full size)
                    for a in range(int(lo), int(hi), _TEXELS_PER_PRODUCT):
                        z = min(a + _TEXELS_PER_PRODUCT, int(hi))
                        start = int(texels[lo]) + a - int(lo)
                        yield a, z, sxv[start:start + z - a]
                return
            yield 0, n, sxv.index_select(0, torch.from_numpy(texels).to(device))
            return
        step = max(1, _CHUNK_BYTES // max(1, self._sxv[c].shape[1] * 4))
        for lo in range(0, n, step):
            file_rows = self._file_texels(texels[lo:lo + step])
            block = np.asarray(self._sxv[c][file_rows], dtype=self._compute[c])
            yield lo, lo + len(file_rows), torch.from_numpy(block).to(device)

    def view_images(self, view_index: int, light_indices=None) -> np.ndarray:
        """Images of one view for several lights, ``(L, H, W, 3)`` float32 (default all lights).

        One matrix product per channel for all requested lights: much faster per
        image than :meth:`image` when streaming a whole BTF.
        """
        v, _ = self._check_pair(view_index, 0)
        lights = np.arange(self.n_lights) if light_indices is None else np.asarray(light_indices, np.int64).reshape(-1)
        for l in lights:
            self._check_pair(v, l)
        return self._decode_rows(v * self.n_lights + lights)


def _log_yuv_to_rgb(c):
    """Colour model 11: log-YUV channel values ``(..., 3)`` -> RGB clamped to ``[0, 1]``.

    ``c`` is a NumPy array (returns float32) or a torch tensor (returns its dtype, on its device).
    """
    if not isinstance(c, np.ndarray):
        import torch

        y = torch.exp(c[..., 0]) - _DRR_EPS
        u = c[..., 1] * y + _DRR_EPS
        v = c[..., 2] * y + _DRR_EPS
        rgb = torch.stack([y + 1.13983 * v, y - 0.39465 * u - 0.5806 * v, y + 2.03211 * u], dim=-1)
        return rgb.clamp(0.0, 1.0)  # NaN stays NaN, caught by the caller's finite check
    with np.errstate(over="ignore", invalid="ignore"):
        y = np.exp(c[..., 0]) - _DRR_EPS
        u = c[..., 1] * y + _DRR_EPS
        v = c[..., 2] * y + _DRR_EPS
        rgb = np.stack([y + 1.13983 * v, y - 0.39465 * u - 0.5806 * v, y + 2.03211 * u], axis=-1)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


_YUV_TO_RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])


def _rgb_to_log_yuv(rgb: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_log_yuv_to_rgb` for RGB in ``[0, 1]`` ``(..., 3)`` -> channel values."""
    yuv = np.clip(rgb, 0.0, 1.0).astype(np.float64) @ np.linalg.inv(_YUV_TO_RGB).T
    y = np.maximum(yuv[..., 0], 0.0)
    y_safe = np.maximum(y, 1e-4)  # black texels: chroma is irrelevant, keep the ratios bounded
    return np.stack([np.log(y + _DRR_EPS), (yuv[..., 1] - _DRR_EPS) / y_safe,
                     (yuv[..., 2] - _DRR_EPS) / y_safe], axis=-1)


def read_ubo2014(path, **kwargs) -> UBO2014BTF:
    """Open a UBO2014 ``.btf`` file (see :class:`UBO2014BTF`)."""
    return UBO2014BTF(path, **kwargs)


def btf_extractor_angles(source: BTFSource, view_index: int, light_index: int) -> tuple[float, float, float, float]:
    """btf-extractor's angle tuple ``(theta_l, phi_l, theta_v, phi_v)`` in degrees (unrounded).

    btf-extractor rounds these to one decimal for its ``angles_set`` keys.
    """
    tl, pl = direction_to_spherical(source.lights[light_index])
    tv, pv = direction_to_spherical(source.views[view_index])
    return float(tl), float(pl), float(tv), float(pv)


def _truncated_svd(m: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rank-``k`` SVD of ``m`` (rows x cols): ``U (rows, k)``, ``s (k,)``, ``SxV (cols, k)``.

    Exact LAPACK SVD for small matrices; otherwise the eigen-decomposition of
    the Gram matrix on the smaller side (deterministic, and fast when ``k`` is
    much smaller than the matrix: one ``m^T m`` product and one symmetric
    eigen-solve). Either way ``U @ SxV.T`` is the projection of ``m`` onto its
    top ``k`` singular vectors.
    """
    k = min(k, *m.shape)
    if min(m.shape) <= 512:
        u, s, vt = np.linalg.svd(m, full_matrices=False)
        return u[:, :k], s[:k], vt[:k].T * s[:k]
    from scipy.linalg import eigh

    def top_eigenvectors(gram):
        n = len(gram)
        evals, evecs = eigh(gram, subset_by_index=[n - k, n - 1])  # ascending
        return np.sqrt(np.maximum(evals[::-1], 0.0)), evecs[:, ::-1]

    if m.shape[0] < m.shape[1]:  # left singular vectors from m m^T
        s, u = top_eigenvectors(m @ m.T)
        return u, s, m.T @ u
    s, v = top_eigenvectors(m.T @ m)  # right singular vectors from m^T m
    mv = m @ v
    u = np.divide(mv, s, out=np.zeros_like(mv), where=s > s[0] * 1e-12)
    return u, s, v * s


def write_ubo2014(path, source_or_arrays, *, components: int = 16, scalar: str = "half",
                  colour_model: int = 0, version: int = 3, views=None, lights=None,
                  max_bytes: int = 2 << 30, method: str = "auto", oversample: int = 16, seed: int = 0,
                  progress: bool = False) -> Path:
    """Compress a BTF into a UBO2014 DFMF ``.btf`` file, written atomically.

    Each colour channel's ``(n_views * n_lights) x (H * W)`` matrix is replaced by
    its rank-``components`` truncated SVD, stored as ``U`` and ``SxV = V S``.
    Two methods:

    * ``"exact"``: the whole BTF is held in memory as float64 and factored exactly
      (small BTFs: tests and hand-over to other tools);
    * ``"randomized"``: the images are streamed twice through a randomized SVD
      (Halko, Martinsson and Tropp 2011, algorithm 4.1 without power iterations):
      pass 1 projects every image on ``components + oversample`` random texel
      combinations (a seeded Gaussian ``Omega``, ``cols x k'``) giving ``Y = A Omega``,
      whose orthonormal basis ``Q`` spans the rows' dominant subspace; pass 2
      accumulates ``B = Q^T A`` (``k' x cols``), and ``B``'s small SVD gives the
      factors. Memory: ``Omega``, ``B`` and ``Q`` (float64 ``Omega`` and ``B``: about
      ``2 x cols x k' x 8`` bytes per channel) plus one view's images, never the BTF:
      a 400 x 400 texel, 151 x 151 direction BTF at 96 components needs ~1 GB.

    ``"auto"`` (default) is exact when the float64 matrices fit ``max_bytes``.

    Parameters
    ----------
    path : str or Path
        Output ``.btf`` file.
    source_or_arrays : BTFSource or array ``(n_views, n_lights, H, W, 3)``
        The BTF (linear RGB); an array needs ``views`` and ``lights``.
    components : int
        Components ``C`` per channel (clipped to the matrix rank bound); default 16.
    scalar : ``"half"``, ``"float"`` or ``"double"``
        Stored scalar type (default ``"half"``, as UBO2014).
    colour_model : 0 or 11
        0 stores RGB; 11 stores log-YUV (values are clamped to ``[0, 1]`` on
        reading, as btf-extractor does, so use it only for values in ``[0, 1]``).
    version : int
        Common-header version 1..4 (default 3: cosine flag 0 and an XML
        provenance string; 4 adds channel names "R", "G", "B").
    views, lights : arrays ``(N, 3)``, only with an array input.
    max_bytes : int
        The exact method refuses BTFs whose float64 matrices exceed this (default 2 GiB).
    method : ``"auto"``, ``"exact"`` or ``"randomized"``
        See above.
    oversample : int
        Extra random directions of the randomized method (default 16).
    seed : int
        Seed of the randomized method's Gaussian test matrix (same seed: same file).
    progress : bool
        Show a tqdm progress bar while reading the source (views, rate, ETA).

    Returns
    -------
    Path : the file written. Our reader returns images equal to the input up to
    the SVD truncation and the scalar precision.
    """
    source = _writable_source(source_or_arrays, views, lights)
    _check_write_options(source, components=components, scalar=scalar, colour_model=colour_model, version=version,
                         method=method)
    matrix_bytes = source.n_pairs * source.height * source.width * 3 * 8
    if method == "randomized" or (method == "auto" and matrix_bytes > max_bytes):
        return _write_ubo2014_randomized(path, source, int(components), scalar=scalar, colour_model=colour_model,
                                         version=version, oversample=oversample, seed=seed, progress=progress)
    if matrix_bytes > max_bytes:
        raise InputError(f"write_ubo2014: {source.name} needs {matrix_bytes / 2**30:.2f} GiB while "
                         f"compressing exactly (max_bytes={max_bytes}); use method='randomized' (bounded memory)")
    factors = _exact_factors(source, int(components), colour_model=colour_model, progress=progress)
    provenance = (f'<dynbtf source="{source.name}" writer="dynbtf.data.ubo2014.write_ubo2014" '
                  f'components="{components}" scalar="{scalar}"/>')
    return write_dfmf_factors(path, source.views, source.lights, source.height, source.width,
                              [f[0] for f in factors], [f[2] for f in factors],
                              singular_values=[f[1] for f in factors], scalar=scalar,
                              colour_model=colour_model, version=version, xml=provenance)


def _writable_source(source_or_arrays, views, lights) -> BTFSource:
    """The BTF to write: a :class:`BTFSource` as is, an array ``(n_views, n_lights, H, W, 3)`` with its
    ``views, lights (N, 3)`` as an :class:`ArrayBTF` (:class:`InputError` when they are missing or invalid)."""
    if isinstance(source_or_arrays, BTFSource):
        return source_or_arrays
    if views is None or lights is None:
        raise InputError("write_ubo2014: an array input needs views= and lights= direction arrays")
    try:
        return ArrayBTF(source_or_arrays, views, lights, name="array")
    except DynBTFError:
        raise
    except ValueError as e:  # check_directions' plain ValueError names the argument
        raise InputError(f"write_ubo2014: {e}") from None


def _check_write_options(source: BTFSource, *, components: int, scalar: str, colour_model: int, version: int,
                         method: str) -> None:
    """:class:`InputError` for options :func:`write_ubo2014` does not know, and for directions below the
    horizon (a ``.btf`` file stores (theta, phi) of the upper hemisphere)."""
    if scalar not in _SCALAR_NAMES:
        raise InputError(f"scalar: expected one of {sorted(_SCALAR_NAMES)}, got {scalar!r}")
    if colour_model not in COLOUR_MODELS:
        raise InputError(f"colour_model: expected one of {sorted(COLOUR_MODELS)}, got {colour_model!r}")
    if int(components) < 1:
        raise InputError(f"components: expected a positive integer, got {components!r}")
    if version not in DFMF_VERSIONS:
        raise InputError(f"version: expected one of {DFMF_VERSIONS}, got {version!r}")
    if (source.views[:, 2] < -1e-6).any() or (source.lights[:, 2] < -1e-6).any():
        raise InputError(f"{source.name}: directions below the horizon cannot be stored in a .btf file")
    if method not in ("auto", "exact", "randomized"):
        raise InputError(f"method: expected 'auto', 'exact' or 'randomized', got {method!r}")


def _exact_factors(source: BTFSource, components: int, *, colour_model: int, progress: bool
                   ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Exact rank-``components`` SVD (:func:`_truncated_svd`) of each channel's float64 matrix, read whole.

    Rows: the ``n_views * n_lights`` images, view-major; columns: the ``H * W`` texels in file order (rows
    bottom-up); values RGB, or log-YUV for ``colour_model`` 11. Returns per channel ``(U, s, SxV)``.
    """
    rows, cols = source.n_pairs, source.height * source.width
    matrix = np.empty((rows, source.height, source.width, 3), dtype=np.float64)
    view_images = getattr(source, "view_images", None)  # all lights of a view at once, when offered
    from ..progress import progress_bar
    for v in progress_bar(range(source.n_views), unit="view", desc=f"reading {source.name}", disable=not progress):
        images = view_images(v) if view_images is not None else [source.image(v, l) for l in range(source.n_lights)]
        matrix[v * source.n_lights:(v + 1) * source.n_lights] = np.asarray(images)[:, ::-1]
    if colour_model == 11:
        matrix = _rgb_to_log_yuv(matrix)
    matrix = matrix.reshape(rows, cols, 3)
    return [_truncated_svd(np.ascontiguousarray(matrix[:, :, c]), components) for c in range(3)]


def _write_ubo2014_randomized(path, source: BTFSource, components: int, *, scalar: str, colour_model: int,
                              version: int, oversample: int, seed: int, progress: bool) -> Path:
    """Streamed randomized SVD of the three channel matrices (see :func:`write_ubo2014`)."""
    from ..progress import progress_bar
    rows, cols = source.n_pairs, source.height * source.width
    k = min(components, rows, cols)
    width = min(k + max(int(oversample), 0), rows, cols)
    rng = np.random.default_rng([int(seed), 0xDF3F])
    omega = [rng.standard_normal((cols, width)).astype(np.float32) for _ in range(3)]
    view_images = getattr(source, "view_images", None)

    def views_in_file_order(desc: str):
        """Per view: its ``(L, cols, 3)`` float64 channel values, texels in file order (rows bottom-up)."""
        for v in progress_bar(range(source.n_views), unit="view", desc=desc, disable=not progress):
            images = view_images(v) if view_images is not None else \
                np.stack([source.image(v, l) for l in range(source.n_lights)])
            values = np.asarray(images, dtype=np.float32)[:, ::-1].reshape(source.n_lights, cols, 3)
            if colour_model == 11:
                values = _rgb_to_log_yuv(values).astype(np.float32)
            yield v, values

    n_lights = source.n_lights
    y = [np.empty((rows, width)) for _ in range(3)]
    for v, values in views_in_file_order(f"{source.name}: range (pass 1/2)"):
        for c in range(3):
            y[c][v * n_lights:(v + 1) * n_lights] = np.ascontiguousarray(values[..., c]) @ omega[c]
    del omega
    q = [np.linalg.qr(m)[0] for m in y]
    del y
    b = [np.zeros((width, cols)) for _ in range(3)]
    for v, values in views_in_file_order(f"{source.name}: projection (pass 2/2)"):
        for c in range(3):
            b[c] += q[c][v * n_lights:(v + 1) * n_lights].T @ np.ascontiguousarray(values[..., c], dtype=np.float64)
    u, sxv, singular = [], [], []
    for c in range(3):
        ub, s, vt = np.linalg.svd(b[c], full_matrices=False)
        b[c] = None
        u.append(q[c] @ ub[:, :k])
        singular.append(s[:k])
        sxv.append(vt[:k].T * s[:k])
    provenance = (f'<dynbtf source="{source.name}" writer="dynbtf.data.ubo2014.write_ubo2014" '
                  f'components="{k}" scalar="{scalar}" method="randomized" oversample="{oversample}" seed="{seed}"/>')
    return write_dfmf_factors(path, source.views, source.lights, source.height, source.width, u, sxv,
                              singular_values=singular, scalar=scalar, colour_model=colour_model, version=version,
                              xml=provenance)


def write_dfmf_factors(path, views, lights, height: int, width: int, u, sxv, *, singular_values=None,
                       scalar: str = "half", colour_model: int = 0, version: int = 3, xml: str = "") -> Path:
    """Write given SVD factors as a DFMF file, atomically (the layout of the module docstring).

    Parameters
    ----------
    path : str or Path
        Output ``.btf`` file.
    views, lights : float ``(n_views, 3)``, ``(n_lights, 3)``
        Unit vectors (upper hemisphere), stored as (theta, phi) radians.
    height, width : int
        Image size in texels.
    u : three arrays ``(n_views * n_lights, C_c)``
        Per channel (R, G, B; or log-YUV for ``colour_model=11``), rows view-major.
    sxv : three arrays ``(height * width, C_c)``
        Per channel; texel ``k`` is file row ``k // width`` (rows bottom-up:
        our image row ``i`` is file row ``height - 1 - i``), column ``k % width``.
    singular_values : three arrays ``(C_c,)``, optional
        Stored for reference only (readers use ``U`` and ``SxV``); ones by default.
    scalar, colour_model, version : as for :func:`write_ubo2014`.
    xml : str
        Provenance string stored in the header (version >= 3).
    """
    if scalar not in _SCALAR_NAMES:
        raise InputError(f"scalar: expected one of {sorted(_SCALAR_NAMES)}, got {scalar!r}")
    if colour_model not in COLOUR_MODELS:
        raise InputError(f"colour_model: expected one of {sorted(COLOUR_MODELS)}, got {colour_model!r}")
    if version not in DFMF_VERSIONS:
        raise InputError(f"version: expected one of {DFMF_VERSIONS}, got {version!r}")
    views, lights = np.asarray(views, dtype=np.float64), np.asarray(lights, dtype=np.float64)
    for what, w in (("views", views), ("lights", lights)):
        if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0:
            raise InputError(f"{what}: expected an (N, 3) array of unit vectors, got shape {w.shape}")
        if (w[:, 2] < -1e-6).any():
            raise InputError(f"{what}: directions below the horizon cannot be stored in a .btf file")
    rows, cols = len(views) * len(lights), int(height) * int(width)
    if len(u) != 3 or len(sxv) != 3:
        raise InputError("u, sxv: expected one factor matrix per colour channel (3 each)")
    for c in range(3):
        if u[c].ndim != 2 or sxv[c].ndim != 2 or u[c].shape[1] != sxv[c].shape[1] or u[c].shape[1] < 1:
            raise InputError(f"channel {c}: U and SxV must be 2-D with the same positive number of columns, "
                             f"got {u[c].shape} and {sxv[c].shape}")
        if u[c].shape[0] != rows or sxv[c].shape[0] != cols:
            raise InputError(f"channel {c}: expected U with {rows} rows (views x lights) and SxV with {cols} rows "
                             f"(height x width), got {u[c].shape[0]} and {sxv[c].shape[0]}")
    size = _SCALAR_NAMES[scalar]
    dtype = SCALAR_TYPES[size]

    def angles(w):
        theta, phi = direction_to_spherical(w)
        return np.stack([np.radians(theta), np.radians(phi)], axis=1).astype("<f4")

    view_angles, light_angles = angles(views), angles(lights)
    xml_bytes = xml.encode()
    extra = b""
    if version > 1:
        extra += struct.pack("<I", 0)  # cosine flag: values exclude cos(theta_light)
    if version > 2:
        extra += struct.pack("<I", len(xml_bytes)) + xml_bytes
    if version > 3:
        extra += struct.pack("<I", 3) + b"".join(struct.pack("<I", 1) + n for n in (b"R", b"G", b"B"))
    common = _COMMON_HEADER.pack(_COMMON_HEADER.size + len(extra), version, b"dynbtf", b"", b"",
                                 0.0, 1.0, 1.0, 1.0) + extra

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(DFMF_MAGIC)
        f.write(common)
        f.write(struct.pack("<I", len(views)))
        lights_block = struct.pack("<I", len(lights)) + light_angles.tobytes()
        for v in range(len(views)):
            f.write(view_angles[v].tobytes() + lights_block)
        f.write(struct.pack("<II", int(width), int(height)))
        f.write(struct.pack("<II", max(m.shape[1] for m in u), colour_model))
        f.write(np.zeros(3, "<f4").tobytes() + np.eye(3, dtype="<f4").tobytes())
        for c in range(3):
            k = u[c].shape[1]
            s = np.ones(k) if singular_values is None else np.asarray(singular_values[c])
            f.write(struct.pack("<BIII", size, k, rows, cols))
            f.write(s.astype(dtype).tobytes())
            f.write(np.ascontiguousarray(u[c], dtype=dtype).tobytes())
            f.write(np.ascontiguousarray(sxv[c], dtype=dtype).tobytes())
        f.flush()
        os.fsync(f.fileno())
    return path

