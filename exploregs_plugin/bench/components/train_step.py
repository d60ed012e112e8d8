"""Cost of one training step against the bare renderer step on the same Gaussians and camera.

    python -m exploregs_plugin.bench.components.train_step --data builtin:default --methods exploregs-seedsplit
    python -m exploregs_plugin.bench.components.train_step --data ../shared/scenes/beer --data-factor 4 --backends torch cpp
    python -m exploregs_plugin.bench.components.train_step --data ../shared/scenes/beer --device cuda --backend gsplat

Trains ``--warmup`` steps (so the set has grown), then times ``--steps`` more of each, in turn:

- ``train step``: the pipeline's whole step (data, render, loss, backward, Adam, strategy);
- ``bare step``: the renderer's forward + backward of the same loss + Adam on a copy of the same
  Gaussians, one fixed camera, no strategy and no data loading: what the renderer alone costs;
- ``gsplat step`` (gsplat backend only): the same bare step written with gsplat's own
  ``gsplat.rasterization`` (RGB, packed=False, as gsplat's simple trainer renders) instead of our
  backend, so our wrapper's cost (background, expected depth, info) shows too.

The ratio train / bare is the engine's overhead and train / gsplat the whole cost over a bare
gsplat trainer's step (the gsplat backend's target for both is at most 1.3); the
speed-up is the first backend's train step over this one's, for the same method (same seed, so
the same Gaussians before timing up to float rounding).
Times are medians; on a GPU every step is waited for (torch.cuda.synchronize).
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.model.gaussians import activate, render_params
from exploregs_plugin.model.losses import photometric_loss
from exploregs_plugin.model.optim import set_lr


def _timed(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def measure(data: str, method: str, device: str, backend: str, warmup: int, steps: int, data_factor: int | None,
            max_steps: int, profile: int = 0) -> dict:
    """Median seconds of a training step and of the bare renderer step, and what they ran on;
    with ``profile`` > 0, also torch.profiler's table of that many more training steps (the
    operators by self CPU time, under "profile")."""
    base = get_method(method).config
    config = replace(base, data=data, data_factor=data_factor, max_steps=max_steps, device=device)
    config.pipeline.model.raster = replace(config.pipeline.model.raster, backend=backend)
    where = resolve_device(device)
    pipeline = config.pipeline.setup(config.schedule.resolve(max_steps), config.seed, where)
    for step in range(warmup):
        pipeline.train_step(step)
    train = [_timed(lambda s=step: pipeline.train_step(s), where) for step in range(warmup, warmup + steps)]
    table = None
    if profile > 0:
        from torch.profiler import ProfilerActivity, profile as profiler

        with profiler(activities=[ProfilerActivity.CPU]) as prof:
            for step in range(warmup + steps, warmup + steps + profile):
                pipeline.train_step(step)
        table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25)

    params = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach().clone()) for k, v in pipeline.params.items()})
    optimizers = config.pipeline.optim.setup(params, pipeline.scene_extent)
    set_lr(optimizers["means"], pipeline.means_lr_at(warmup))
    camera, target, _ = pipeline.datamanager.train_item(0)
    target = target.to(where)
    degree = pipeline.sh_degree_at(warmup)

    def optimise(image: torch.Tensor) -> None:
        loss, _ = photometric_loss(image, target, config.pipeline.ssim_lambda)
        loss.backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)

    def bare() -> None:
        optimise(render_params(params, camera, degree, pipeline.background, settings=pipeline.model.config.raster)[0])

    def native() -> None:
        # gsplat's own call, as its simple trainer makes it: activated parameters, RGB only
        from gsplat import rasterization

        renders, _, _ = rasterization(
            *activate(params), camera.viewmat.to(where)[None], camera.K.to(where)[None],
            int(camera.width), int(camera.height), sh_degree=degree, packed=False,
        )  # fmt: skip
        optimise(renders[0])

    bare()  # warm-up
    bare_times = [_timed(bare, where) for _ in range(steps)]
    t_train, t_bare = statistics.median(train), statistics.median(bare_times)
    t_native = None
    if backend == "gsplat":
        native()  # warm-up
        t_native = statistics.median([_timed(native, where) for _ in range(steps)])
    peak = torch.cuda.max_memory_allocated(where) / 2**30 if where.type == "cuda" else None
    return {"device": str(where) if where.type == "cpu" else torch.cuda.get_device_name(where), "backend": backend,
            "method": method, "gaussians": pipeline.model.num_gaussians, "train_s": t_train, "bare_s": t_bare,
            "ratio": t_train / t_bare, "native_s": t_native, "peak_gib": peak, "size": f"{camera.width}x{camera.height}",
            "profile": table}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="builtin:default")
    ap.add_argument("--data-factor", type=int, default=None)
    ap.add_argument("--methods", nargs="+", default=["exploregs-default", "exploregs-seedsplit"])
    ap.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N")
    ap.add_argument("--backends", nargs="+", default=["torch", "cpp"], choices=["torch", "cpp", "gsplat"])
    ap.add_argument("--warmup", type=int, default=300, help="steps trained before timing (the set grows)")
    ap.add_argument("--steps", type=int, default=20, help="timed steps of each kind (median)")
    ap.add_argument("--max-steps", type=int, default=1500, help="run length the schedule is resolved for")
    ap.add_argument("--profile", type=int, default=0, help="also profile this many training steps (torch.profiler)")
    a = ap.parse_args(argv)
    print(f"# torch {torch.__version__}; {a.data} (data factor {a.data_factor or 'default'}); "
          f"{a.warmup} warm-up steps, median of {a.steps}")
    print("| method | backend | device | image | Gaussians | train step s | bare step s | train / bare | gsplat step s | "
          "train / gsplat | speed-up | peak GPU GiB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for method in a.methods:
        first = None
        for backend in a.backends:
            r = measure(a.data, method, a.device, backend, a.warmup, a.steps, a.data_factor, a.max_steps, a.profile)
            first = first or r
            peak = f"{r['peak_gib']:.2f}" if r["peak_gib"] is not None else ""
            native = ("| |" if r["native_s"] is None else
                      f"{r['native_s']:.4f} | {r['train_s'] / r['native_s']:.2f} |")
            print(f"| {r['method']} | {r['backend']} | {r['device']} | {r['size']} | {r['gaussians']:,} | "
                  f"{r['train_s']:.4f} | {r['bare_s']:.4f} | {r['ratio']:.2f} | {native} "
                  f"{first['train_s'] / r['train_s']:.2f}x | {peak} |", flush=True)
            if r["profile"] is not None:
                print(f"\nprofile of {a.profile} training steps, {r['method']}, {r['backend']}:\n{r['profile']}", flush=True)


if __name__ == "__main__":
    main()
