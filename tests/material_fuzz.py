"""Crafted compiled materials against the reader: a hostile user's files, written through the public
:func:`dynbtf.material.format.save_compiled` (so every checksum is valid).

Run by ``tests/test_material_fuzz.py`` in a child process (a crash must not take the test runner with
it), or by hand for a longer campaign::

    python tests/material_fuzz.py CASES SEED WORKDIR

Each case takes one of six valid materials (tile, linear, hist, hex, struct, quilt; footprint decoders
and a sampling table on some), changes one thing -- a table's values (NaN, infinity, 1e30, huge or
negative indices, reversed rows), its shape or dtype, a table dropped or added, a header field (method,
seed, arguments, model checksum, config), the model's tensors -- saves it, and opens and queries it as a
user would (``synthesized_btf(path).eval``, point and footprint queries). The contract: every case ends in
a one-line :class:`~dynbtf.errors.FormatError` / :class:`~dynbtf.errors.InputError`, or in finite answers.
Anything else (another exception, a non-finite answer) is recorded as a violation; a crash or a hang
ends the child process, and the parent names the case from ``WORKDIR/current.txt``.
Prints one JSON line: ``{"cases": n, "outcomes": {...}, "violations": [...]}``.
"""

from __future__ import annotations

import json
import math
import os
import sys
import traceback
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

METHODS = ("tile", "linear", "hist", "hex", "struct", "quilt", "relief")
#: Materials of the campaign: a method of the Triple Plane, or ``relief`` (hist of a triple-parallax model: a height
#: channel marched by the query).
SECTIONS = ("synthesis", "decoder", "model", "sampling", "header")


def base_materials(size: int = 32) -> dict:
    """One valid material per method of a random ``size x size`` Triple Plane (footprint decoders copied from
    the point decoder on tile, hist and struct; a sampling table on hist), and ``relief``: hist of a
    triple-parallax model with a random height field."""
    from dynbtf.decoder.folded import MeanAppearance
    from dynbtf.representations.parallax import ParallaxTriplePlane
    from dynbtf.representations.triple_plane import TriplePlane
    from dynbtf.synthesis.mip import level_shapes
    from dynbtf.synthesis.registry import synthesizer_class
    from dynbtf.material import compile_material

    model = TriplePlane(size, size, seed=0)
    materials = {}
    relief = ParallaxTriplePlane(size, size, seed=0)
    relief.set_height(0.01 * torch.rand(size, size, generator=torch.Generator().manual_seed(4)))
    for method in METHODS:
        if method == "relief":
            materials[method] = compile_material(relief, "hist", 0, footprints=False, progress=False)
            continue
        material = compile_material(model, method, 0, footprints=False, progress=False)
        if method in ("tile", "hist", "struct"):
            plane = model.positional_plane().detach()
            count = len(level_shapes(*synthesizer_class(method).pyramid_size(material.synthesis, plane)))
            point = material.decoder.levels[0]
            hidden = material.decoder.hidden
            mean = MeanAppearance(torch.randn(4, hidden, generator=torch.Generator().manual_seed(1)),
                                  torch.full((4,), 0.25), [(w.clone(), b.clone()) for w, b in point.rest])
            material.decoder = material.decoder.with_footprints([point] * count, mean)
        if method == "hist":
            density = torch.rand(9, 12, 8, 8, generator=torch.Generator().manual_seed(2)) + 0.1
            material = material.with_sampling({
                "density": density.float(), "phi_nodes": torch.linspace(0, 2 * math.pi, 9, dtype=torch.float64),
                "theta_nodes": 0.5 * math.pi * (1 - (1 - torch.linspace(0, 1, 12, dtype=torch.float64)) ** 2)})
        materials[method] = material
    return materials


def sections(material) -> dict:
    """The material's tensors by section, and its header fields (plain, mutable copies)."""
    return {"model": {k: v.detach().clone() for k, v in material.model.state_dict().items()},
            "synthesis": {k: v.clone() for k, v in material.synthesis.items()},
            "decoder": {} if material.decoder is None else {k: v.clone() for k, v in material.decoder.to_tensors().items()},
            "sampling": {k: v.clone() for k, v in (material.sampling or {}).items()},
            "header": {"kind": material.model.kind, "config": dict(material.model.config()), "method": material.method,
                       "seed": material.seed, "arguments": dict(material.arguments), "choice": material.choice,
                       "key": material.key, "model_sha256": material.model_sha256}}


def crafted(parts: dict):
    """An object :func:`save_compiled` writes as a material with exactly these tensors and header fields."""
    h = parts["header"]
    model = SimpleNamespace(state_dict=lambda: parts["model"], kind=h["kind"], config=lambda: h["config"])
    decoder = SimpleNamespace(to_tensors=lambda: parts["decoder"]) if parts["decoder"] else None
    return SimpleNamespace(model=model, synthesis=parts["synthesis"], decoder=decoder, sampling=parts["sampling"] or None,
                           method=h["method"], seed=h["seed"], arguments=h["arguments"], choice=h["choice"],
                           key=h["key"], model_sha256=h["model_sha256"])


# ---------------------------------------------------------------------------------------------- mutations
def _value_mutation(t: torch.Tensor, rng: np.random.Generator) -> tuple[str, torch.Tensor]:
    kinds = ["nan", "inf", "-inf", "x1e30", "-1e30", "huge", "negative", "reverse", "random", "tiny change",
             "zero", "truncate", "extend", "flatten", "empty", "dtype", "transpose"]
    kind = kinds[rng.integers(len(kinds))]
    t = t.clone()
    flat = t.reshape(-1)
    i = int(rng.integers(max(flat.numel(), 1)))
    is_float = t.is_floating_point()
    if kind in ("nan", "inf", "-inf") and flat.numel():
        if is_float:
            flat[i] = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}[kind]
        elif t.dtype != torch.bool:
            flat[i] = torch.iinfo(t.dtype).max if kind != "-inf" else torch.iinfo(t.dtype).min
    elif kind in ("x1e30", "-1e30"):
        t = t * (1e30 if kind == "x1e30" else -1e30) if is_float else t
        if not is_float and t.dtype != torch.bool and flat.numel():
            t.reshape(-1)[i] = 30000 if kind == "x1e30" else -30000
    elif kind == "huge" and flat.numel() and t.dtype != torch.bool:
        flat[i] = 1e9 if is_float else min(100000, torch.iinfo(t.dtype).max)
    elif kind == "negative" and flat.numel() and t.dtype != torch.bool:
        flat[i] = -abs(float(flat[i])) - 5 if is_float else -5
    elif kind == "reverse" and t.ndim:
        t = t.flip(-1)
    elif kind == "random" and t.dtype != torch.bool:
        g = torch.Generator().manual_seed(int(rng.integers(2 ** 31)))
        t = (torch.randn(t.shape, generator=g, dtype=torch.float64) * 10).to(t.dtype)
    elif kind == "tiny change" and is_float and flat.numel():
        flat[i] = flat[i] * (1 + 1e-3)
    elif kind == "zero":
        t = torch.zeros_like(t)
    elif kind == "truncate" and t.ndim and t.shape[-1] > 1:
        t = t[..., :-1].contiguous()
    elif kind == "extend" and t.ndim:
        t = torch.cat([t, t[..., :1]], dim=-1)
    elif kind == "flatten":
        t = t.reshape(-1)
    elif kind == "empty":
        t = t.reshape(-1)[:0]
    elif kind == "dtype":
        t = t.double() if t.dtype == torch.float32 else t.float() if is_float else t.to(torch.int32)
    elif kind == "transpose" and t.ndim >= 2:
        t = t.transpose(0, 1).contiguous()
    return kind, t


BAD_ARGUMENTS = [("gamma", math.nan), ("gamma", math.inf), ("gamma", -1.0), ("gamma", 0.0), ("gamma", 1e300),
                 ("gamma", "x"), ("gamma", [1, 2]), ("lut_size", 1), ("lut_size", 1e12), ("lut_size", "big"),
                 ("repeats", math.inf), ("repeats", math.nan), ("repeats", 1e9), ("decorrelate", "x"), ("separate", 99),
                 ("separate", -3), ("tileable", "maybe"), ("band", -4), ("band", 10 ** 9), ("contrast", 2.0),
                 ("contrast", math.nan), ("beta", math.inf), ("offsets", 0), ("offsets", 10 ** 6), ("cells", 3),
                 ("cells", 0), ("margin", math.nan), ("margin", 7.0), ("nosuch", 1), ("fast", "x"), ("guide", "x")]


def mutate(parts: dict, rng: np.random.Generator, others: dict) -> str:
    """Change one thing of ``parts`` in place; returns what was changed."""
    section = SECTIONS[rng.integers(len(SECTIONS))]
    if section != "header" and not parts[section]:
        section = "synthesis" if parts["synthesis"] else "decoder"
    h = parts["header"]
    if section == "header":
        field = ["method", "seed", "arguments", "model_sha256", "config", "choice", "other model"][rng.integers(7)]
        if field == "method":
            h["method"] = [*METHODS, "auto", "nosuch", 42, None][rng.integers(len(METHODS) + 4)]
            return f"header method -> {h['method']!r}"
        if field == "seed":
            h["seed"] = [-1, 2 ** 64, 1.5, True, "7", 123456, None][rng.integers(7)]
            return f"header seed -> {h['seed']!r}"
        if field == "arguments":
            name, value = BAD_ARGUMENTS[rng.integers(len(BAD_ARGUMENTS))]
            h["arguments"] = {**h["arguments"], name: value}
            return f"header arguments {name} -> {value!r}"
        if field == "model_sha256":
            h["model_sha256"] = others["digest"]
            return "header model_sha256 -> another model's"
        if field == "config":
            keys = ["hidden", "positional_channels", "height", "angular_resolution", "layers", "height_scale",
                    "march_step_texels"]
            key = keys[rng.integers(len(keys))]
            h["config"] = {**h["config"], key: [0, 1, 64, -3, 10 ** 6, 1e-9, 4.0][rng.integers(7)]}
            return f"header config {key} -> {h['config'][key]}"
        if field == "choice":
            h["choice"] = [{"method": 5}, "x", {"method": "hist", "line": None, "strength": "high"}][rng.integers(3)]
            return f"header choice -> {h['choice']!r}"
        parts["model"] = {k: v.clone() for k, v in others["model"].items()}  # another model, checksum recomputed
        h["model_sha256"] = others["digest"]
        return "another model's tensors under this material's tables"
    tensors = parts[section]
    names = sorted(tensors)
    choice = rng.integers(len(names) + 2)
    if choice == len(names):
        tensors[f"extra{rng.integers(10)}"] = torch.zeros(3)
        return f"{section}: an unknown table added"
    if choice == len(names) + 1:
        name = names[rng.integers(len(names))]
        del tensors[name]
        return f"{section}.{name}: dropped"
    name = names[choice]
    kind, tensors[name] = _value_mutation(tensors[name], rng)
    if section == "model":
        from dynbtf.representations.model_file import tensor_digest

        if rng.random() < 0.7:  # mostly a consistent file: the checksum of the changed model recomputed
            h["model_sha256"] = tensor_digest(tensors)
    return f"{section}.{name}: {kind}"


# ---------------------------------------------------------------------------------------------- one case
def query(path: Path, footprints: bool) -> torch.Tensor:
    """What a user does with a material: open it and ask for point (and footprint) answers."""
    from dynbtf.synthesized import synthesized_btf

    btf = synthesized_btf(path, level_decoders=footprints)
    g = torch.Generator().manual_seed(3)
    uv = (torch.rand(96, 2, generator=g, dtype=torch.float64) - 0.5) * 2e4
    w = torch.nn.functional.normalize(torch.rand(96, 3, generator=g) - torch.tensor([0.5, 0.5, -0.2]), dim=-1)
    out = [btf.eval(uv, w, w.flip(0))]
    if footprints:
        out.append(btf.eval(uv, w, w.flip(0), footprint=torch.logspace(-4, 2, 96, dtype=torch.float64)))
    return torch.cat(out)


def run(cases: int, seed: int, workdir: Path) -> dict:
    from dynbtf.material import save_compiled
    from dynbtf.errors import FormatError, InputError
    from dynbtf.representations.model_file import tensor_digest
    from dynbtf.representations.triple_plane import TriplePlane

    os.environ.setdefault("DYNBTF_COMPILED_CACHE", "off")
    workdir.mkdir(parents=True, exist_ok=True)
    materials = base_materials()
    other = TriplePlane(32, 32, seed=99).state_dict()
    others = {"model": other, "digest": tensor_digest(other)}
    rng = np.random.default_rng(seed)
    outcomes, violations = Counter(), []
    progress = workdir / "current.txt"
    for case in range(cases):
        method = METHODS[rng.integers(len(METHODS))]
        parts = sections(materials[method])
        what = f"case {case} ({method}): " + mutate(parts, rng, others)
        progress.write_text(what)
        path = workdir / f"case{case % 4}.dbtfc"
        try:
            save_compiled(crafted(parts), path)
        except Exception:  # the writer itself refused (e.g. a tensor safetensors cannot store)
            outcomes["not writable"] += 1
            continue
        footprints = method in ("tile", "hist", "struct")
        try:
            answer = query(path, footprints)
        except (FormatError, InputError) as e:
            message = str(e)
            outcomes["refused"] += 1
            if "\n" in message.strip() or not message:
                violations.append(f"{what}: a refusal of several lines: {message!r}")
            continue
        except Exception:
            violations.append(f"{what}: {traceback.format_exc(limit=4)}")
            outcomes["traceback"] += 1
            continue
        if not bool(torch.isfinite(answer).all()):
            violations.append(f"{what}: non-finite answers")
            outcomes["non-finite"] += 1
        else:
            outcomes["accepted, finite"] += 1
    progress.unlink(missing_ok=True)
    return {"cases": cases, "outcomes": dict(outcomes), "violations": violations}


if __name__ == "__main__":
    import warnings

    warnings.simplefilter("ignore")
    print(json.dumps(run(int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]))))
