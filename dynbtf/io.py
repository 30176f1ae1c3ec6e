"""Atomic file writing and image input/output.

Images are ``(H, W, 3)`` linear RGB float32 in memory. PNG files are written
sRGB-encoded (clamped to ``[0, 1]``) and read back to linear; EXR files hold
linear half or float data (written with the OpenEXR package: imageio would
silently write TIFF data into a ``.exr`` name).
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
import threading
from pathlib import Path

import numpy as np

from .errors import FormatError, InputError

__all__ = [
    "load_painted_image",
    "atomic_path",
    "check_writable",
    "os_error_message",
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
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            e.filename = str(path)  # a failed write or close names no file: name it (an errno-less message stays)
        raise


def _nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (``.`` for a relative path with none)."""
    current = path
    while not os.path.lexists(current):
        parent = current.parent
        if parent == current:
            break
        current = parent
    return current


def user_cache_dir(variable: str, name: str) -> Path | None:
    """A dynbtf cache directory: ``$variable`` if set (``off``, ``0``, ``none`` or empty: no cache, None), else
    ``$XDG_CACHE_HOME/dynbtf/<name>`` (``~/.cache/dynbtf/<name>``). Nothing is created.

    >>> user_cache_dir("DYNBTF_UNSET_EXAMPLE_CACHE", "example").parts[-2:]
    ('dynbtf', 'example')
    """
    setting = os.environ.get(variable)
    if setting is not None and setting.strip().lower() in ("off", "0", "none", ""):
        return None
    if setting:
        return Path(setting)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "dynbtf" / name


def check_writable(path, what: str, *, directory: bool = False, needed_bytes: int | None = None) -> Path:
    """Check, before any work, that output ``path`` can be written; else :class:`InputError`, one line.

    ``what`` names the output in the message (e.g. ``"-o/--output"``). ``directory``: ``path`` is
    a directory to create or fill (else a file to create or replace). Refused, with the reason:
    ``path`` is a directory where a file is wanted (``-o .``) or a file where a directory is
    wanted; a component of the path is a file (``out.png/x.png``); the nearest existing directory
    is not writable (permissions, a read-only file system); its file system has no space left
    (or less than ``needed_bytes``). Nothing is created. Writes themselves go through
    :func:`atomic_path`, so a disk that fills up later leaves no partial file.

    >>> import tempfile
    >>> from pathlib import Path
    >>> root = Path(tempfile.mkdtemp())
    >>> check_writable(root / "new" / "x.png", "-o").name
    'x.png'
    >>> check_writable(root, "-o")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    dynbtf.errors.InputError: -o ...: is a directory; expected a file name in it (e.g. .../out.png)
    """
    raw = path
    try:
        path = Path(os.fsdecode(path))
        text = str(path)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: expected a path, got {raw!r} ({e})") from None
    if not text or "\x00" in text:
        raise InputError(f"{what}: expected a path, got {raw!r}")
    try:
        is_dir, exists = path.is_dir(), os.path.lexists(path)
        if directory and exists and not is_dir:
            raise InputError(f"{what} {path}: exists and is not a directory")
        if not directory and is_dir:
            example = "out" + (path.suffix or ".png")
            raise InputError(f"{what} {path}: is a directory; expected a file name in it (e.g. {path / example})")
        base = _nearest_existing(path if directory else path.parent)
        if not base.is_dir():
            raise InputError(f"{what} {path}: cannot be created: {base} is a file, not a directory")
        if not os.access(base, os.W_OK | os.X_OK):
            readonly = bool(os.statvfs(base).f_flag & getattr(os, "ST_RDONLY", 1))
            reason = "read-only file system" if readonly else "permission denied"
            raise InputError(f"{what} {path}: cannot write into {base}: {reason}")
        stat = os.statvfs(base)
        free = stat.f_bavail * stat.f_frsize
        if free <= 0 or (needed_bytes is not None and free < needed_bytes):
            need = f" (about {needed_bytes / 1e6:.3g} MB needed, {free / 1e6:.3g} MB free)" if needed_bytes else ""
            raise InputError(f"{what} {path}: cannot write into {base}: no space left on device{need}")
    except OSError as e:  # a path too long, a loop of links, an unreadable parent
        raise InputError(f"{what} {path}: cannot be written: {os_error_message(e)}") from None
    return path


def os_error_message(e: OSError) -> str:
    """One line for an operating-system error: ``"PATH: no space left on device"``.

    What the command line prints for an :class:`OSError` (a full disk, a read-only file system)
    met while reading or writing, instead of a traceback.

    >>> import errno
    >>> os_error_message(OSError(errno.ENOSPC, "No space left on device", "/tmp/x.png"))
    '/tmp/x.png: no space left on device'
    """
    reason = e.strerror or str(e) or type(e).__name__
    if e.errno is not None and not e.strerror:
        reason = os.strerror(e.errno)
    reason = reason[:1].lower() + reason[1:]
    if e.errno == errno.ENOSPC:
        reason = "no space left on device"
    names = [n for n in (e.filename, e.filename2) if n is not None]
    where = " -> ".join(os.fsdecode(n) if isinstance(n, (str, bytes)) else str(n) for n in names)
    return f"{where}: {reason}" if where else reason


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
                try:
                    f.write(str(tmp))
                except RuntimeError as e:  # OpenEXR reports a failed write (a full disk) as a RuntimeError
                    full = "No space left on device" in str(e)
                    raise OSError(errno.ENOSPC if full else errno.EIO,
                                  "No space left on device" if full else f"cannot write the EXR file ({e})",
                                  str(path)) from None
    else:
        import imageio.v3 as iio

        # encoded in memory, then written: a failed write raises here, not in a plug-in's destructor
        data = iio.imwrite("<bytes>", to_uint8_srgb(rgb, exposure), extension=ext)
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
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



#: The last painted images read, by file (:func:`load_painted_image`): ``(real path, size, modification time)`` ->
#: the image. A command checks its ``--target`` before anything loads and the Mitsuba plugin reads it again.
_PAINTED: dict[tuple, np.ndarray] = {}
_PAINTED_KEPT = 4
_PAINTED_LOCK = threading.Lock()  # Mitsuba may construct plugins on several threads


def load_painted_image(path, name: str = "image") -> np.ndarray:
    """A painted grey image (a layered material's mask, a guided synthesis' target) as ``(H, W)`` float64 in
    ``[0, 1]``: a PNG or JPEG as painted, its stored grey levels over the maximum (a 50% grey is 0.5, a level saved
    as 255 exactly 1); an EXR's values as they are; colour images by the mean of R, G and B. ``name`` (e.g.
    ``"--mask"``) is named in the error for values outside ``[0, 1]``.

    A file read again unchanged (the same size and modification time) is not decoded again: the caller gets a
    copy of the image read before."""
    try:
        stat = os.stat(path)
        key = (os.path.realpath(path), stat.st_size, stat.st_mtime_ns)
    except OSError:
        key = None  # load_image says what is wrong with the path
    with _PAINTED_LOCK:
        kept = _PAINTED.get(key)
    if kept is not None:
        return kept.copy()
    image = _read_painted_image(path, name)
    if key is not None:
        with _PAINTED_LOCK:
            while len(_PAINTED) >= _PAINTED_KEPT:
                _PAINTED.pop(next(iter(_PAINTED)))
            _PAINTED[key] = image.copy()
    return image


def _read_painted_image(path, name: str) -> np.ndarray:
    """:func:`load_painted_image`'s decoding and checks."""
    image = np.asarray(load_image(path), dtype=np.float64)
    if not str(path).lower().endswith(".exr"):
        # back to the stored levels, on the grid of 16-bit levels (which holds every 8-bit level k / 255 exactly)
        image = np.round(np.clip(np.asarray(linear_to_srgb(image), dtype=np.float64), 0.0, 1.0) * 65535.0) / 65535.0
    image = image[..., :3].mean(-1)
    if not np.isfinite(image).all() or image.min() < 0.0 or image.max() > 1.0:
        raise InputError(f"{name} {path}: expected grey values in [0, 1] (finite); scale the image first")
    return image
