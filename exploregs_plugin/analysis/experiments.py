"""The paper's ablations as experiment specs for the benchmark runner (plain data).

An experiment is ``{entry name: overrides}``; ``overrides`` maps dotted TrainerConfig field paths
to values, plus the key ``"method"`` naming the base method (a built-in or plugin method of
``eg-train``). :func:`entry_config` turns one entry into a complete TrainerConfig.
"""

from __future__ import annotations

import dataclasses
from itertools import combinations
from typing import Any

METHOD_KEY = "method"
DEPTH_WEIGHT = 0.1
"""Weight of the depth L1 term in the depth-supervision entries."""
MONOCULAR_DEPTH = {"pipeline.depth_supervision.noise_std": 0.05, "pipeline.depth_supervision.bias_amplitude": 0.1}
"""A monocular-like depth map: 5% per-pixel noise and a 10% smooth bias (relative to depth)."""
PATHS = ("mean2d", "cov", "sh")


def _branch_ablation() -> dict[str, dict[str, Any]]:
    """Every subset of switched-off position branches (8 entries, "all-branches" first)."""
    out: dict[str, dict[str, Any]] = {}
    for k in range(len(PATHS) + 1):
        for off in combinations(PATHS, k):
            name = "all-branches" if not off else "no-" + "-".join(off)
            out[name] = {METHOD_KEY: "exploregs-default", "pipeline.model.detach_paths": off}
    return out


def _depth_supervision() -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for label, method in (("default", "exploregs-default"), ("seed", "exploregs-seed"),
                          ("seedsplit", "exploregs-seedsplit")):  # fmt: skip
        out[label] = {METHOD_KEY: method}
        out[f"{label}+depth"] = {METHOD_KEY: method, "pipeline.depth_loss_weight": DEPTH_WEIGHT}
        out[f"{label}+mono-depth"] = {METHOD_KEY: method, "pipeline.depth_loss_weight": DEPTH_WEIGHT,
                                      **MONOCULAR_DEPTH}  # fmt: skip
    return out


def _split_ablation() -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for n in (0, 5, 10, 20, 40, 80):
        out[f"split-n{n}"] = {METHOD_KEY: "exploregs-split", "pipeline.strategy.n_split": n}
    for g in (0.0001, 0.0002, 0.0004, 0.0008):
        out[f"default-grad{g:g}"] = {METHOD_KEY: "exploregs-default", "pipeline.strategy.grow_grad2d": g}
    return out


BRANCH_ABLATION = _branch_ablation()
"""Default ADC with every subset of {mean2d, cov, sh} detached (the paper's branch ablation)."""
DEPTH_SUPERVISION = _depth_supervision()
"""Default / Seed / Seed+Split, each without depth, with ground-truth depth and with a
monocular-like depth (the paper's depth table; the mono entries need
``PipelineConfig.depth_supervision``)."""
SPLIT_ABLATION = _split_ablation()
"""Random Splitting's n_split and Default's gradient threshold: PSNR against Gaussian count."""

EXPERIMENTS: dict[str, tuple[str, dict[str, dict[str, Any]]]] = {
    "branch-ablation": ("Default with every subset of the position-gradient branches switched off.", BRANCH_ABLATION),
    "depth-supervision": ("Default, Seed, Seed+Split without depth, with true depth, with noisy biased depth.",
                          DEPTH_SUPERVISION),
    "split-ablation": ("Random Splitting n_split sweep and Default grow_grad2d sweep (PSNR vs #Gaussians).",
                       SPLIT_ABLATION),
}
"""Experiment name -> (one-line description, entries)."""


def apply_overrides(config: Any, overrides: dict[str, Any]) -> Any:
    """A copy of the dataclass ``config`` with dotted fields replaced, e.g.
    ``{"pipeline.model.detach_paths": ("cov",)}``. Unknown fields raise ValueError."""
    for dotted, value in overrides.items():
        config = _replace_path(config, dotted.split("."), value, dotted)
    return config


def _replace_path(obj: Any, parts: list[str], value: Any, dotted: str) -> Any:
    if not dataclasses.is_dataclass(obj):
        raise ValueError(f"override {dotted!r}: {type(obj).__name__} is not a config with fields")
    names = {f.name for f in dataclasses.fields(obj)}
    if parts[0] not in names:
        raise ValueError(f"override {dotted!r}: {type(obj).__name__} has no field {parts[0]!r} "
                         f"(fields: {', '.join(sorted(names))})")
    if len(parts) == 1:
        return dataclasses.replace(obj, **{parts[0]: value})
    child = _replace_path(getattr(obj, parts[0]), parts[1:], value, dotted)
    return dataclasses.replace(obj, **{parts[0]: child})


def cli_overrides(entry: dict[str, Any]) -> tuple[str, ...]:
    """The entry's overrides as eg-train arguments (what the eg-bench runner parses), e.g.
    ``{"pipeline.model.detach_paths": ("cov", "sh")}`` -> ``("--model.detach-paths", "cov", "sh")``.

    The pipeline's fields sit at the top level of the eg-train CLI (``--model.*``,
    ``--strategy.*``, ``--depth-loss-weight``), so a leading ``pipeline.`` is dropped.
    """
    args: list[str] = []
    for dotted, value in entry.items():
        if dotted == METHOD_KEY:
            continue
        parts = dotted.split(".")
        if parts[0] == "pipeline":
            parts = parts[1:]
        args.append("--" + ".".join(p.replace("_", "-") for p in parts))
        if isinstance(value, (tuple, list)):
            args.extend(str(v) for v in value)  # an empty tuple: the flag alone
        else:
            args.append(repr(value) if isinstance(value, float) else str(value))
    return tuple(args)


def entry_config(entry: dict[str, Any], **trainer_fields: Any) -> Any:
    """The complete TrainerConfig of one entry: its method's config, then ``trainer_fields``
    (e.g. data=, max_steps=), then the entry's overrides."""
    from exploregs_plugin.method_configs import get_method

    if METHOD_KEY not in entry:
        raise ValueError(f"experiment entry {entry!r} names no {METHOD_KEY!r}")
    config = dataclasses.replace(get_method(entry[METHOD_KEY]).config, **trainer_fields)
    return apply_overrides(config, {k: v for k, v in entry.items() if k != METHOD_KEY})
