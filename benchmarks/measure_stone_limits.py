"""What limits the Triple Plane on deep-relief materials: the data, over-fitting, or the model?

The measurements behind docs/results.md ("Stone: data, fit and model"), docs/parallax.md (the positional fetch)
and docs/triple_plane.md ("Stone: the limit is parallax"). PSNR is given against each image's peak and against a
fixed peak of 1 (the tables show the latter).

``python benchmarks/measure_stone_limits.py oracle SPEC MODEL``
    Scores MODEL on its held-out pairs and on 64 random training pairs (a large gap = over-fitting,
    none = the model's capacity), and two oracles that see the ground truth of the training pairs:
    the nearest measured light at the same view, and the inverse-angle-weighted blend of the three
    nearest lights. If the oracle reaches a PSNR, the BTF's angular sampling supports it.

``python benchmarks/measure_stone_limits.py views SPEC MAX_THETA OUTPUT [--seed S]``
    Fits a Triple Plane (lr x3 as in the relief fits of docs/triple_plane.md, up to 64 texel groups, as many
    optimizer steps as a 30-epoch fit of the whole BTF, the same total learning-rate decay) to the sub-BTF of the
    views with theta <= MAX_THETA degrees (all lights), and scores it on its held-out pairs (10%) and on
    64 training pairs. Training PSNR against the range of views shows how much of the model's
    capacity view dependence (parallax, masking) takes. ~3-4 minutes on 2 cores at 128^2.

``python benchmarks/measure_stone_limits.py parallax SPEC {none,wide,oracle,stereo} [--seed S]``
    Fits the Triple Plane with its positional fetch moved, per view, to a point of the surface
    (the fast recipe: 30 epochs, lr x6, 64 texel groups, bf16, with every group's 16 pairs sharing one
    view), and scores it on the held-out pairs of the seed's split (5 %) and on 64 training
    pairs. ``none``: the texel centre, as the paper (the control: it must match ``dynbtf fit``);
    ``wide``: the same with a model twice as wide (f_U 32 channels, 64 hidden units).
    ``oracle``: the visible surface point the simulator traced (simulated BTFs only): what a perfect
    parallax and masking model would fetch. ``stereo``: the visible point traced through a height
    field estimated from the BTF alone by plane-sweep stereo
    (:func:`dynbtf.training.stereo_height.stereo_height`), kept fixed (``dynbtf fit --repr
    triple-parallax`` refines it). ~6 minutes each.

``python benchmarks/measure_stone_limits.py limits SPEC --seeds 3 --json benchmarks/results/stone.json``
    Per seed, the view-subset fits (all views, theta <= 30, theta <= 15, the normal view) and the oracles on the
    all-views fit's held-out pairs: part ``limits`` of the JSON file (each number's mean and min-max over the
    seeds; its other parts kept), docs/results.md's table. ~15 minutes per seed.

``python benchmarks/measure_stone_limits.py fetch SPEC --seeds 3 --json benchmarks/results/stone.json``
    Per seed, ``parallax`` with ``wide``, ``stereo`` and ``oracle``: part ``fetch``, docs/parallax.md's table,
    whose `uv` and refined-parallax rows are the stone rows of quality.json (``fit_materials.py`` with the same
    recipe and seeds). ~18 minutes per seed.

A seed fixes every random choice of a fit (initialization, batches, held-out split); seed 0 is the split the
other stone tables use.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from dynbtf.conventions import texel_centers_uv
from dynbtf.data.array import ArrayBTF
from dynbtf.data.open import open_btf
from dynbtf.data.simulator.geometry import trace_view
from dynbtf.representations.triple_plane import TriplePlane
from dynbtf.texture import fetch_wrap
from dynbtf.training.images import held_out_split
from dynbtf.training.stereo_height import stereo_height
from dynbtf.metrics.image_metrics import dssim, flip, psnr, psnr_fixed_range
from dynbtf.representations.model_file import load_model
from dynbtf.training import TrainConfig, get_fitter
from dynbtf.training.evaluate import evaluate_model


def _training_sample(btf, held_out, n=64, seed=0):
    held = set(held_out)
    pairs = [(v, k) for v in range(btf.n_views) for k in range(btf.n_lights) if (v, k) not in held]
    rng = np.random.default_rng(seed)
    return [pairs[i] for i in rng.choice(len(pairs), min(n, len(pairs)), replace=False)]


def oracle(spec: str, model: str) -> dict:
    """The model's held-out and training scores and the two light oracles' (see the module docstring); printed,
    and returned as ``{"model_held_out", "model_training", "nearest", "blend3"}``, each ``{"psnr",
    "psnr_fixed1"}`` (means over the pairs)."""
    btf = open_btf(spec)
    rep, meta = load_model(model)
    held = [tuple(p) for p in meta["provenance"]["held_out_pairs"]]
    held_set = set(held)
    lights = np.asarray(btf.lights)
    nearest, blend3 = [], []
    for v, k in held:
        candidates = [c for c in range(btf.n_lights) if (v, c) not in held_set]
        angle = np.degrees(np.arccos(np.clip(lights[candidates] @ lights[k], -1.0, 1.0)))
        order = np.argsort(angle)
        truth = btf.image(v, k)
        weights = 1.0 / np.maximum(angle[order[:3]], 1e-3)
        weights /= weights.sum()
        estimate = sum(w * btf.image(v, candidates[o]) for w, o in zip(weights, order[:3]))
        for scores, guess in ((nearest, btf.image(v, candidates[order[0]])), (blend3, estimate)):
            scores.append((psnr(truth, guess), psnr_fixed_range(truth, guess)))
    held_out, training = evaluate_model(rep, btf, held), evaluate_model(rep, btf, _training_sample(btf, held))
    print(f"{spec}: {len(held)} held-out pairs")
    print(f"  model, held-out pairs        : {held_out.summary()}")
    print(f"  model, 64 training pairs     : {training.summary()}")
    result = {"model_held_out": _scores(held_out), "model_training": _scores(training)}
    for name, label, scores in (("nearest", "nearest light", nearest), ("blend3", "3 nearest lights", blend3)):
        result[name] = {"psnr": float(np.mean([a for a, _ in scores])),
                        "psnr_fixed1": float(np.mean([b for _, b in scores]))}
        print(f"  oracle, {label:20s} : PSNR {result[name]['psnr']:.2f} dB "
              f"(fixed peak 1: {result[name]['psnr_fixed1']:.2f})")
    return result


def _scores(evaluation) -> dict:
    """``{"psnr", "psnr_fixed1"}``: an evaluation's mean PSNR against each image's peak and against 1."""
    return {"psnr": float(evaluation.mean["psnr"]), "psnr_fixed1": float(evaluation.mean["psnr_fixed1"])}


def views(spec: str, max_theta: float, output: str, seed: int = 0) -> dict:
    """The view-subset fit (see the module docstring); printed, and returned as ``{"views", "lights", "epochs",
    "held_out", "training"}`` (the last two ``{"psnr", "psnr_fixed1"}``)."""
    btf = open_btf(spec)
    directions = np.asarray(btf.views)
    theta = np.degrees(np.arccos(np.clip(directions[:, 2], -1.0, 1.0)))
    keep = np.nonzero(theta <= max_theta + 1e-6)[0]
    if keep.size == 0:
        raise SystemExit(f"error: no view of {spec} has theta <= {max_theta} degrees")
    values = np.stack([np.stack([btf.image(int(v), k) for k in range(btf.n_lights)]) for v in keep])
    sub = ArrayBTF(values, directions[keep], np.asarray(btf.lights), name=f"{spec} views<={max_theta}")
    full_pairs = btf.n_views * btf.n_lights * 0.95
    train_pairs = sub.n_pairs * 0.9
    epochs = max(30, round(30 * full_pairs / train_pairs))  # as many steps as 30 epochs of the whole BTF
    config = TrainConfig(epochs=epochs, lr_scale=3.0, lr_decay=0.9 ** (30 / epochs), held_out_fraction=0.1,
                         texel_groups=max(1, min(64, int(train_pairs) // 16)), seed=seed)
    get_fitter("triple")(sub, output, config)
    rep, meta = load_model(output)
    held = [tuple(p) for p in meta["provenance"]["held_out_pairs"]]
    held_out, training = evaluate_model(rep, sub, held), evaluate_model(rep, sub, _training_sample(sub, held))
    print(f"views with theta <= {max_theta}: {len(keep)} views x {btf.n_lights} lights, {epochs} epochs")
    print(f"  held-out pairs    : {held_out.summary()}")
    print(f"  64 training pairs : {training.summary()}")
    return {"views": int(len(keep)), "lights": int(btf.n_lights), "epochs": epochs, "held_out": _scores(held_out),
            "training": _scores(training)}


def parallax(spec: str, mode: str, epochs: int = 30, seed: int = 0) -> dict:
    """The fit with a moved positional fetch (see the module docstring); printed, and returned as ``{"held_out":
    {"psnr", "psnr_fixed1", "dssim", "flip"}, "training": {"psnr", "psnr_fixed1"}, "pairs", "minutes"}`` (means over
    the pairs)."""
    btf = open_btf(spec)
    size, n_texels, n_views, n_lights = btf.height, btf.height * btf.width, btf.n_views, btf.n_lights
    start = time.time()
    if mode in ("none", "wide"):
        fetch_uv = torch.from_numpy(texel_centers_uv(size, size).reshape(-1, 2)).expand(n_views, -1, -1)
    elif mode == "oracle":
        fetch_uv = torch.stack([torch.as_tensor(btf.renderer.view_trace(btf.views[v])["uv"]) for v in range(n_views)])
    else:
        height = stereo_height(btf)
        true = btf.renderer.height.double()[btf.renderer.stride // 2::btf.renderer.stride,
                                            btf.renderer.stride // 2::btf.renderer.stride]
        print(f"stereo height: RMSE {float((height - true).pow(2).mean().sqrt()) * size:.2f} texels, correlation "
              f"{float(np.corrcoef(height.reshape(-1), true.reshape(-1))[0, 1]):.3f} with the simulator's "
              f"({time.time() - start:.0f} s)")
        fetch_uv = torch.stack([trace_view(height, btf.views[v])[0] for v in range(n_views)])
    images = torch.empty(n_views, n_lights, n_texels, 3, dtype=torch.float16)
    for v in range(n_views):
        images[v] = torch.from_numpy(np.asarray(btf.view_images(v)).reshape(n_lights, n_texels, 3))
    views = torch.tensor(np.asarray(btf.views), dtype=torch.float32)
    lights = torch.tensor(np.asarray(btf.lights), dtype=torch.float32)
    train, held = held_out_split(n_views, n_lights, 0.05, seed)
    train_lights = [train[train[:, 0] == v, 1] for v in range(n_views)]
    wide = dict(positional_channels=32, hidden=64) if mode == "wide" else {}
    rep = TriplePlane(size, size, seed=seed, **wide)
    groups = [dict(g, lr=g["lr"] * 6.0) for g in rep.param_groups()]
    optimizer = torch.optim.AdamW(groups, fused=True)
    base_lr = [g["lr"] for g in optimizer.param_groups]
    n_groups, per_group = 64, 16
    n = n_texels // n_groups
    rng = np.random.default_rng(1 + seed)  # (seed 0: the generator of the earlier, unseeded version)
    for epoch in range(epochs):
        for g, lr in zip(optimizer.param_groups, base_lr):
            g["lr"] = lr * 0.9 ** epoch
        for _ in range(len(train) // per_group):
            group_views = rng.integers(0, n_views, n_groups)
            group_lights = torch.from_numpy(np.stack([rng.choice(train_lights[v], per_group, replace=False)
                                                      for v in group_views]))
            texels = torch.from_numpy((rng.integers(0, n_texels) + np.arange(n_groups * n)).reshape(n_groups, n)
                                      % n_texels)
            gv = torch.from_numpy(group_views)
            uv = torch.gather(fetch_uv[gv], 1, texels[..., None].expand(-1, -1, 2))
            features = fetch_wrap(rep.f_u, uv).reshape(n_groups * n, -1)
            target = images[gv[:, None, None], group_lights[:, :, None], texels[:, None, :]]
            target = target.permute(1, 0, 2, 3).reshape(per_group, n_groups * n, 3).float()
            angular = rep.angular_features(views[gv].repeat_interleave(per_group, 0), lights[group_lights.reshape(-1)])
            loss = rep.decoder.texel_image_l1_loss(features, angular, target, texel_groups=n_groups, workers=2,
                                                   precision="bf16")
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()

    @torch.no_grad()
    def score(pairs, every_metric: bool) -> dict:
        values = []
        for v, k in pairs:
            features = fetch_wrap(rep.f_u, fetch_uv[v])
            model = rep.decode(features, views[v].expand(n_texels, 3), lights[k].expand(n_texels, 3))
            truth = images[v, k].float().numpy().reshape(size, size, 3)
            guess = model.numpy().reshape(size, size, 3)
            values.append({"psnr": psnr(truth, guess), "psnr_fixed1": psnr_fixed_range(truth, guess),
                           **({"dssim": dssim(truth, guess), "flip": flip(truth, guess)} if every_metric else {})})
        return {key: float(np.nanmean([v[key] for v in values])) for key in values[0]}

    sample = train[np.random.default_rng(seed).choice(len(train), 64, replace=False)]
    result = {"held_out": score(held, True), "training": score(sample, False), "pairs": len(held),
              "minutes": (time.time() - start) / 60}
    print(f"{spec}, positional fetch at {mode} (seed {seed}): held-out PSNR {result['held_out']['psnr']:.2f} dB "
          f"(fixed peak 1: {result['held_out']['psnr_fixed1']:.2f}; {len(held)} pairs), 64 training pairs "
          f"{result['training']['psnr']:.2f} dB, {result['minutes']:.1f} min")
    return result


#: The view subsets of ``limits``: the largest view theta (degrees) each keeps.
LIMIT_THETAS = (90.0, 30.0, 15.0, 0.0)
#: The rows ``fetch`` measures (the ``parallax`` modes) and the quality.json parts whose stone row it shows between
#: them (:data:`QUALITY_PARTS`), in the table's order: (mode or part, the row's label).
FETCH_ROWS = (("triple", "`uv` (the paper's Triple Plane, `--repr triple`)"),
              ("wide", "`uv`, 2x wider model (f_U 32, 64 hidden)"),
              ("stereo", "visible point of the stereo height, kept fixed"),
              ("triple_parallax", "visible point of the stereo height, refined by the fit "
                                  "(`--repr triple-parallax`)"),
              ("oracle", "visible point the simulator traced (oracle: exact height)"))
#: The fits of the fetch table that fit_materials.py makes (quality.json's parts), not this script.
QUALITY_PARTS = ("triple", "triple_parallax")


def _view_subset_label(result: dict, theta: float) -> str:
    if theta >= 90.0:
        return f"the fit of all {result['views']} views (lr x3)"
    if result["views"] == 1:
        return f"the normal view only (1 x {result['lights']})"
    return f"views with theta <= {theta:g} deg only ({result['views']} x {result['lights']})"


def limits(spec: str, seeds: int, out: Path) -> dict:
    """Part ``limits``: per seed, the view-subset fits of :data:`LIMIT_THETAS` (models in ``out``) and the oracles on
    the all-views fit's held-out pairs; each number's spread over the seeds."""
    from results_io import spread

    runs = []
    for seed in range(seeds):
        fits = {theta: views(spec, theta, str(out / f"seed{seed}_views{theta:g}.dbtfm"), seed)
                for theta in LIMIT_THETAS}
        runs.append((fits, oracle(spec, str(out / f"seed{seed}_views{LIMIT_THETAS[0]:g}.dbtfm"))))
    rows = [{"measurement": "oracle: the 3 nearest measured lights at the same view, inverse-angle weights "
                            "(`oracle`)", "psnr_training": None,
             "psnr_held_out": spread([o["blend3"]["psnr_fixed1"] for _, o in runs]),
             "nearest_light_psnr_held_out": spread([o["nearest"]["psnr_fixed1"] for _, o in runs])}]
    for theta in LIMIT_THETAS:
        rows.append({"measurement": _view_subset_label(runs[0][0][theta], theta),
                     "psnr_training": spread([f[theta]["training"]["psnr_fixed1"] for f, _ in runs]),
                     "psnr_held_out": spread([f[theta]["held_out"]["psnr_fixed1"] for f, _ in runs])})
    return {"seeds": list(range(seeds)), "conditions": f"`{spec}`; PSNR against a fixed peak of 1; each view-subset "
            "fit has as many steps as a 30-epoch fit of the whole BTF, 10% of its pairs held out (the seed's split); "
            "the oracles on the all-views fit's held-out pairs", "rows": rows}


def fetch(spec: str, seeds: int) -> dict:
    """Part ``fetch``: per seed, the ``parallax`` fits of :data:`FETCH_ROWS`; its rows from quality.json name their
    part (``"from": "quality"``, ``"part"``)."""
    from results_io import spread

    results = {mode: [parallax(spec, mode, seed=seed) for seed in range(seeds)]
               for mode, _ in FETCH_ROWS if mode not in QUALITY_PARTS}
    rows = []
    for mode, label in FETCH_ROWS:
        if mode in QUALITY_PARTS:
            rows.append({"fetch": label, "from": "quality", "part": mode})
            continue
        held = [r["held_out"] for r in results[mode]]
        rows.append({"fetch": label, **{key: spread([h[key] for h in held]) for key in ("psnr_fixed1", "dssim",
                                                                                        "flip")}})
    return {"seeds": list(range(seeds)), "conditions": f"`{spec}`, held-out pairs of each seed's split (5%); fast "
            "recipe: 30 epochs, lr x6, 64 texel groups, bf16; PSNR against a fixed peak of 1", "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("oracle")
    p.add_argument("spec")
    p.add_argument("model")
    p = sub.add_parser("views")
    p.add_argument("spec")
    p.add_argument("max_theta", type=float)
    p.add_argument("output")
    p.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("parallax")
    p.add_argument("spec")
    p.add_argument("mode", choices=("none", "wide", "oracle", "stereo"))
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    for name in ("limits", "fetch"):
        p = sub.add_parser(name)
        p.add_argument("spec")
        p.add_argument("--seeds", type=int, default=3)
        p.add_argument("--json", type=Path, default=None, help=f"write part {name!r} of this JSON file (e.g. "
                       "benchmarks/results/stone.json)")
        if name == "limits":
            p.add_argument("--out", type=Path, default=Path("stone_limits_out"), help="where the fits are written")
    args = parser.parse_args()
    if args.command == "oracle":
        oracle(args.spec, args.model)
    elif args.command == "views":
        views(args.spec, args.max_theta, args.output, args.seed)
    elif args.command == "parallax":
        parallax(args.spec, args.mode, args.epochs, args.seed)
    else:
        if args.command == "limits":
            args.out.mkdir(parents=True, exist_ok=True)
            measured = limits(args.spec, args.seeds, args.out)
        else:
            measured = fetch(args.spec, args.seeds)
        if args.json is not None:
            from results_io import write_part

            write_part(args.json, args.command, "measure_stone_limits.py", measured)


if __name__ == "__main__":
    main()
