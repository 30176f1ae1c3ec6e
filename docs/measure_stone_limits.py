"""What limits the Triple Plane on deep-relief materials: the data, over-fitting, or the model?

Two measurements behind docs/triple_plane.md ("Stone: what limits it"):

``python docs/measure_stone_limits.py oracle SPEC MODEL``
    Scores MODEL on its held-out pairs and on 64 random training pairs (a large gap = over-fitting,
    none = the model's capacity), and two oracles that see the ground truth of the training pairs:
    the nearest measured light at the same view, and the inverse-angle-weighted blend of the three
    nearest lights. If the oracle reaches a PSNR, the BTF's angular sampling supports it.

``python docs/measure_stone_limits.py views SPEC MAX_THETA OUTPUT``
    Fits a Triple Plane (lr x3 as in the relief fits of docs/triple_plane.md, up to 64 texel groups, as many optimizer steps as a
    30-epoch fit of the whole BTF, the same total learning-rate decay) to the sub-BTF of the views
    with theta <= MAX_THETA degrees (all lights), and scores it on its held-out pairs (10%) and on
    64 training pairs. Training PSNR against the range of views shows how much of the model's
    capacity view dependence (parallax, masking) takes. ~3-4 minutes on 2 cores at 128^2.

Seeds are fixed; the numbers are reproducible on one machine.
"""

from __future__ import annotations

import argparse

import numpy as np

from dynbtf.data.array import ArrayBTF
from dynbtf.data.open import open_btf
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
    args = parser.parse_args()
    if args.command == "oracle":
        oracle(args.spec, args.model)
    else:
        views(args.spec, args.max_theta, args.output)


if __name__ == "__main__":
    main()
