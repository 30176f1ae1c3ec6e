"""One training run for tests/test_distributed.py: run as a plain script (one process) or under
torchrun (several); writes the per-step losses and the final model to OUT_DIR."""

import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # synthetic_btf

import torch  # noqa: E402

from dynbtf.representations.triple_plane import TriplePlane  # noqa: E402
from dynbtf.training import TrainConfig, fit  # noqa: E402
from synthetic_btf import synthetic_btf  # noqa: E402


def main(out_dir: str, texel_groups: int, images_per_step: int, subtexel: float = 0.0) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    btf = synthetic_btf(size=8)
    config = TrainConfig(epochs=2, images_per_step=images_per_step, texel_groups=texel_groups, seed=3, workers=1,
                         monitor_pairs=2, device="cpu", precision="fp32", lr_scale=3.0, subtexel=subtexel)
    losses = []
    result = fit(TriplePlane(8, 8, positional_channels=8, angular_channels=4, hidden=16, seed=3), btf, config,
                 out / "model.dbtfm", progress=False, callback=lambda info: losses.append(info["loss"]))
    rank = int(os.environ.get("RANK", "0"))
    (out / f"losses_rank{rank}.json").write_text(json.dumps(losses))
    if rank == 0:
        torch.save(result.representation.state_dict(), out / "state.pt")


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]) if len(sys.argv) > 4 else 0.0)
