"""Which filtered query works for features + decoder: a study on one fitted model (the filtering issue).

For a footprint of ``2^k x 2^k`` texels the right answer is the BTF averaged over it: here the
measured images box-filtered by ``2^k`` (held-out pairs). Candidates, scored against it with the
per-image-peak PSNR:

* **point sample** -- today's query: one texel of the block (what aliasing shows);
* **decode(mip features)** -- the decoder on box-filtered features (the decoder is nonlinear);
* **filtered decoded** -- the model's own output averaged over the block (what supersampling
  the model converges to: the ceiling of any filtered query of this model);
* **tuned planes, frozen decoder** -- a positional plane per level, initialized with the mip of
  ``f_U`` and fitted (L1, Adam) to the filtered images with the decoder and angular planes kept;
* **tuned planes + decoder** -- the same with a decoder copy per level fitted too.

Run: ``python benchmarks/measure_filtering.py MODEL.dbtfm 'sim:leather?size=32'`` (a few minutes at
32 x 32 texels on 2 cores).
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
import torch
import torch.nn.functional as F


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model")
    parser.add_argument("btf")
    parser.add_argument("--levels", default="1,2,3,5")
    parser.add_argument("--steps", type=int, default=600)
    args = parser.parse_args()

    from dynbtf.data.open import open_btf
    from dynbtf.metrics import psnr
    from dynbtf.representations.model_file import load_model

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rep, meta = load_model(args.model)
    src = open_btf(args.btf)
    n_lights = src.n_lights
    held = np.array(meta["provenance"]["held_out_pairs"])
    pairs = np.array([(v, l) for v in range(src.n_views) for l in range(n_lights)])
    images = torch.from_numpy(np.stack([src.image(v, l) for v, l in pairs]).astype(np.float32)).permute(0, 3, 1, 2)
    views = torch.tensor(src.views, dtype=torch.float32)
    lights = torch.tensor(src.lights, dtype=torch.float32)
    held_index = np.array([v * n_lights + l for v, l in held])
    test = held_index[::4]
    train = np.setdiff1d(np.arange(len(pairs)), held_index)
    f_u = rep.f_u.detach()

    def target(k):
        return (F.avg_pool2d(images, 2 ** k) if k else images).permute(0, 2, 3, 1)

    def mip(plane, k):
        return F.avg_pool2d(plane.permute(2, 0, 1)[None], 2 ** k)[0].permute(1, 2, 0) if k else plane

    def decode(plane, index, decoder):
        with torch.no_grad():
            angular = rep.angular_features(views[pairs[index, 0]], lights[pairs[index, 1]])
            return decoder(plane.reshape(-1, plane.shape[-1])[None], angular[:, None])

    def score(pred, index, k):
        truth = target(k)[index].reshape(len(index), -1, 3).numpy()
        return float(np.mean([psnr(a[:, None], b[:, None]) for a, b in zip(truth, pred.numpy())]))

    for k in (int(x) for x in args.levels.split(",")):
        row = {"point sample": score(decode(f_u[::2 ** k, ::2 ** k], test, rep.decoder), test, k),
               "decode(mip features)": score(decode(mip(f_u, k), test, rep.decoder), test, k)}
        full = decode(f_u, test, rep.decoder).reshape(len(test), *f_u.shape[:2], 3).permute(0, 3, 1, 2)
        row["filtered decoded"] = score(F.avg_pool2d(full, 2 ** k).permute(0, 2, 3, 1).reshape(len(test), -1, 3),
                                        test, k)
        flat_target = target(k).reshape(len(pairs), -1, 3)
        for tune_decoder in (False, True):
            plane = mip(f_u, k).clone().requires_grad_()
            decoder = copy.deepcopy(rep.decoder).requires_grad_(tune_decoder)
            groups = [{"params": [plane], "lr": 3e-3}]
            if tune_decoder:
                groups.append({"params": list(decoder.parameters()), "lr": 1e-3})
            optimizer = torch.optim.Adam(groups)
            for _ in range(args.steps):
                index = rng.choice(train, 64, replace=False)
                with torch.no_grad():
                    angular = rep.angular_features(views[pairs[index, 0]], lights[pairs[index, 1]])
                pred = decoder(plane.reshape(-1, plane.shape[-1])[None], angular[:, None])
                loss = (pred - flat_target[index]).abs().mean()
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
            name = "tuned planes + decoder" if tune_decoder else "tuned planes, frozen decoder"
            row[name] = score(decode(plane.detach(), test, decoder), test, k)
        print(f"level {k} ({2 ** k} x {2 ** k} texels): " + ", ".join(f"{a} {b:.2f} dB" for a, b in row.items()),
              flush=True)


if __name__ == "__main__":
    main()
