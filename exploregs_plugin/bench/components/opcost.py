"""Per-element cost of the torch ops the compositor is built from, and the effect of
``torch.set_flush_denormal`` on a full render (thread CPU time, one thread).

    python -m exploregs_plugin.bench.components.opcost
"""

from __future__ import annotations

import time

import torch

from exploregs_plugin.rasterizer import rasterize
from .raster_scenes import random_scene
from exploregs_plugin.rasterizer.settings import RasterSettings


def _ns_per_element(fn, n_elements: int, repeats: int = 200) -> float:
    for _ in range(3):
        fn()
    t = time.thread_time()
    for _ in range(repeats):
        fn()
    return (time.thread_time() - t) / repeats / n_elements * 1e9


def op_costs(n: int = 1 << 17) -> dict[str, float]:
    """ns per element of float32 ops on cache-sized tensors."""
    g = torch.Generator().manual_seed(0)
    x = -20.0 * torch.rand(n, generator=g)
    y = torch.rand(n, generator=g)
    mask = torch.rand(n, generator=g) < 0.5
    buf = torch.empty(n)
    rows = y.view(512, -1)
    w = torch.rand(2, 256, n // 512, generator=g)
    f = torch.rand(2, n // 512, 4, generator=g)
    f_col = f.transpose(1, 2).contiguous().transpose(1, 2)
    return {
        "exp": _ns_per_element(lambda: torch.exp(x, out=buf), n),
        "exp2": _ns_per_element(lambda: torch.exp2(x, out=buf), n),
        "mul": _ns_per_element(lambda: torch.mul(x, y, out=buf), n),
        "threshold": _ns_per_element(lambda: torch.nn.functional.threshold(y, 0.5, 0.0), n),
        "sign": _ns_per_element(lambda: torch.sign(y, out=buf), n),
        "masked_fill (bool mask)": _ns_per_element(lambda: buf.masked_fill_(mask, 0.0), n),
        "where (bool mask)": _ns_per_element(lambda: torch.where(mask, x, y), n),
        "cumprod (last dim)": _ns_per_element(lambda: torch.cumprod(rows, -1), n),
        "cumsum (last dim)": _ns_per_element(lambda: torch.cumsum(rows, -1), n),
        "bmm [B,P,K]x[B,K,4], thin operand row-major": _ns_per_element(lambda: torch.bmm(w, f), w.numel()),
        "bmm [B,P,K]x[B,K,4], thin operand column-major": _ns_per_element(lambda: torch.bmm(w, f_col), w.numel()),
    }


def flush_denormal_effect(repeats: int = 5) -> dict[str, float]:
    """Median thread CPU seconds of one forward+backward of the S scene, without/with flushing."""
    s = random_scene(20_000, 256, 256, torch.Generator().manual_seed(0))
    params = [t.clone().requires_grad_() for t in (s.means, s.quats, s.scales, s.opacities, s.sh_coeffs)]
    settings = RasterSettings(workers=1)

    def fb():
        img, *_ = rasterize(*params, s.camera, settings=settings)
        img.sum().backward()

    out = {}
    for flag in (False, True, False, True):
        torch.set_flush_denormal(flag)
        fb()
        times = []
        for _ in range(repeats):
            t = time.thread_time()
            fb()
            times.append(time.thread_time() - t)
        out.setdefault(f"flush_denormal={flag}", []).append(sorted(times)[repeats // 2])
    torch.set_flush_denormal(False)
    return {k: min(v) for k, v in out.items()}


def main() -> None:
    torch.set_num_threads(1)
    print("| op | ns / element |\n|---|---|")
    for name, ns in op_costs().items():
        print(f"| {name} | {ns:.2f} |")
    print("\n| S scene forward+backward, 1 thread | CPU s |\n|---|---|")
    for name, sec in flush_denormal_effect().items():
        print(f"| {name} | {sec:.3f} |")


if __name__ == "__main__":
    main()
