"""One generator step of the generative feature synthesis, forward + backward: today's MMD against the earlier one.

    .venv/bin/python benchmarks/bench_feature_synthesis.py [--width 384] [--repeats 21] [--threads 1] [--spread 1.0]

Implementations (the same generator, the same 8 classes x 128 samples, ``SynthesisConfig``'s bandwidths):
- ``mmd2``: the classes batched, squared distances in Gram form about the samples' mean, kernel exponents floored
  at ``EXPONENT_FLOOR`` (``ovgaussian.openvocab.feature_synthesis``);
- ``cdist, per class``: as ``train_generator`` was written before: a ``torch.cdist`` of each class's real and
  generated samples, squared, one ``exp`` per bandwidth with no floor, the classes summed in a Python loop.

The real samples are standard normal features times ``--spread`` (the trainer standardizes the model's features, so
1.0 is what it sees; far pairs then reach exponents of about -6,000, where ``exp`` leaves its fast path). Each is
timed alternated (A B A B ...), median wall time of ``--repeats`` steps, and the two losses are printed to show they
agree.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--width", type=int, default=384, help="feature width (the slim model's semantic width)")
    parser.add_argument("--text-width", type=int, default=384, help="text embedding width")
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--spread", type=float, default=1.0, help="scale of the real features")
    args = parser.parse_args()

    import torch

    from ovgaussian.openvocab.config import SynthesisConfig
    from ovgaussian.openvocab.feature_synthesis import FeatureGenerator, mmd2

    torch.set_num_threads(args.threads)
    config = SynthesisConfig()
    classes, n = config.classes_per_step, config.samples_per_class
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    text = torch.randn(classes, args.text_width, generator=g)
    real = torch.randn(classes, n, args.width, generator=g) * args.spread
    gen = FeatureGenerator(args.text_width, args.width, config)

    def batched() -> torch.Tensor:
        fake = gen(text, n, torch.Generator().manual_seed(1))
        return mmd2(fake.reshape(classes, n, -1), real, config.kernel_bandwidths).sum()

    def per_class_cdist() -> torch.Tensor:
        fake = gen(text, n, torch.Generator().manual_seed(1))
        loss = torch.zeros(())
        for j in range(classes):
            xy = torch.cat([fake[j * n:(j + 1) * n], real[j]])
            d2 = torch.cdist(xy, xy).square()
            k = sum(torch.exp(-d2 / (2.0 * h * h)) for h in config.kernel_bandwidths)
            loss = loss + k[:n, :n].mean() + k[n:, n:].mean() - 2.0 * k[:n, n:].mean()
        return loss

    impls = {"mmd2 (batched, Gram form, floored exponent)": batched, "cdist, per class (before)": per_class_cdist}
    times: dict[str, list[float]] = {name: [] for name in impls}
    losses: dict[str, float] = {}
    for rep in range(args.repeats + 1):
        for name, fn in impls.items():
            gen.zero_grad()
            t0 = time.perf_counter()
            loss = fn()
            loss.backward()
            if rep:
                times[name].append(time.perf_counter() - t0)
            losses[name] = float(loss.detach())
    print(f"generator step: {classes} classes x {n} samples, width {args.width}, spread {args.spread}, "
          f"{args.threads} thread(s), forward + backward, median of {args.repeats} (alternated):")
    for name, values in times.items():
        print(f"  {name}: {statistics.median(values) * 1e3:.1f} ms (loss {losses[name]:.6f})")


if __name__ == "__main__":
    main()
