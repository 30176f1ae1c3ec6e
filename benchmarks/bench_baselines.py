"""The paper's representations side by side on a small BTF, over several seeds: held-out quality, storage and fit time.

Usage::

    python benchmarks/bench_baselines.py [--btf 'sim:leather?size=64'] [--kinds triple,neumip,pca,sh] [--seeds 3]
                                         [--epochs 30] [--lr-scale 3] [--texel-groups 64] [--out DIR]
                                         [--json benchmarks/results/baselines.json] [--part small]

Each seed runs :func:`dynbtf.compare.compare_representations` (what ``dynbtf compare --repr ...`` runs) into a
folder of its own under ``--out``: every kind fitted with that seed (its held-out split and its initialization)
and scored on the same held-out pairs. The rows -- per kind, each number's mean and min-max over the seeds, the
storage, and the best mean of each quality column marked -- become part ``--part`` of the ``--json`` file (its
other parts kept); docs/results.md's "Baselines: further comparisons" table is generated from it
(``benchmarks/tables.py``). About 4 minutes per seed on 2 cores for the default 64 x 64 BTF.

``--storage`` measures only what each kind stores (its positional plane and the whole model, float32): one fit of
one epoch per kind (sizes do not depend on training), part ``storage``, docs/baselines.md's storage table::

    python benchmarks/bench_baselines.py --storage --btf 'sim:leather?size=128'
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from results_io import spread  # benchmarks/ is on the path of a script run from it

#: The quality numbers kept per seed, and whether a higher value is better.
QUALITY = {"psnr": True, "psnr_fixed1": True, "dssim": False, "flip": False}



def summarize(scores_per_seed: list[list]) -> list[dict]:
    """A row per kind from each seed's :class:`~dynbtf.compare.RepresentationScore` list (the same kinds in the same
    order): the quality numbers and fit seconds as :func:`spread`, the storage (the same for every seed), and under
    ``"bold"`` the quality columns in which this kind's mean is the best."""
    rows = []
    for i, first in enumerate(scores_per_seed[0]):
        mine = [scores[i] for scores in scores_per_seed]
        assert all(s.kind == first.kind for s in mine)
        rows.append({"kind": first.kind, **{key: spread([getattr(s, key) for s in mine]) for key in QUALITY},
                     "model_bytes": int(first.storage_bytes), "positional_bytes": int(first.positional_bytes),
                     "fit_seconds": spread([s.fit_seconds for s in mine])})
    for key, higher in QUALITY.items():
        best = (max if higher else min)(rows, key=lambda r: r[key]["mean"])
        best.setdefault("bold", []).append(key)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--btf", default="sim:leather?size=64", help="BTF path or spec")
    parser.add_argument("--kinds", default="triple,neumip,pca,sh")
    parser.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 (each: its held-out split and its fits)")
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--lr-scale", type=float, default=3.0)
    parser.add_argument("--texel-groups", type=int, default=64)
    parser.add_argument("--out", type=Path, default=Path("bench_baselines"),
                        help="the comparisons' folders (models kept: a second run reuses them)")
    parser.add_argument("--json", type=Path, default=Path(__file__).resolve().parent / "results" / "baselines.json")
    parser.add_argument("--part", default="small", help="the part of --json the rows go to")
    parser.add_argument("--storage", action="store_true",
                        help="only each kind's storage (one 1-epoch fit per kind): part 'storage'")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error(f"--seeds: expected at least 1, got {args.seeds}")
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from results_io import write_part

    from dynbtf.compare import compare_representations
    from dynbtf.data.open import open_btf
    from dynbtf.training import TrainConfig

    source = open_btf(args.btf)
    kinds = args.kinds.split(",")
    if args.storage:
        scores = compare_representations(source, args.out / "storage", kinds, TrainConfig(epochs=1, seed=0),
                                         progress=False)
        write_part(args.json, "storage", "bench_baselines.py", {
            "btf": args.btf, "height": source.height, "width": source.width, "n_pairs": source.n_pairs,
            "conditions": "float32; one 1-epoch fit per kind (what a kind stores does not depend on its training)",
            "rows": [{"kind": s.kind, "positional_bytes": int(s.positional_bytes), "model_bytes": int(s.storage_bytes)}
                     for s in scores]})
        return
    scores_per_seed = []
    start = time.perf_counter()
    for seed in range(args.seeds):
        config = TrainConfig(epochs=args.epochs, lr_scale=args.lr_scale, texel_groups=args.texel_groups, seed=seed)
        scores = compare_representations(source, args.out / f"seed{seed}", kinds, config, progress=False)
        scores_per_seed.append(scores)
        print(f"seed {seed}: " + ", ".join(f"{s.kind} {s.psnr_fixed1:.2f} dB" for s in scores)
              + f" ({(time.perf_counter() - start) / 60:.1f} min so far)", file=sys.stderr, flush=True)
    write_part(args.json, args.part, "bench_baselines.py", {
        "btf": args.btf, "seeds": list(range(args.seeds)),
        "conditions": f"{args.epochs} epochs, learning rates x{args.lr_scale:g}, {args.texel_groups} texel groups; "
                      f"each number the mean over the seeds (min-max), the held-out split the seed's; "
                      f"{(time.perf_counter() - start) / 60:.1f} min in all",
        "rows": summarize(scores_per_seed)})
    from tables import baselines_small

    print("\n" + baselines_small({"small": json.loads(args.json.read_text())[args.part]}))


if __name__ == "__main__":
    main()
