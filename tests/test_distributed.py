"""Data-parallel training (torchrun, gloo on the CPU) against one process training the same global batch."""

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parent / "ddp_fit.py"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(out: Path, groups: int, images: int, processes: int, subtexel: float) -> None:
    args = [str(out), str(groups), str(images), str(subtexel)]
    if processes == 1:
        command = [sys.executable, str(SCRIPT), *args]
    else:
        command = [sys.executable, "-m", "torch.distributed.run", f"--nproc-per-node={processes}",
                   "--master-addr=127.0.0.1", f"--master-port={_free_port()}", str(SCRIPT), *args]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]


@pytest.mark.parametrize("groups, images, subtexel", [(4, 8, 0.0), (1, 8, 0.0), (4, 8, 0.5), (1, 8, 0.5)],
                         ids=["texel-groups", "whole-images", "texel-groups-subtexel", "whole-images-subtexel"])
def test_two_gloo_processes_follow_the_single_process_loss_curve(tmp_path, groups, images, subtexel):
    """Also with the sub-texel term, which one process computes for the whole step."""
    _run(tmp_path / "one", groups, images, 1, subtexel)
    _run(tmp_path / "two", groups, images, 2, subtexel)
    single = np.array(json.loads((tmp_path / "one" / "losses_rank0.json").read_text()))
    ranks = [np.array(json.loads((tmp_path / "two" / f"losses_rank{r}.json").read_text())) for r in (0, 1)]
    assert len(single) > 20 and all(len(r) == len(single) for r in ranks)
    np.testing.assert_array_equal(ranks[0], ranks[1])  # every process reports the whole step's loss
    np.testing.assert_allclose(ranks[0], single, rtol=1e-5, atol=1e-7)  # measured: 9e-8 relative
    one = torch.load(tmp_path / "one" / "state.pt")
    two = torch.load(tmp_path / "two" / "state.pt")
    for name in one:
        torch.testing.assert_close(two[name], one[name], rtol=1e-4, atol=1e-5)  # measured: 2e-7
    assert (tmp_path / "two" / "model.dbtfm").is_file() and not (tmp_path / "two" / "model.dbtfm.ckpt").exists()
