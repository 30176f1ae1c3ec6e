"""What limits the Triple Plane on deep-relief materials: the data, over-fitting, or the model?

Two measurements behind docs/triple_plane.md ("Stone: the limit is parallax"):

``python benchmarks/measure_stone_limits.py oracle SPEC MODEL``
    Scores MODEL on its held-out pairs and on 64 random training pairs (a large gap = over-fitting,
    none = the model's capacity), and two oracles that see the ground truth of the training pairs:
    the nearest measured light at the same view, and the inverse-angle-weighted blend of the three
    nearest lights. If the oracle reaches a PSNR, the BTF's angular sampling supports it.

``python benchmarks/measure_stone_limits.py views SPEC MAX_THETA OUTPUT``
    Fits a Triple Plane (lr x3 as in the relief fits of docs/triple_plane.md, up to 64 texel groups, as many optimizer steps as a
    30-epoch fit of the whole BTF, the same total learning-rate decay) to the sub-BTF of the views
    with theta <= MAX_THETA degrees (all lights), and scores it on its held-out pairs (10%) and on
    64 training pairs. Training PSNR against the range of views shows how much of the model's
    capacity view dependence (parallax, masking) takes. ~3-4 minutes on 2 cores at 128^2.

``python benchmarks/measure_stone_limits.py parallax SPEC {none,oracle,stereo}``
    Fits the Triple Plane with its positional fetch moved, per view, to a point of the surface
    (the fast recipe: 30 epochs, lr x6, 64 texel groups, bf16, with every group's 16 pairs sharing one
    view), and scores it on the held-out pairs of the usual split (5 %, seed 0) and on 64 training
    pairs. ``none``: the texel centre, as the paper (the control: it must match ``dynbtf fit``).
    ``oracle``: the visible surface point the simulator traced (simulated BTFs only): what a perfect
    parallax and masking model would fetch. ``stereo``: the visible point traced through a height
    field estimated from the BTF alone by plane-sweep stereo
    (:func:`dynbtf.training.stereo_height.stereo_height`), kept fixed (``dynbtf fit --repr
    triple-parallax`` refines it). ~6 minutes each.

Seeds are fixed; the numbers are reproducible on one machine.
"""

from __future__ import annotations

import argparse
import time

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
from dynbtf.metrics.image_metrics import psnr
from dynbtf.representations.model_file import load_model
from dynbtf.training import TrainConfig, get_fitter
from dynbtf.training.evaluate import evaluate_model


def _training_sample(btf, held_out, n=64, seed=0):
    held = set(held_out)
    pairs = [(v, k) for v in range(btf.n_views) for k in range(btf.n_lights) if (v, k) not in held]
    rng = np.random.default_rng(seed)
    return [pairs[i] for i in rng.choice(len(pairs), min(n, len(pairs)), replace=False)]


def oracle(spec: str, model: str) -> None:
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
        nearest.append(psnr(truth, btf.image(v, candidates[order[0]])))
        weights = 1.0 / np.maximum(angle[order[:3]], 1e-3)
        weights /= weights.sum()
        estimate = sum(w * btf.image(v, candidates[o]) for w, o in zip(weights, order[:3]))
        blend3.append(psnr(truth, estimate))
    print(f"{spec}: {len(held)} held-out pairs")
    print(f"  model, held-out pairs        : {evaluate_model(rep, btf, held).summary()}")
    print(f"  model, 64 training pairs     : {evaluate_model(rep, btf, _training_sample(btf, held)).summary()}")
    print(f"  oracle, nearest light        : PSNR {np.mean(nearest):.2f} dB")
    print(f"  oracle, 3 nearest lights     : PSNR {np.mean(blend3):.2f} dB")


def views(spec: str, max_theta: float, output: str) -> None:
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
                         texel_groups=max(1, min(64, int(train_pairs) // 16)))
    get_fitter("triple")(sub, output, config)
    rep, meta = load_model(output)
    held = [tuple(p) for p in meta["provenance"]["held_out_pairs"]]
    print(f"views with theta <= {max_theta}: {len(keep)} views x {btf.n_lights} lights, {epochs} epochs")
    print(f"  held-out pairs    : {evaluate_model(rep, sub, held).summary()}")
    print(f"  64 training pairs : {evaluate_model(rep, sub, _training_sample(sub, held)).summary()}")


def parallax(spec: str, mode: str, epochs: int = 30) -> None:
    btf = open_btf(spec)
    size, n_texels, n_views, n_lights = btf.height, btf.height * btf.width, btf.n_views, btf.n_lights
    start = time.time()
    if mode == "none":
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
    train, held = held_out_split(n_views, n_lights, 0.05, 0)
    train_lights = [train[train[:, 0] == v, 1] for v in range(n_views)]
    rep = TriplePlane(size, size, seed=0)
    groups = [dict(g, lr=g["lr"] * 6.0) for g in rep.param_groups()]
    optimizer = torch.optim.AdamW(groups, fused=True)
    base_lr = [g["lr"] for g in optimizer.param_groups]
    n_groups, per_group = 64, 16
    n = n_texels // n_groups
    rng = np.random.default_rng(1)
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
    def score(pairs) -> float:
        values = []
        for v, k in pairs:
            features = fetch_wrap(rep.f_u, fetch_uv[v])
            model = rep.decode(features, views[v].expand(n_texels, 3), lights[k].expand(n_texels, 3))
            values.append(psnr(images[v, k].float().numpy().reshape(size, size, 3),
                               model.numpy().reshape(size, size, 3)))
        return float(np.mean(values))

    sample = train[np.random.default_rng(0).choice(len(train), 64, replace=False)]
    print(f"{spec}, positional fetch at {mode}: held-out PSNR {score(held):.2f} dB ({len(held)} pairs), "
          f"64 training pairs {score(sample):.2f} dB, {(time.time() - start) / 60:.1f} min")


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
    p = sub.add_parser("parallax")
    p.add_argument("spec")
    p.add_argument("mode", choices=("none", "oracle", "stereo"))
    p.add_argument("--epochs", type=int, default=30)
    args = parser.parse_args()
    if args.command == "oracle":
        oracle(args.spec, args.model)
    elif args.command == "views":
        views(args.spec, args.max_theta, args.output)
    else:
        parallax(args.spec, args.mode, args.epochs)


if __name__ == "__main__":
    main()
