"""Independent test-side code for UBO2014 DFMF files: a byte builder and a brute-force decoder.

Written from the format description in the notes (and btf-extractor's loader
behaviour), with ``struct`` and plain Python loops only, sharing no code with
:mod:`dynbtf.data.ubo2014`, so the reader can be checked against it.
"""

from __future__ import annotations

import math
import struct

import numpy as np

_FMT = {2: "e", 4: "f", 8: "d"}


def dfmf_bytes(view_angles, light_angles, width, height, u_list, sxv_list, *, scalar_size=4, colour_model=0,
               version=1, rotations=None, cosine_flag=0, channel_names=None, xml=b"") -> bytes:
    """Build a DFMF file: angles in radians ``(N, 2)``; ``u_list[c]`` (rows, C), ``sxv_list[c]`` (W*H, C)."""
    out = bytearray(b"!DFMF08FC")
    if rotations is not None:
        out += b"R"
    extra = b""
    if version > 1:
        extra += struct.pack("<I", cosine_flag)
    if version > 2:
        extra += struct.pack("<I", len(xml)) + xml
    if version > 3:
        names = channel_names or [b"R", b"G", b"B"]
        extra += struct.pack("<I", len(names)) + b"".join(struct.pack("<I", len(n)) + n for n in names)
    common = struct.pack("<II80s80s80sf3f", 264 + len(extra), version, b"setup", b"sensor", b"light", 0.1,
                         1.0, 1.0, 1.0)
    out += common + extra
    out += struct.pack("<I", len(view_angles))
    for theta, phi in view_angles:
        out += struct.pack("<ff", theta, phi) + struct.pack("<I", len(light_angles))
        for lt, lp in light_angles:
            out += struct.pack("<ff", lt, lp)
    out += struct.pack("<II", width, height)
    if rotations is not None:
        out += struct.pack("<I", len(rotations))
        for r in rotations:
            out += struct.pack("<9f", *np.asarray(r, dtype=float).ravel())
    out += struct.pack("<II", u_list[0].shape[1], colour_model) + struct.pack("<3f", 0, 0, 0)
    out += struct.pack("<9f", 1, 0, 0, 0, 1, 0, 0, 0, 1)
    f = "<" + _FMT[scalar_size]
    for u, sxv in zip(u_list, sxv_list):
        c = u.shape[1]
        out += struct.pack("<BIII", scalar_size, c, u.shape[0], sxv.shape[0])
        out += b"".join(struct.pack(f, 1.0) for _ in range(c))
        out += np.ascontiguousarray(u, dtype=f).tobytes()
        out += np.ascontiguousarray(sxv, dtype=f).tobytes()
    return bytes(out)


class _Bytes:
    def __init__(self, data: bytes):
        self.data, self.pos = data, 0

    def read(self, fmt: str):
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += struct.calcsize("<" + fmt)
        return values


def reference_decode(path, view_index: int, light_index: int):
    """Decode one image the slow, obvious way; returns ``(rgb (H, W, 3) list-based array, views, lights)``.

    Texel ``(row i, col j)`` of the returned image is file texel ``(H - 1 - i) * W + j``
    (btf-extractor's vertical flip); channels are in file order (R, G, B).
    Directions are returned as lists of (theta, phi) in radians.
    """
    with open(path, "rb") as f:
        data = f.read()
    b = _Bytes(data)
    assert data[:9] == b"!DFMF08FC"
    b.pos = 9
    if data[9:10] == b"R":
        b.pos += 1
        rotations = True
    else:
        rotations = False
    size, version = b.read("II")
    b.pos += 240 + 16
    cosine = 0
    if version > 1:
        (cosine,) = b.read("I")
    if version > 2:
        (n,) = b.read("I")
        b.pos += n
    if version > 3:
        (nc,) = b.read("I")
        for _ in range(nc):
            (n,) = b.read("I")
            b.pos += n
    (n_views,) = b.read("I")
    views, lights = [], []
    for v in range(n_views):
        views.append(b.read("ff"))
        (n_lights,) = b.read("I")
        these = [b.read("ff") for _ in range(n_lights)]
        if v == 0:
            lights = these
    width, height = b.read("II")
    if rotations:
        (n,) = b.read("I")
        b.pos += 36 * n
    _, colour_model = b.read("II")
    b.pos += 48
    row = view_index * len(lights) + light_index
    channels = []
    for _ in range(3):
        scalar_size, c, rows, cols = b.read("BIII")
        f = _FMT[scalar_size]
        b.pos += c * scalar_size
        u_start = b.pos
        b.pos += rows * c * scalar_size
        sxv_start = b.pos
        b.pos += cols * c * scalar_size
        u_row = struct.unpack_from("<" + f * c, data, u_start + row * c * scalar_size)
        values = []
        for texel in range(cols):
            sxv_row = struct.unpack_from("<" + f * c, data, sxv_start + texel * c * scalar_size)
            total = 0.0
            for k in range(c):
                total += u_row[k] * sxv_row[k]
            values.append(total)
        channels.append(values)
    assert b.pos == len(data)
    image = np.zeros((height, width, 3))
    for i in range(height):
        for j in range(width):
            texel = (height - 1 - i) * width + j
            c0, c1, c2 = (channels[c][texel] for c in range(3))
            if colour_model == 11:
                y = math.exp(c0) - 1e-5
                u, v = c1 * y + 1e-5, c2 * y + 1e-5
                rgb = (y + 1.13983 * v, y - 0.39465 * u - 0.5806 * v, y + 2.03211 * u)
                rgb = tuple(min(max(x, 0.0), 1.0) for x in rgb)
            else:
                rgb = (c0, c1, c2)
            if cosine:
                rgb = tuple(x / max(math.cos(lights[light_index][0]), math.cos(math.radians(89.0))) for x in rgb)
            image[i, j] = rgb
    return image, views, lights
