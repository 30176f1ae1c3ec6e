"""``dynbtf info``, ``dynbtf convert`` and ``dynbtf show``: look at and convert BTF sources.

Every command takes a BTF as a path or spec understood by
:func:`dynbtf.data.open_btf`: a UBO2014 ``.btf``, a UBO2003 ``.zip``, a stored
``*.dbtf`` directory or ``sim:<material>[?size=128&grid=ubo2003&seed=0]``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import typer

from .app import app

__all__ = ["info", "convert", "show", "btf_summary", "parse_direction"]

_BTF_HELP = ("BTF to read: a UBO2014 .btf, a UBO2003 .zip, a stored *.dbtf directory, or "
             "'sim:<material>[?size=128&grid=ubo2003&seed=0]'.")


def _theta_range(w: np.ndarray) -> tuple[float, float]:
    from ..conventions import direction_to_spherical

    theta, _ = direction_to_spherical(w)
    return float(theta.min()), float(theta.max())


def _path_bytes(spec: str) -> int | None:
    path = Path(spec)
    if path.is_file():
        return path.stat().st_size
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return None


def btf_summary(source, spec: str, n_images: int = 8) -> dict:
    """What ``dynbtf info`` prints, as a dict: size, directions, value range over ``n_images`` images.

    ``details`` holds the source's short metadata (e.g. a .btf file's colour
    model and components, a stored BTF's dtype and provenance).

    The value range is estimated from ``n_images`` (view, light) pairs spread
    evenly over all pairs (first and last included).
    """
    pairs = np.unique(np.linspace(0, source.n_pairs - 1, max(1, min(n_images, source.n_pairs))).round().astype(int))
    lo, hi, total, count = np.inf, -np.inf, 0.0, 0
    for k in pairs:
        img = source.image(*divmod(int(k), source.n_lights))
        lo, hi = min(lo, float(img.min())), max(hi, float(img.max()))
        total, count = total + float(img.sum(dtype=np.float64)), count + img.size
    on_disk = _path_bytes(spec)
    details = {}
    for key, value in source.metadata.items():
        items = value.items() if isinstance(value, dict) else [(None, value)]
        for sub, v in items:
            if key in ("format", "path") or sub == "values" or v == "" or not isinstance(v, (str, int, float, list)):
                continue
            if isinstance(v, list) and any(isinstance(x, list) for x in v):
                continue  # matrices (e.g. a colour transform) do not fit on a line
            if len(str(v)) <= 60:
                details[key if sub is None else f"{key}.{sub}"] = v
    return {
        "source": spec,
        "format": source.metadata.get("format", type(source).__name__),
        "name": source.name,
        "height": source.height,
        "width": source.width,
        "n_views": source.n_views,
        "view_theta_range_deg": _theta_range(source.views),
        "n_lights": source.n_lights,
        "light_theta_range_deg": _theta_range(source.lights),
        "n_images": source.n_pairs,
        "value_range_sampled": (lo, hi),
        "value_mean_sampled": total / max(count, 1),
        "images_sampled": int(len(pairs)),
        "raw_float32_bytes": source.nbytes_float32,
        "bytes_on_disk": on_disk,
        "details": details,
    }


def _gib(n: int | None) -> str:
    return "-" if n is None else f"{n / 2**30:.3f} GiB" if n >= 2**28 else f"{n / 2**20:.2f} MiB"


@app.command()
def info(
    btf: str = typer.Argument(..., help=_BTF_HELP),
    images: int = typer.Option(8, "--images", min=1, help="Number of images sampled (evenly over all view/light "
                               "pairs) to estimate the value range."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Describe a BTF: format, size in texels, direction counts and theta ranges (degrees), value range.

    Example: dynbtf info leather.dbtf
    """
    from ..data.open import open_btf
    from ..training.fit import MAX_REFLECTANCE

    with open_btf(btf) as source:
        s = btf_summary(source, btf, images)
    lo, hi = s["value_range_sampled"]
    if not max(abs(lo), abs(hi)) <= MAX_REFLECTANCE:  # NaN too
        typer.echo(f"dynbtf: warning: {btf}: sampled values reach {lo if abs(lo) > abs(hi) else hi:.3g}, beyond any "
                   f"plausible reflectance ({MAX_REFLECTANCE:g}): the file probably decodes to garbage (damaged "
                   "factors?); `dynbtf fit` refuses it unless --max-reflectance is raised", err=True)
    if as_json:
        typer.echo(json.dumps(s, indent=1))
        return
    typer.echo(f"{s['source']}: {s['format']} ({s['name']})")
    typer.echo(f"  size       {s['height']} x {s['width']} texels (rows x columns)")
    typer.echo(f"  views      {s['n_views']}, theta {s['view_theta_range_deg'][0]:.1f}..{s['view_theta_range_deg'][1]:.1f} deg")
    typer.echo(f"  lights     {s['n_lights']}, theta {s['light_theta_range_deg'][0]:.1f}..{s['light_theta_range_deg'][1]:.1f} deg")
    typer.echo(f"  images     {s['n_images']}")
    typer.echo(f"  values     {s['value_range_sampled'][0]:.4g} .. {s['value_range_sampled'][1]:.4g}, mean "
               f"{s['value_mean_sampled']:.4g} (linear RGB, excluding cos(theta_light); from {s['images_sampled']} images)")
    typer.echo(f"  raw size   {_gib(s['raw_float32_bytes'])} as float32; on disk {_gib(s['bytes_on_disk'])}")
    if s["details"]:
        typer.echo("  details    " + ", ".join(f"{k}={v}" for k, v in s["details"].items()))


@app.command()
def convert(
    src: str = typer.Argument(..., help=_BTF_HELP),
    output: Path = typer.Option(..., "-o", "--output", help="Where to write. A directory (conventionally *.dbtf): "
                                "a stored BTF, streamed and resumable (rerun after an interruption). A .btf file: "
                                "UBO2014 DFMF (truncated SVD, for small BTFs). A .zip file: UBO2003 JPEGs."),
    dtype: str = typer.Option("float16", help="Stored BTF value type: float16 (half the size, ~1e-3 relative "
                              "error) or float32."),
    components: int = typer.Option(16, min=1, help=".btf output: SVD components per colour channel."),
    scalar: str = typer.Option("half", help=".btf output: scalar type half, float or double."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing output."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
) -> None:
    """Convert any readable BTF into a stored BTF (or a UBO2014 .btf / UBO2003 .zip for other tools).

    Examples: dynbtf convert carpet.btf -o carpet.dbtf --dtype float16;
    dynbtf convert "sim:leather?size=32" -o leather.btf --components 32
    """
    from ..data.open import open_btf
    from ..data.stored import write_stored
    from ..data.ubo2003 import write_ubo2003
    from ..data.ubo2014 import write_ubo2014
    from ..errors import InputError

    suffix = output.suffix.lower()
    if suffix in (".btf", ".zip") and output.exists() and not overwrite:
        raise InputError(f"{output}: already exists (pass --overwrite to replace it)")
    with open_btf(src) as source:
        if suffix == ".btf":
            write_ubo2014(output, source, components=components, scalar=scalar, progress=not quiet)
            what = f"UBO2014 DFMF, {components} components, {scalar}"
        elif suffix == ".zip":
            write_ubo2003(output, source, progress=not quiet)
            what = "UBO2003 zip of JPEGs"
        else:
            write_stored(output, source, dtype=dtype, progress=not quiet, overwrite=overwrite)
            what = f"stored, {dtype}"
        typer.echo(f"wrote {output}: {source.height}x{source.width} texels, {source.n_views} views x "
                   f"{source.n_lights} lights ({what})")


def parse_direction(text: str, directions: np.ndarray, what: str) -> int:
    """``"INDEX"`` or ``"THETA,PHI"`` (degrees) -> index of the nearest of ``directions`` ``(N, 3)``."""
    from ..conventions import spherical_to_direction
    from ..errors import InputError
    from .arguments import THETA_PHI, parse_theta_phi

    text = str(text).strip()
    try:
        number = float(text)
    except ValueError:
        number = None
    if number is not None and number.is_integer():
        index = int(number)
        if not 0 <= index < len(directions):
            raise InputError(f"--{what}: index {index} out of range 0..{len(directions) - 1}")
        return index
    theta, phi = parse_theta_phi(text, what, expected=f"an index (e.g. 12) or {THETA_PHI}")
    w = spherical_to_direction(np.array(theta), np.array(phi))
    return int(np.argmax(directions @ w))


@app.command()
def show(
    btf: str = typer.Argument(..., help=_BTF_HELP),
    view: str = typer.Option(..., "--view", help="View direction: an index, or THETA,PHI in degrees (the nearest "
                             "measured direction is used)."),
    light: str = typer.Option(..., "--light", help="Light direction: an index, or THETA,PHI in degrees (nearest)."),
    output: Path = typer.Option(..., "-o", "--output", help="Image to write: .png (sRGB 8-bit, clamped) or .exr "
                                "(linear float)."),
    exposure: float = typer.Option(1.0, "--exposure", help="Multiply the linear values by this factor before "
                                   "writing (default 1)."),
    cosine: bool = typer.Option(False, "--cosine", help="Multiply by cos(theta_light), i.e. show the image as "
                                "lit by a unit-irradiance directional light (values exclude it otherwise)."),
    max_reflectance: float = typer.Option(1e4, "--max-reflectance", help="Largest |value| written without "
                                          "complaint (as `dynbtf fit`'s option): an image beyond it (or with NaN) is "
                                          "refused as the decode of a damaged file; raise it to write it anyway."),
) -> None:
    """Write one BTF image (one view and one light direction) as PNG or EXR.

    Example: dynbtf show leather.dbtf --view 0 --light 45,90 -o leather.png
    """
    from ..conventions import direction_to_spherical
    from ..data.open import open_btf
    from ..errors import InputError
    from ..io import save_image
    from .arguments import check_exposure

    check_exposure(exposure)
    if not (isinstance(max_reflectance, (int, float)) and max_reflectance > 0):
        raise InputError(f"--max-reflectance: expected a positive number, got {max_reflectance}")
    with open_btf(btf) as source:
        v = parse_direction(view, source.views, "view")
        l = parse_direction(light, source.lights, "light")
        img = np.asarray(source.image(v, l), dtype=np.float32)
        peak = float(np.abs(img).max()) if img.size else 0.0
        if not peak <= max_reflectance:  # NaN too: what `dynbtf info` warns about and `dynbtf fit` refuses
            raise InputError(f"{btf}: image (view {v}, light {l}) reaches {peak:.3g}, beyond any plausible "
                             f"reflectance (--max-reflectance {max_reflectance:g}): the file probably decodes to "
                             "garbage (damaged factors?); raise --max-reflectance to write it anyway")
        img = img * np.float32(exposure)
        if cosine:
            img = img * np.float32(max(source.lights[l, 2], 0.0))
        save_image(output, img)
        tv, pv = direction_to_spherical(source.views[v])
        tl, pl = direction_to_spherical(source.lights[l])
    typer.echo(f"wrote {output}: view {v} (theta {float(tv):.1f}, phi {float(pv):.1f} deg), "
               f"light {l} (theta {float(tl):.1f}, phi {float(pl):.1f} deg)")
