"""The parts the training loop composes, each against a brute-force reference:
the batch sampler (which pairs and texels a step sees, and their values), the checkpointer
(atomic, tied to its run) and the held-out monitor (PSNR of fixed pairs)."""

import numpy as np
import pytest
import torch

from dynbtf.errors import FormatError, InputError
from dynbtf.metrics import psnr
from dynbtf.training import monitor as monitor_module
from dynbtf.training.batches import BatchSampler
from dynbtf.training.checkpoint import Checkpointer
from dynbtf.training.images import ImageStore, held_out_split
from dynbtf.training.monitor import HeldOutMonitor
from synthetic_btf import synthetic_btf


@pytest.fixture(scope="module")
def btf():
    return synthetic_btf(size=6)  # 15 x 15 pairs, 36 texels


def _uncached(btf):
    return ImageStore(btf, 0)  # nothing cached: every value read from the source, exactly


def _brute_force_target(btf, pairs, texels):
    """``(B, N, 3)`` straight from whole images."""
    images = np.stack([btf.image(int(v), int(l)).reshape(-1, 3) for v, l in pairs])
    return images[:, texels]


def test_an_epoch_visits_every_training_pair_once(btf):
    train, _ = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=1)
    sampler = BatchSampler(_uncached(btf), train, images_per_step=16, seed=4)
    seen = np.concatenate([sampler.pairs(0, s) for s in range(sampler.steps_per_epoch)])
    assert sorted(map(tuple, seen)) == sorted(map(tuple, train))
    other_epoch = np.concatenate([sampler.pairs(1, s) for s in range(sampler.steps_per_epoch)])
    assert not np.array_equal(seen, other_epoch)  # reshuffled per epoch
    again = BatchSampler(_uncached(btf), train, images_per_step=16, seed=4)
    assert np.array_equal(again.pairs(3, 2), sampler.pairs(3, 2))  # the seed decides


def test_a_batch_holds_the_sources_values_at_its_pairs_and_texels(btf):
    train, _ = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=1)
    sampler = BatchSampler(_uncached(btf), train, images_per_step=4, texels_per_image=20, seed=2)
    batch = sampler.batch(1, 3)
    assert batch.texels is not None and len(batch.texels) == 20 and np.all(np.diff(batch.texels) > 0)
    np.testing.assert_array_equal(batch.target.numpy(), _brute_force_target(btf, batch.pairs, batch.texels))


def test_texel_groups_pair_each_block_of_texels_with_its_own_images(btf):
    """Group g's texels (a contiguous block, wrapping round) are seen under group g's images only."""
    train, _ = held_out_split(btf.n_views, btf.n_lights, 0.1, seed=1)
    g, b = 3, 4
    sampler = BatchSampler(_uncached(btf), train, images_per_step=b, texel_groups=g, texels_per_image=30, seed=5)
    batch = sampler.batch(0, 1)
    n = 30 // g
    assert batch.pairs.shape == (g * b, 2) and batch.target.shape == (b, g * n, 3)
    for k in range(g):
        block = batch.texels[k * n:(k + 1) * n]
        assert np.all(np.diff(block) % 36 == 1)  # consecutive texels of the 6 x 6 image, wrapping round
        want = _brute_force_target(btf, batch.pairs[k * b:(k + 1) * b], block)
        np.testing.assert_array_equal(batch.target[:, k * n:(k + 1) * n].numpy(), want)


def test_checkpoints_round_trip_and_belong_to_their_run(tmp_path):
    path = tmp_path / "m.dbtfm.ckpt"
    saver = Checkpointer(path, {"kind": "triple", "lr_scale": 1.0})
    saver.save({"model": {"w": torch.arange(4.0)}, "epoch": 2, "step": 7, "config": {"epochs": 9}})
    state = Checkpointer(path, {"kind": "triple", "lr_scale": 1.0}).load()
    assert state["epoch"] == 2 and state["step"] == 7 and torch.equal(state["model"]["w"], torch.arange(4.0))
    assert Checkpointer.saved_config(path) == {"epochs": 9}
    with pytest.raises(InputError, match=r"different training run \(differs in \['lr_scale'\]\)"):
        Checkpointer(path, {"kind": "triple", "lr_scale": 6.0}).load()


def test_a_failed_save_keeps_the_previous_checkpoint_and_damage_is_named(tmp_path, monkeypatch):
    path = tmp_path / "m.dbtfm.ckpt"
    saver = Checkpointer(path, {"kind": "triple"})
    saver.save({"epoch": 1})

    def crash(obj, f, *args, **kwargs):
        with open(f, "wb") as handle:
            handle.write(b"half")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", crash)
    with pytest.raises(OSError, match="disk full"):
        saver.save({"epoch": 2})
    monkeypatch.undo()
    assert saver.load()["epoch"] == 1 and sorted(p.name for p in tmp_path.iterdir()) == ["m.dbtfm.ckpt"]
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match=r"m\.dbtfm\.ckpt: damaged checkpoint"):
        saver.load()


def test_the_monitor_scores_its_pairs_like_psnr_on_whole_images(btf):
    _, held_out = held_out_split(btf.n_views, btf.n_lights, 0.2, seed=3)
    monitor = HeldOutMonitor(_uncached(btf), held_out, n_pairs=5, seed=0)
    assert len(monitor.pairs) == 5 and monitor.texels is None
    offsets = {tuple(p): 0.01 * (k + 1) for k, p in enumerate(monitor.pairs)}

    def predict(rep, w_view, w_light, size, texels):  # the truth, off by a known amount per pair
        out = []
        for wv, wl in zip(w_view.numpy(), w_light.numpy()):
            v = int(np.argmin(np.abs(btf.views - wv).sum(1)))
            l = int(np.argmin(np.abs(btf.lights - wl).sum(1)))
            out.append(btf.image(v, l).reshape(-1, 3) + offsets[(v, l)])
        return torch.from_numpy(np.stack(out))

    want = np.mean([psnr(btf.image(int(v), int(l)), btf.image(int(v), int(l)) + offsets[(v, l)])
                    for v, l in monitor.pairs])
    assert monitor.score(None, predict) == pytest.approx(want, rel=1e-5)


def test_the_monitor_keeps_to_a_fixed_texel_subset_on_large_btfs(btf, monkeypatch):
    monkeypatch.setattr(monitor_module, "MONITOR_TEXELS", 10)
    _, held_out = held_out_split(btf.n_views, btf.n_lights, 0.2, seed=3)
    a = HeldOutMonitor(_uncached(btf), held_out, n_pairs=4, seed=7)
    b = HeldOutMonitor(_uncached(btf), held_out, n_pairs=4, seed=7)
    assert len(a.texels) == 10 and len(np.unique(a.texels)) == 10 and np.array_equal(a.texels, b.texels)
