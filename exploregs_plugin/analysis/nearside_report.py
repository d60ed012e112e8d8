"""The near-side diagnostics of a run: the scene's views with depth and region labels, the
occluded region's error split by how many training views see it, and the occluded Gaussians'
transmittance and densification statistic (the maths is in :mod:`.nearside`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from exploregs_plugin.cameras import Camera
from exploregs_plugin.data.parsed import REGION_LABELS

from . import nearside as ns
from .blending import composited_pairs, image_gradient
from .sampling import pipeline_view

if TYPE_CHECKING:
    from exploregs_plugin.engine.pipeline import Pipeline

SEED_FLAG = "seed"
"""Seeding's per-Gaussian flag in the strategy statistics (1 for seeds and their descendants)."""
HIDDEN = 100
"""Class id of occluded-region Gaussians that are hidden behind a surface in most views they project
into (the near-side trap proper); the rest of the occluded region is merely outside most frusta."""
VISIBILITY_EDGES = (0, 1, 3, 5)
"""Bins of the number of training views that see a pixel: none, 1-2, 3-4, 5 or more."""


@dataclass
class SceneViews:
    """One split's views: cameras, images [V, H, W, 3], z-depths [V, H, W] and region labels
    [V, H, W] (REGION_LABELS values). Depths and poses are float64: the sky lies 1e3 times
    farther than the cabinet, and the 2% depth test must hold at both ends."""

    cameras: list[Camera]
    images: Tensor
    depths: Tensor
    labels: Tensor

    @property
    def viewmats(self) -> Tensor:
        return torch.stack([c.viewmat for c in self.cameras]).double()

    @property
    def Ks(self) -> Tensor:
        return torch.stack([c.K for c in self.cameras]).double()


def scene_views(datamanager: Any, split: str) -> SceneViews:
    """The views of ``split`` ('train' or 'test'); ValueError when the dataset has no depth or masks."""
    count = len(datamanager.train_cameras if split == "train" else datamanager.test_cameras)
    item = datamanager.train_item if split == "train" else datamanager.test_item
    cameras, images, depths, labels = [], [], [], []
    for i in range(count):
        camera, image, extras = item(i)
        if "depth" not in extras or "masks" not in extras:
            raise ValueError("the near-side diagnostics need ground-truth depth and region masks "
                             "(the built-in scenes have both)")
        label = torch.zeros(camera.height, camera.width, dtype=torch.long)
        for name, mask in extras["masks"].items():
            label[mask] = REGION_LABELS[name]
        cameras.append(camera)
        images.append(image)
        depths.append(extras["depth"][..., 0].double())
        labels.append(label)
    return SceneViews(cameras, torch.stack(images), torch.stack(depths), torch.stack(labels))


def view_counts(views: SceneViews, train: SceneViews, tol: float) -> tuple[Tensor, Tensor]:
    """([V, H, W], [V, H, W]): at each pixel of ``views``, how many training views see its surface
    point, and how many have it in the image but behind another surface."""
    seen, hidden = [], []
    for camera, depth in zip(views.cameras, views.depths):
        points = ns.unproject(depth, camera.K.double(), camera.viewmat.double()).reshape(-1, 3)
        seen.append(ns.seen_by(points, train.viewmats, train.Ks, train.depths, tol).sum(0).reshape(depth.shape))
        hidden.append(ns.hidden_from(points, train.viewmats, train.Ks, train.depths, tol).sum(0).reshape(depth.shape))
    return torch.stack(seen), torch.stack(hidden)


def occluded_parts(labels: Tensor, seen: Tensor, hidden: Tensor) -> dict[str, Tensor]:
    """The occluded region [V, H, W] and its two parts: 'occluded-hidden' (behind a surface in more
    training views than see it: the near-side trap) and 'occluded-out-of-view' (seen by few views
    because few views point there)."""
    occ = labels == REGION_LABELS["occluded"]
    return {"occluded": occ, "occluded-hidden": occ & (hidden > seen), "occluded-out-of-view": occ & (hidden <= seen)}


def squared_errors(pipeline: Pipeline, views: SceneViews) -> Tensor:
    """[V, H, W] squared error (mean over channels) of the model's renders at its full SH degree."""
    model, background = pipeline.model, pipeline.datamanager.background
    out = []
    with torch.no_grad():
        for camera, target in zip(views.cameras, views.images):
            image, _, _, _ = model.render(camera, model.config.sh_degree, background)
            out.append(((image.clamp(0.0, 1.0) - target) ** 2).mean(-1).double())
    return torch.stack(out)


def pixel_rows(pipeline: Pipeline, split: str, views: SceneViews, train: SceneViews, tol: float
               ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(error rows, reference rows) of the occluded region and its parts, pooled over the views.

    Error rows: :func:`nearside.error_by_visibility` per part (and per view for the whole
    region). Reference rows: per part, pixels, the model's PSNR and :func:`nearside.reference_psnrs`."""
    seen, hidden = view_counts(views, train, tol)
    sq = squared_errors(pipeline, views)
    rows, refs = [], []
    for part, mask in occluded_parts(views.labels, seen, hidden).items():
        if not bool(mask.any()):
            continue
        rows += [{"split": split, "part": part, "view": "all", **r}
                 for r in ns.error_by_visibility(sq[mask], seen[mask], VISIBILITY_EDGES)]
        refs.append({"split": split, "part": part, "pixels": int(mask.sum()),
                     "model": ns.psnr_of(float(sq[mask].sum()), int(mask.sum())),
                     **ns.reference_psnrs(views.images, mask)})
        if part == "occluded":
            for k, camera in enumerate(views.cameras):
                m = mask[k]
                if bool(m.any()):
                    rows += [{"split": split, "part": part, "view": camera.name, **r}
                             for r in ns.error_by_visibility(sq[k][m], seen[k][m], VISIBILITY_EDGES)]
    return rows, refs


def gaussian_rows(pipeline: Pipeline, step: int, train: SceneViews, threshold: float, tol: float
                  ) -> list[dict[str, Any]]:
    """Per region class of the Gaussians at ``step``: count, transmittance, statistic against
    ``threshold`` (plain and compensated), shares; with seeding, how many are seeds or descendants."""
    params = pipeline.params
    region, names, regions = gaussian_classes(pipeline, train, tol)
    stats = [ns.view_stats(pipeline_view(pipeline, c, img, step)) for c, img in zip(train.cameras, train.images)]
    acc = ns.accumulate(stats)
    rows = ns.class_summary(region, acc, threshold, params["scales"], names)
    flag = pipeline.strategy_state.get("stats", {}).get(SEED_FLAG)
    for row, value in zip(rows, names):
        m = region == value
        row["step"] = step
        row["median_front_views"] = float(regions.front_views[m].double().median()) if bool(m.any()) else math.nan
        opacity = torch.sigmoid(params["opacities"].detach()[m])
        row["mean_opacity"] = float(opacity.mean()) if bool(m.any()) else math.nan
        row["seed_descendants"] = int((flag[m] > 0).sum()) if flag is not None and flag.shape[0] == m.shape[0] else 0
    return [{"step": r.pop("step"), **r} for r in rows]


def gaussian_classes(pipeline: Pipeline, train: SceneViews, tol: float
                     ) -> tuple[Tensor, dict[int, str], ns.GaussianRegions]:
    """Class id per Gaussian [N] (REGION_LABELS, HIDDEN for the occluded region's hidden part,
    NO_REGION off every surface), the class names and the regions they come from."""
    regions = ns.gaussian_regions(pipeline.params["means"].detach().double(), train.viewmats, train.Ks,
                                  train.depths, train.labels, n_labels=max(REGION_LABELS.values()) + 1, tol=tol)
    region = regions.region.clone()
    region[(region == REGION_LABELS["occluded"]) & regions.hidden()] = HIDDEN
    names = {value: name for name, value in REGION_LABELS.items() if name != "moving"}
    names[HIDDEN] = "occluded-hidden"
    names[ns.NO_REGION] = "off-surface"
    return region, names, regions


def cancellation_rows(pipeline: Pipeline, step: int, train: SceneViews, views: list[int], tol: float
                      ) -> list[dict[str, Any]]:
    """Per training view of ``views`` and Gaussian class: medians of the net and absolute
    screen-space gradient, of their ratio and of the pixels covered (:func:`nearside.gradient_cancellation`)."""
    region, names, _ = gaussian_classes(pipeline, train, tol)
    n = region.shape[0]
    rows = []
    for index in views:
        camera, target = train.cameras[index], train.images[index]
        view = pipeline_view(pipeline, camera, target, step)
        pairs = composited_pairs(pipeline.params, camera, view.settings, sh_degree=view.sh_degree,
                                 background=view.background, image_grad=image_gradient(view))
        c = ns.gradient_cancellation(pairs["ids"], pairs["grad_px"], n, camera.width, camera.height)
        for value, name in names.items():
            m = (region == value) & (c["pixels"] > 0) & ~torch.isnan(c["ratio"])
            k = int(m.sum())
            rows.append({"step": step, "view": camera.name, "region": name, "gaussians": k,
                         "median_pixels": float(c["pixels"][m].double().median()) if k else math.nan,
                         "median_net": float(c["net"][m].median()) if k else math.nan,
                         "median_absolute": float(c["absolute"][m].median()) if k else math.nan,
                         "median_ratio": float(c["ratio"][m].median()) if k else math.nan})
    return rows


def plot_nearside(pixels: list[dict[str, Any]], gaussians: list[dict[str, Any]], path: Any, title: str = "") -> Any:
    """Left: share of the occluded region's pixels and squared error by the number of training
    views that see them (test and train, pooled). Right: per checkpoint, the count of the
    Gaussians hidden in the occluded region and the share of them above the threshold, plain and
    with T undone."""
    from .plots import plt, _save  # matplotlib only when a figure is drawn

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    pooled = [r for r in pixels if r["view"] == "all" and r["part"] == "occluded"]
    labels = sorted({(r["views_lo"], r["views_hi"]) for r in pooled})
    names = [f"{lo}+" if hi < 0 else (str(lo) if hi - 1 == lo else f"{lo}-{hi - 1}") for lo, hi in labels]
    for k, (split, key, hatch) in enumerate((("test", "share_pixels", ""), ("test", "share_sq_error", "//"),
                                             ("train", "share_pixels", ".."), ("train", "share_sq_error", "xx"))):
        values = [next((r[key] for r in pooled if r["split"] == split and (r["views_lo"], r["views_hi"]) == b), 0.0)
                  for b in labels]
        left.bar([i + 0.2 * k - 0.3 for i in range(len(labels))], values, width=0.2, hatch=hatch,
                 label=f"{split}: {key.replace('share_', 'share of ')}")
    left.set_xticks(range(len(labels)), names)
    left.set_xlabel("training views that see the pixel")
    left.set_title("occluded region")
    left.legend(fontsize=7)
    occ = [r for r in gaussians if r["region"] == "occluded-hidden"]
    steps = [r["step"] for r in occ]
    if not occ:
        right.text(0.5, 0.5, "no Gaussian statistics", ha="center", va="center", transform=right.transAxes)
    right.plot(steps, [r["frac_above"] for r in occ], "o-", label="share above grow_grad2d")
    right.plot(steps, [r["frac_above_compensated"] for r in occ], "s--", label="same, T undone")
    other = [r for r in gaussians if r["region"] == "other"]
    right.plot([r["step"] for r in other], [r["frac_above"] for r in other], "^:", label="other region, above")
    right.set_xlabel("step")
    right.set_ylim(0, 1)
    twin = right.twinx()
    twin.plot(steps, [r["gaussians"] for r in occ], "k-", alpha=0.4, label="hidden occluded Gaussians")
    twin.set_ylabel("Gaussians hidden in the occluded region")
    right.legend(fontsize=7, loc="upper left")
    right.set_title("occluded region, hidden part: Gaussians")
    fig.suptitle(title, fontsize=9)
    return _save(fig, path)
