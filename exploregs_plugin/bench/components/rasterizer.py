"""Speed / memory / error benchmark of the rasterizer against a plain autograd compositor.

    python -m exploregs_plugin.bench.components.rasterizer            # cpp and torch on S, M and (if present) beer
    python -m exploregs_plugin.bench.components.rasterizer --methods torch torch-cuda gsplat --scenes S M L   # GPU

Every (scene, method) runs in a fresh subprocess, so its peak resident memory is its own.
Times are medians of ``--repeats`` runs after warm-up: wall clock and process CPU time (the
CPU time stays meaningful when other processes share the cores). Errors are against the dense
float64 reference on 32 x 32 windows: image (max / mean absolute) and the gradients of a
windowed loss (max |difference| / max |reference|, worst parameter).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from exploregs_plugin.runtime.device import resolve_device
from exploregs_plugin.rasterizer import rasterize
from exploregs_plugin.rasterizer.reference import reference_rasterize
from exploregs_plugin.rasterizer.settings import RasterSettings

from .raster_baseline import rasterize_baseline
from .raster_scenes import GaussianScene, random_scene

SCENES = {"S": (20_000, 256, 256), "M": (50_000, 512, 512), "L": (500_000, 1024, 1024)}
METHODS = {"cpp": "cpu", "torch": "cpu", "baseline": "cpu", "torch-cuda": "cuda", "gsplat": "cuda"}
"""Method -> device: the compiled CPU backend (cpp), the pure-torch rasterizer (torch), the plain
autograd compositor (baseline), the torch rasterizer on CUDA, and gsplat's CUDA kernels."""
BACKEND = {"cpp": "cpp", "torch": "torch", "torch-cuda": "torch", "gsplat": "gsplat"}
BASE = {"cpp": "torch", "torch": "baseline", "torch-cuda": "torch", "gsplat": "torch"}
"""The row each method's speed-up is measured against, when it ran."""
SCENES_DIR = Path(__file__).resolve().parents[3] / "shared" / "scenes"
WINDOW = 32


def beer_scene(data_factor: int = 4, image_index: int = 0) -> GaussianScene:
    """The beer capture's sparse points as small isotropic Gaussians (3DGS initialisation:
    scale = mean distance to the 3 nearest points, opacity 0.1, SH DC from the point colour),
    seen from one registered camera at 1/data_factor resolution (radial distortion ignored)."""
    import numpy as np
    import pycolmap

    rec = pycolmap.Reconstruction(str(SCENES_DIR / "beer" / "sparse" / "0"))
    img = rec.images[sorted(rec.images)[image_index]]
    cam = rec.cameras[img.camera_id]
    f, cx, cy = (float(v) for v in cam.params[:3])
    pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
    view = torch.eye(4, dtype=torch.float64)
    view[:3] = torch.from_numpy(np.asarray(pose.matrix()))
    pts = torch.tensor(np.array([p.xyz for p in rec.points3D.values()]), dtype=torch.float64)
    rgb = torch.tensor(np.array([p.color for p in rec.points3D.values()]), dtype=torch.float64) / 255.0
    d = torch.cdist(pts, pts)
    d.fill_diagonal_(float("inf"))
    scale = d.topk(3, largest=False).values.mean(-1).clamp_min(1e-7)
    n = pts.shape[0]
    sh = torch.zeros(n, 16, 3, dtype=torch.float64)
    sh[:, 0] = (rgb - 0.5) / 0.28209479177387814
    s = 1.0 / data_factor
    K = torch.tensor([[f * s, 0, cx * s], [0, f * s, cy * s], [0, 0, 1]], dtype=torch.float64)
    quats = torch.zeros(n, 4, dtype=torch.float64)
    quats[:, 0] = 1.0
    scene = GaussianScene(pts, quats, scale[:, None].repeat(1, 3), torch.full((n,), 0.1, dtype=torch.float64), sh,
                          view, K, round(cam.width * s), round(cam.height * s))  # fmt: skip
    return scene.to(torch.float32)


def checkpoint_scene(path: str, view: int = 0) -> GaussianScene:
    """A trained set: the Gaussians of a checkpoint (a ``.pt`` file, or a run folder's newest),
    seen from training view ``view`` of its run (loaded on the CPU)."""
    from exploregs_plugin.model.gaussians import activate_detached
    from exploregs_plugin.runs.load import load_run

    run = load_run(Path(path), "cpu")
    cameras = run.pipeline.datamanager.train_cameras
    if not 0 <= view < len(cameras):
        raise ValueError(f"bench: {path} has {len(cameras)} training views, no view {view}")
    cam = cameras[view]
    scene = GaussianScene(*activate_detached(run.pipeline.model.params), cam.viewmat, cam.K, int(cam.width), int(cam.height))
    return scene.to(torch.float32)


def make_scene(name: str) -> GaussianScene:
    """S, M, L (random), beer (its sparse points), or ``PATH[@VIEW]``: a checkpoint's trained set."""
    if name in SCENES:
        n, w, h = SCENES[name]
        return random_scene(n, w, h, torch.Generator().manual_seed(0))
    if name == "beer":
        return beer_scene()
    path, _, view = name.rpartition("@") if "@" in name else (name, "", "0")
    if Path(path).exists() and view.isdigit():
        return checkpoint_scene(path, int(view))
    raise ValueError(f"bench: unknown scene '{name}' (choose from {', '.join(SCENES)}, beer, or a checkpoint "
                     f"PATH[@VIEW])")


def _windows(w: int, h: int) -> list[tuple[int, int, int, int]]:
    size = min(WINDOW, w, h)
    spots = [(0.5, 0.5), (0.2, 0.3), (0.8, 0.7), (0.3, 0.85)]
    return [(int((w - size) * fx), int((h - size) * fy), size, size) for fx, fy in spots]


def _rasterize(method: str, params, scene: GaussianScene, settings: RasterSettings):
    """(image, alpha, depth, info) of ``method`` on the scene's camera."""
    args = (*params, scene.camera.to(params[0]))
    if method == "baseline":
        return rasterize_baseline(*args, settings=replace(settings, backend="torch"))
    return rasterize(*args, settings=replace(settings, backend=BACKEND[method]))


def _render(method: str, params, scene: GaussianScene, settings: RasterSettings):
    return _rasterize(method, params, scene, settings)[0]


def _median_times(fn, repeats: int, device: torch.device) -> tuple[float, float]:
    """Median wall and process-CPU seconds; on a GPU the kernels are waited for."""
    walls, cpus = [], []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t, c = time.perf_counter(), time.process_time()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus)


def run_child(scene_name: str, method: str, repeats: int, settings: RasterSettings) -> dict:
    load0 = os.getloadavg()[0]
    device = resolve_device(METHODS[method])
    scene = make_scene(scene_name)
    params = [t.to(device, copy=True).requires_grad_() for t in (scene.means, scene.quats, scene.scales,
                                                                 scene.opacities, scene.sh_coeffs)]  # fmt: skip
    wts = torch.rand(scene.height, scene.width, 3, generator=torch.Generator().manual_seed(1)).to(device)

    def forward():
        return _render(method, params, scene, settings)

    def forward_backward():
        for p in params:
            p.grad = None
        (forward() * wts).sum().backward()

    first = _median_times(forward_backward, 1, device)[0]  # includes gsplat's kernel compilation
    forward_backward()  # warm-up
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    fwd = _median_times(forward, repeats, device)
    fb = _median_times(forward_backward, repeats, device)
    if device.type == "cuda":
        peak_mib = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    load1 = os.getloadavg()[0]
    with torch.no_grad():
        # the pair count comes from our rasterizer (the baseline composites the same pairs)
        info = _rasterize("torch" if method == "baseline" else method, params, scene, settings)[3]
    img_err, grad_err = _errors(method, params, scene, settings, wts)
    return {
        "scene": scene_name, "method": method, "n": scene.means.shape[0], "size": f"{scene.width}x{scene.height}",
        "first_s": first, "fwd_s": fwd[0], "fwd_cpu_s": fwd[1], "fb_s": fb[0], "fb_cpu_s": fb[1],
        "peak_mib": peak_mib, "pairs": info["n_pairs"], "img_max": img_err[0], "img_mean": img_err[1],
        "grad_rel": grad_err, "load": (load0 + load1) / 2, "threads": torch.get_num_threads(),
        "device": str(device) if device.type == "cpu" else torch.cuda.get_device_name(device),
    }  # fmt: skip


def _errors(method, params, scene, settings, wts) -> tuple[tuple[float, float], float]:
    """Image error over the windows and the worst relative gradient error of a windowed loss."""
    wins = _windows(scene.width, scene.height)
    p32 = [p.detach().clone().requires_grad_() for p in params]
    img = _render(method, p32, scene, settings)
    loss = sum((img[y : y + h, x : x + w] * wts[y : y + h, x : x + w]).sum() for x, y, w, h in wins)
    loss.backward()
    img, wts = img.detach().cpu(), wts.cpu()
    s64 = scene.to(torch.float64)
    p64 = [p.detach().cpu().double().clone().requires_grad_() for p in params]
    diffs = []
    loss64 = 0.0
    for x, y, w, h in wins:
        ref, *_ = reference_rasterize(*p64, s64.camera, window=(x, y, w, h))
        diffs.append((img[y : y + h, x : x + w].detach().double() - ref.detach()).abs().reshape(-1))
        loss64 = loss64 + (ref * wts[y : y + h, x : x + w].double()).sum()
    loss64.backward()
    d = torch.cat(diffs)
    rel = max(
        ((a.grad.cpu().double() - b.grad).abs().max() / b.grad.abs().max().clamp_min(1e-30)).item()
        for a, b in zip(p32, p64)
        if b.grad is not None and b.grad.abs().max() > 0
    )
    return (d.max().item(), d.mean().item()), rel


def _row(r: dict, base: dict | None) -> str:
    """``base``: the row this one's speed-up is measured against (:data:`BASE`)."""
    ratio = f"{base['fb_s'] / r['fb_s']:.1f}x" if base and base is not r else ""
    return (
        f"| {r['scene']} | {r['n']:,} | {r['size']} | {r['method']} ({r['device']}) | "
        f"{r['fwd_s']:.3f} ({r['fwd_cpu_s']:.3f}) | "
        f"{r['fb_s']:.3f} ({r['fb_cpu_s']:.3f}) | {ratio} | {r['peak_mib']:.0f} | {r['pairs']:,} | "
        f"{r['pairs'] / r['fb_s'] / 1e6:.2f} | {r['img_max']:.1e} / {r['img_mean']:.1e} | {r['grad_rel']:.1e} | "
        f"{r['load']:.1f} |"
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["S", "M", "beer"],
                    help="S, M, L (500k Gaussians at 1024x1024), beer (skipped if absent), or a trained set: "
                         "PATH[@VIEW], a checkpoint file or run folder and one of its training views (default 0)")
    ap.add_argument("--methods", nargs="+", default=["cpp", "torch"], choices=list(METHODS),
                    help="cpp (compiled, CPU), torch (pure torch, CPU), baseline (plain compositor, CPU), "
                         "torch-cuda, gsplat (CUDA)")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per measurement (median)")
    ap.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0 = torch default)")
    ap.add_argument("--tile-size", type=int, default=16, help="RasterSettings.tile_size")
    ap.add_argument("--chunk-elements", type=int, default=RasterSettings.chunk_elements)
    ap.add_argument("--workers", type=int, default=0, help="RasterSettings.workers (0 = available CPUs)")
    ap.add_argument("--child", nargs=2, metavar=("SCENE", "METHOD"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    settings = RasterSettings(tile_size=a.tile_size, chunk_elements=a.chunk_elements, workers=a.workers)
    if a.child:
        print(json.dumps(run_child(a.child[0], a.child[1], a.repeats, settings)))
        return
    scenes = [s for s in a.scenes if s != "beer" or (SCENES_DIR / "beer").is_dir()]
    print(f"# torch {torch.__version__}, {os.cpu_count()} CPUs, threads={a.threads or 'default'}, "
          f"workers={a.workers or 'default'}, tile {a.tile_size}, chunk {a.chunk_elements}, "
          f"repeats {a.repeats}")  # fmt: skip
    print("| scene | N | W x H | method (device) | fwd s (cpu) | fwd+bwd s (cpu) | speed-up | peak MiB (RSS; GPU: "
          "allocated) | pairs | "
          "Mpairs/s | image err max / mean | grad rel err | load |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for scene in scenes:
        rows = {}
        for method in reversed(a.methods):  # baselines first, so the later rows can show their ratio
            print(f"# {scene} / {method} ...", file=sys.stderr, flush=True)
            cmd = [sys.executable, "-m", "exploregs_plugin.bench.components.rasterizer", "--child", scene, method,
                   "--repeats", str(a.repeats), "--threads", str(a.threads), "--tile-size", str(a.tile_size),
                   "--chunk-elements", str(a.chunk_elements), "--workers", str(a.workers)]  # fmt: skip
            res = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if res.returncode != 0:
                raise RuntimeError(f"bench child {scene}/{method} failed:\n{res.stderr}")
            rows[method] = json.loads(res.stdout.strip().splitlines()[-1])
        for method in a.methods:
            base = rows.get(BASE.get(method, ""))
            print(_row(rows[method], base), flush=True)


if __name__ == "__main__":
    main()
