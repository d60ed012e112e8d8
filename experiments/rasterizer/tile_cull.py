"""The compiled binning with and without the tiles that a Gaussian's ellipse misses, on a run's
checkpoint: tile-Gaussian pairs over the training views, CPU seconds of a forward and backward
render of every training view on one thread (the two binnings alternated, each repeated), the
ratio, and whether the images and every gradient are the same bits.

    python experiments/rasterizer/tile_cull.py RUN_DIR/checkpoints/step-0001000.pt --repeats 5
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time

import torch

from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.rasterizer.cpp_backend import CppBins
from exploregs_plugin.runs.load import load_run

rasterize_module = importlib.import_module("exploregs_plugin.rasterizer.rasterize")  # the package exports the function


def box_bins(*args) -> CppBins:
    """The binning of every tile of the support box (no conics: the culling's test is not made)."""
    return CppBins(*args[:7])


def render_all(pipeline, box: bool) -> tuple[float, int, list[torch.Tensor], dict[str, torch.Tensor]]:
    """CPU seconds, pairs, images and gradients of a forward and backward render of every training view."""
    rasterize_module.CppBins = box_bins if box else CppBins
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in pipeline.params.items()}
    pairs, images = 0, []
    start = time.process_time()
    for index in range(len(pipeline.datamanager.train_cameras)):
        camera, target, _ = pipeline.datamanager.train_item(index, pipeline.device)
        image, _, _, info = render_params(leaves, camera, 3, pipeline.background, pipeline.model.config.raster)
        ((image - target) ** 2).mean().backward()
        pairs += int(info["n_pairs"])
        images.append(image.detach())
    seconds = time.process_time() - start
    rasterize_module.CppBins = CppBins
    return seconds, pairs, images, {k: v.grad for k, v in leaves.items()}


def main(checkpoint: str, repeats: int) -> None:
    torch.set_num_threads(1)
    pipeline = load_run(checkpoint, "cpu").pipeline
    seconds = {True: [], False: []}
    for _ in range(repeats):
        for box in (True, False):
            s, pairs_, images, grads = render_all(pipeline, box)
            seconds[box].append(s)
            if box:
                box_pairs, box_images, box_grads = pairs_, images, grads
            else:
                pairs, same = pairs_, all(torch.equal(a, b) for a, b in zip(images, box_images)) and all(
                    torch.equal(grads[k], box_grads[k]) for k in grads)
    box_s, cull_s = statistics.median(seconds[True]), statistics.median(seconds[False])
    print(f"{pipeline.params['means'].shape[0]:,} Gaussians, {len(pipeline.datamanager.train_cameras)} training views")
    print(f"every tile of the box: {box_pairs:,} pairs, {box_s:.2f} s (median of {repeats})")
    print(f"the tiles the ellipse reaches: {pairs:,} pairs ({pairs / box_pairs:.1%}), {cull_s:.2f} s "
          f"({cull_s / box_s:.3f}x); images and gradients the same bits: {same}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", help="a checkpoint file (or a run folder: its latest)")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    main(args.checkpoint, args.repeats)
