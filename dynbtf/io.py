"""Atomic file writing and image input/output.

Images are ``(H, W, 3)`` linear RGB float32 in memory. PNG files are written
sRGB-encoded (clamped to ``[0, 1]``) and read back to linear; EXR files hold
linear half or float data (written with the OpenEXR package: imageio would
silently write TIFF data into a ``.exr`` name).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import FormatError, InputError

__all__ = [
    "atomic_path",
    "require_file",
    "linear_to_srgb",
    "srgb_to_linear",
    "IMAGE_EXTENSIONS",
    "check_image_path",
    "save_image",
    "load_image",
    "to_uint8_srgb",
]


@contextlib.contextmanager
def atomic_path(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    Nothing half-written is ever left at ``path``: on an exception the temporary
    file is removed and ``path`` keeps its previous content (if any).

    >>> import tempfile
    >>> from pathlib import Path
    >>> target = Path(tempfile.mkdtemp()) / "x.txt"
    >>> with atomic_path(target) as tmp:
    ...     _ = Path(tmp).write_text("hello")
    >>> target.read_text()
    'hello'
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield Path(tmp)
        if os.path.isfile(tmp):  # mkstemp makes 0600 files; give the usual umask-based mode
            os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def require_file(path, expected: str) -> Path:
    """``path`` as a :class:`~pathlib.Path` if it is an existing regular file, else :class:`FormatError`.

    ``expected`` describes the file wanted (e.g. ``"a UBO2014 .btf file"``) and
    appears in the error when ``path`` exists but is not a file.
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "file not found")
    if not path.is_file():
        raise FormatError(path, f"not a file (expected {expected})")
    return path


def linear_to_srgb(x):
    """sRGB transfer function (IEC 61966-2-1) of linear values; input clamped to [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(x):
    """Inverse sRGB transfer function of values in [0, 1]."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def to_uint8_srgb(rgb, exposure: float = 1.0) -> np.ndarray:
    """Linear ``(H, W, 3)`` float image -> sRGB-encoded uint8 for display."""
    return np.round(linear_to_srgb(np.asarray(rgb, dtype=np.float32) * exposure) * 255.0).astype(np.uint8)


def _check_image(rgb, name="image"):
    rgb = np.asarray(rgb)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=-1)
    if rgb.ndim != 3 or rgb.shape[-1] not in (1, 3, 4):
        raise InputError(f"{name}: expected an (H, W, 3) array, got shape {rgb.shape}")
    if rgb.shape[-1] == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    return rgb[..., :3].astype(np.float32)


#: Extensions :func:`save_image` writes (lower case).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr")


def check_image_path(path) -> str:
    """The lower-case extension of an image path :func:`save_image` can write, else :class:`InputError`.

    Call it before long work whose result goes to ``path`` (a render, a
    synthesis), so that a wrong extension fails at once, not after the work.

    >>> check_image_path("render.EXR")
    '.exr'
    """
    ext = Path(path).suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise InputError(f"{path}: unsupported image extension {ext!r}; expected .png, .jpg or .exr")
    return ext


def save_image(path, rgb, *, exposure: float = 1.0) -> Path:
    """Write a linear ``(H, W, 3)`` image atomically; format from the extension.

    ``.png`` (and ``.jpg``): sRGB-encoded 8-bit after ``exposure`` scaling and
    clamping. ``.exr``: linear float32 (HDR, unclamped, no exposure applied).
    Returns the path written.
    """
    path = Path(path)
    ext = check_image_path(path)
    rgb = _check_image(rgb)
    if ext == ".exr":
        import OpenEXR

        with atomic_path(path) as tmp:
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            channels = {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}
            with OpenEXR.File(header, channels) as f:
                f.write(str(tmp))
    else:
        import imageio.v3 as iio

        with atomic_path(path) as tmp:
            iio.imwrite(tmp, to_uint8_srgb(rgb, exposure), extension=ext)
    return path


def load_image(path) -> np.ndarray:
    """Read an image as linear ``(H, W, 3)`` float32 (PNG/JPEG are sRGB-decoded)."""
    path = require_file(path, "an image file")
    ext = path.suffix.lower()
    try:
        if ext == ".exr":
            import OpenEXR

            with OpenEXR.File(str(path)) as f:
                ch = f.channels()
                if "RGB" in ch:
                    rgb = np.asarray(ch["RGB"].pixels, dtype=np.float32)
                else:
                    rgb = np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)
            return _check_image(rgb, str(path))
        import imageio.v3 as iio

        data = path.read_bytes()  # imageio leaks its file handle when decoding fails
        img = iio.imread(data, extension=ext or None)
    except (OSError, ValueError, RuntimeError, KeyError) as e:
        raise FormatError(path, f"cannot read image ({e})") from None
    img = _check_image(img, str(path))
    scale = 65535.0 if np.asarray(img).max() > 255 else 255.0
    return srgb_to_linear(img / scale)
