"""A training run's evaluation on the test views, split across the ranks of a data-parallel run
(one process: all of them), with the panels tensorboard shows."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from exploregs_plugin.runtime.distributed import World
from exploregs_plugin.evaluation.metrics import evaluate_views, evaluation_panel, summarize_evaluation
from exploregs_plugin.engine.pipeline import Pipeline

EVAL_PANELS = 2  # test views shown in tensorboard at each evaluation (render | truth | error)


def evaluate_on_ranks(pipeline: Pipeline, world: World, save_dir: Path | None = None
                      ) -> tuple[dict[str, Any], list[tuple[str, torch.Tensor]]]:
    """(metrics, panels): each rank scores every world-size-th test view and every rank gets the
    summary of all of them; the panels (name, render | truth | error) of the first EVAL_PANELS
    views are kept as they are rendered, so tensorboard's images cost no second render."""
    panels: list[tuple[int, str, torch.Tensor]] = []

    def keep_panel(index: int, name: str, image: torch.Tensor, target: torch.Tensor) -> None:
        if index < EVAL_PANELS:
            panels.append((index, name or f"view{index}", evaluation_panel(image, target)))

    dm = pipeline.datamanager
    views = range(world.rank, len(dm.test_cameras), world.size)
    part = evaluate_views(pipeline.model, dm, views, save_dir=save_dir, on_image=keep_panel)
    parts = world.all_gather_object((part, panels))
    metrics = summarize_evaluation([p for p, _ in parts], pipeline.model.num_gaussians)
    shown = sorted(panel for _, rank_panels in parts for panel in rank_panels)
    return metrics, [(name, image) for _, name, image in shown]
