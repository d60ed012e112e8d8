"""The training loss, forward and backward, as the compiled kernel against the torch path, in one
run (the ratio is what to read: machines are shared and noisy).

    python -m exploregs_plugin.bench.components.loss                       # beer f4's size, 1 thread
    python -m exploregs_plugin.bench.components.loss --height 533 --width 800 --threads 2

The torch path is (1 - lambda) L1 + lambda (1 - SSIM) with the SSIM of five depthwise convolutions
(``model.losses.l1`` and ``ssim``), what a device without the compiled kernels trains with. The two
are timed alternately, ``--rounds`` times ``--repeats`` calls each, on random images of the size
given; the minimum over the calls of each round is reported.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import torch

from exploregs_plugin.kernels.photometric import photometric_loss_cpp
from exploregs_plugin.model.losses import MSE_FLOOR, SSIM_C1, SSIM_C2, l1, ssim

SSIM_LAMBDA = 0.2


@dataclass(frozen=True)
class LossTiming:
    compiled_ms: list[float]
    """Per round: the fastest forward + backward of the compiled kernel."""
    torch_ms: list[float]
    """Per round: the fastest forward + backward of the torch path."""
    loss_difference: float
    """|compiled - torch| of the loss on the benchmark's images (they compute the same value)."""


def _torch_loss(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return (1.0 - SSIM_LAMBDA) * l1(img, ref) + SSIM_LAMBDA * (1.0 - ssim(img, ref))


def _compiled_loss(img: torch.Tensor, ref: torch.Tensor, threads: int) -> torch.Tensor:
    return photometric_loss_cpp(img, ref, SSIM_LAMBDA, SSIM_C1, SSIM_C2, MSE_FLOOR, threads)[0]


def time_loss(height: int, width: int, threads: int = 1, rounds: int = 3, repeats: int = 50) -> LossTiming:
    gen = torch.Generator().manual_seed(0)
    img, ref = torch.rand(height, width, 3, generator=gen), torch.rand(height, width, 3, generator=gen)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        paths = {"compiled": lambda x: _compiled_loss(x, ref, threads), "torch": lambda x: _torch_loss(x, ref)}

        def fastest(loss_fn) -> float:
            best = float("inf")
            for _ in range(repeats):
                x = img.clone().requires_grad_()
                start = time.perf_counter()
                loss_fn(x).backward()
                best = min(best, time.perf_counter() - start)
            return best * 1e3

        for loss_fn in paths.values():  # warm-up: the kernels' build or load, allocator
            loss_fn(img.clone().requires_grad_()).backward()
        compiled, plain = [], []
        for _ in range(rounds):
            compiled.append(fastest(paths["compiled"]))
            plain.append(fastest(paths["torch"]))
        with torch.no_grad():
            difference = float((paths["compiled"](img) - paths["torch"](img)).abs())
    finally:
        torch.set_num_threads(previous)
    return LossTiming(compiled, plain, difference)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--height", type=int, default=176, help="image height (beer at --data-factor 4: 176)")
    parser.add_argument("--width", type=int, default=315, help="image width (beer at --data-factor 4: 315)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=50)
    args = parser.parse_args(argv)
    t = time_loss(args.height, args.width, args.threads, args.rounds, args.repeats)
    print(f"# training loss forward + backward, {args.width}x{args.height}x3 float32, {args.threads} thread(s), "
          f"fastest of {args.repeats} calls per round; |loss difference| {t.loss_difference:.2e}")
    print("| round | compiled (ms) | torch (ms) | compiled / torch |")
    print("|---|---|---|---|")
    for i, (c, p) in enumerate(zip(t.compiled_ms, t.torch_ms)):
        print(f"| {i + 1} | {c:.2f} | {p:.2f} | {c / p:.2f}x |")


if __name__ == "__main__":
    main()
