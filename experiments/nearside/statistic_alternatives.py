"""Which Gaussians other densification statistics would grow, at Default's growth rate.

For one checkpoint, over all training views: Default's statistic (mean NDC screen-space gradient
over the views that draw a Gaussian) and its share above grow_grad2d = 2e-4, per class of
Gaussian (other, occluded and seen, occluded and hidden, off-surface); then, for each other
statistic, the share of each class among the Gaussians it would grow if it grew as many as
Default's threshold does: the largest view's gradient (grad-max), the summed gradient per unit
of light (sum |g| / sum T-bar, per-light), the mean and the largest error mass e(mu) sum(alpha T)
(err-mass, err-mass-max) and the geometric mean of error mass and statistic.

    python experiments/nearside/statistic_alternatives.py "$OUT/runs/default/seed0/checkpoints/step-0000300.pt"
"""

import argparse
from dataclasses import replace

import torch

from exploregs_plugin.analysis import nearside as ns
from exploregs_plugin.analysis import nearside_report as nr
from exploregs_plugin.analysis.sampling import pipeline_view
from exploregs_plugin.runs import load_run

THRESHOLD = 2e-4  # grow_grad2d
HIDDEN = 100  # class id given here to occluded Gaussians that are hidden

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("checkpoint", help="checkpoint file (or run folder: its latest checkpoint)")
args = parser.parse_args()

run = load_run(args.checkpoint, "cpu")
p = run.pipeline
train = nr.scene_views(p.datamanager, "train")
means = p.params["means"].detach().double()
reg = ns.gaussian_regions(means, train.viewmats, train.Ks, train.depths, train.labels, 4)
region = reg.region.clone()
region[(region == 2) & reg.hidden()] = HIDDEN

G, W, E, Vs, A = [], [], [], [], []  # per view: gradient, sum(alpha T), error at centre, drawn, sum(alpha)
for cam, img in zip(train.cameras, train.images):
    view = pipeline_view(p, cam, img, run.step)
    view = replace(view, settings=replace(view.settings, visibility_stats=True))
    _, image, _, info = view.render()
    with torch.enable_grad():
        (g,) = torch.autograd.grad(view.loss_fn(image, img), info["means2d"])
    err = (image.detach() - img).abs().mean(-1)
    xy = info["means2d"].detach()
    x = xy[:, 0].floor().clamp(0, cam.width - 1).long()
    y = xy[:, 1].floor().clamp(0, cam.height - 1).long()
    E.append(err[y, x].double())
    W.append(info["visibility"][:, 0].double())
    A.append(info["visibility"][:, 1].double())
    G.append(ns.ndc_gradient_norm(g.double(), cam.width, cam.height))
    Vs.append((info["radii"] > 0).all(-1))
G, W, E, Vs, A = (torch.stack(t) for t in (G, W, E, Vs, A))
G = torch.where(Vs, G, torch.zeros_like(G))
count = Vs.sum(0).clamp_min(1)
mean = G.sum(0) / count  # Default's statistic
stats = {
    "err-mass": (E * W * Vs).sum(0) / count,
    "err-mass-max": (E * W * Vs).max(0).values,
    "grad-max": G.max(0).values,
    "per-light": G.sum(0) / (torch.where(A > 0, W / A.clamp_min(1e-12), torch.zeros_like(W)) * Vs).sum(0).clamp_min(1.0),
}
stats["err-mass*grad"] = stats["err-mass"].sqrt() * mean.sqrt()
rate = float((mean > THRESHOLD).double().mean())


def share_grown(x: torch.Tensor, m: torch.Tensor) -> float:
    """Share of the rows ``m`` among the top ``rate`` of ``x``."""
    t = torch.quantile(x.float(), 1 - rate).item()
    return round(float((x[m] > t).double().mean()), 3)


print(f"step {run.step}: Default grows {rate:.3f} of the Gaussians (statistic above {THRESHOLD:g})")
for cid, name in ((0, "other"), (2, "occluded"), (HIDDEN, "hidden"), (-1, "off-surface")):
    m = region == cid
    alt = " ".join(f"{k} {share_grown(v, m)}" for k, v in stats.items())
    print(f"{name:14s} n={int(m.sum()):5d} default {float((mean[m] > THRESHOLD).double().mean()):.3f} | at Default's rate: {alt}")
