"""The held-out monitor: how well the model does on pairs it never trains on, during training.

After every epoch :func:`~dynbtf.training.fit.fit` scores a fixed set of held-out
(view, light) pairs (``monitor_pairs`` of them, evenly spread over the held-out list)
at a fixed set of texels: all of them for BTFs up to :data:`MONITOR_TEXELS` texels,
otherwise that many drawn once from the seed, so the monitor stays cheap on a
400 x 400 BTF. The score is the mean over pairs of each image's PSNR
(:func:`dynbtf.metrics.psnr`), as ``dynbtf eval`` averages it.
"""

from __future__ import annotations

import numpy as np
import torch

from ..metrics import psnr
from ..representations.base import Representation
from .images import ImageStore

__all__ = ["HeldOutMonitor", "MONITOR_TEXELS"]

#: Texels scored per monitored image on large BTFs (a 256 x 256 BTF and smaller are scored whole).
MONITOR_TEXELS = 65536


class HeldOutMonitor:
    """Scores a representation on fixed held-out pairs and texels.

    Parameters
    ----------
    store : ImageStore
        Serves the reference values.
    held_out : int64 ``(P, 2)``
        The held-out pairs; ``n_pairs`` of them evenly spread are monitored.
    n_pairs : int
    seed : int
        Seeds the texel subset of large BTFs.
    device : torch.device
    """

    def __init__(self, store: ImageStore, held_out: np.ndarray, n_pairs: int, seed: int = 0, device=None) -> None:
        self.store, self.device = store, torch.device("cpu") if device is None else torch.device(device)
        held_out = np.asarray(held_out, dtype=np.int64).reshape(-1, 2)
        self.pairs = held_out[np.linspace(0, len(held_out) - 1, min(n_pairs, len(held_out))).astype(int)] \
            if len(held_out) else held_out
        n = store.n_texels
        self.texels = None if n <= MONITOR_TEXELS else \
            np.sort(np.random.default_rng([int(seed), 3]).choice(n, MONITOR_TEXELS, replace=False))
        source = store.source
        self._views = torch.as_tensor(source.views, dtype=torch.float32, device=self.device)
        self._lights = torch.as_tensor(source.lights, dtype=torch.float32, device=self.device)

    def score(self, rep: Representation, predict) -> float:
        """Mean per-pair PSNR in dB (NaN without held-out pairs).

        ``predict(rep, w_view, w_light, size, texels)`` returns the model's values ``(B, N, 3)``
        (:func:`dynbtf.training.fit.predict_images`).
        """
        if len(self.pairs) == 0:
            return float("nan")
        source = self.store.source
        size = (source.height, source.width)
        texels_t = None if self.texels is None else torch.from_numpy(self.texels).to(self.device)
        values = []
        with torch.no_grad():
            for k in range(0, len(self.pairs), 8):
                chunk = self.pairs[k:k + 8]
                target = self.store.get(chunk, self.texels)
                pred = predict(rep, self._views[chunk[:, 0]], self._lights[chunk[:, 1]], size, texels_t)
                pred = pred.float().cpu().numpy()
                values += [psnr(t[:, None], p[:, None]) for t, p in zip(target, pred)]
        return float(np.mean(values))
