"""The paper's ablations as runs, written in eg-train's own arguments.

Each experiment is a tuple of :class:`AblationRun` (name, method, eg-train arguments). eg-bench's
ablation presets make each run a row of their tables (``bench/presets.py``: a ``BenchEntry`` with
the same fields), and the bench runner turns it into a TrainerConfig with the same parser as
``eg-train`` (:func:`exploregs_plugin.bench.spec.build_config`), so there is one override language.
The research code states what to run; it does not import the harness that runs it.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations


@dataclass(frozen=True)
class AblationRun:
    """One run of an ablation: a registered method plus eg-train arguments."""

    name: str
    """Row name (``no-cov``, ``seed+depth``)."""
    method: str
    """Registered method, e.g. ``exploregs-branch-ablation``."""
    overrides: tuple[str, ...] = ()
    """eg-train arguments applied to the method's config."""
    description: str = ""
    """One line for the docs and results.md."""


DEPTH_WEIGHT = 0.1
"""Weight of the depth L1 term in the depth-supervision entries."""
MONOCULAR_DEPTH = ("--depth-supervision.noise-std", "0.05", "--depth-supervision.bias-amplitude", "0.1")
"""A monocular-like depth map: 5% per-pixel noise and a 10% smooth bias (relative to depth), the
settings of the method exploregs-mono-depth (given here too, so the entries say what they run)."""
PATHS = ("mean2d", "cov", "sh")


def _branch_ablation(description: str) -> tuple[AblationRun, ...]:
    """Every subset of switched-off position branches (8 entries, "all-branches" first)."""
    out = []
    for k in range(len(PATHS) + 1):
        for off in combinations(PATHS, k):
            name = "all-branches" if not off else "no-" + "-".join(off)
            out.append(AblationRun(name, "exploregs-branch-ablation", ("--model.detach-paths", *off), description))
    return tuple(out)


def _depth_supervision(description: str) -> tuple[AblationRun, ...]:
    out = []
    depth = ("--depth-loss-weight", repr(DEPTH_WEIGHT))
    for label in ("default", "seed", "seedsplit"):
        method = f"exploregs-{label}"
        out.append(AblationRun(label, method, (), description))
        out.append(AblationRun(f"{label}+depth", method, depth, description))
        # the degraded maps are a pipeline variant: that method, with this entry's strategy
        out.append(AblationRun(f"{label}+mono-depth", "exploregs-mono-depth",
                              ("--strategy", label) + depth + MONOCULAR_DEPTH, description))
    return tuple(out)


def _split_ablation(description: str) -> tuple[AblationRun, ...]:
    out = [AblationRun(f"split-n{n}", "exploregs-split", ("--strategy.splitting.n-split", str(n)), description)
           for n in (0, 5, 10, 20, 40, 80)]
    out += [AblationRun(f"default-grad{g:g}", "exploregs-default", ("--strategy.grow-grad2d", repr(g)), description)
            for g in (0.0001, 0.0002, 0.0004, 0.0008)]
    return tuple(out)


BRANCH_ABLATION = _branch_ablation("Default with every subset of the position-gradient branches switched off.")
"""Default ADC with every subset of {mean2d, cov, sh} detached (the paper's branch ablation)."""
DEPTH_SUPERVISION = _depth_supervision(
    "Default, Seed, Seed+Split without depth, with true depth, with noisy biased depth.")
"""Default / Seed / Seed+Split, each without depth, with ground-truth depth and with a
monocular-like depth (the paper's depth table)."""
SPLIT_ABLATION = _split_ablation("Random Splitting n_split sweep and Default grow_grad2d sweep (PSNR vs #Gaussians).")
"""Random Splitting's n_split and Default's gradient threshold: PSNR against Gaussian count."""

EXPERIMENTS: dict[str, tuple[AblationRun, ...]] = {
    "branch-ablation": BRANCH_ABLATION,
    "depth-supervision": DEPTH_SUPERVISION,
    "split-ablation": SPLIT_ABLATION,
}
"""Experiment name -> its entries."""
