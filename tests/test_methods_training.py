"""Each built-in method, trained briefly on the tiny scene, changes the Gaussian set as it claims.

With 30 steps and a 10-step interval the schedule densifies in steps (0, 15) every 10 steps, so ADC and
seeding fire at step 10 and random splitting on steps 1..14; MCMC refines until 25/30 of the
run, at steps 10 and 20.
"""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.method_configs import get_method
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.engine.trainer import Trainer

STEPS = 30
SHORT_SCHEDULE = ScheduleConfig(min_refine_every=10)  # 3DGS's 100-step interval shortened for 30 steps


def train_method(name: str, run_dir, **strategy_fields) -> tuple[Trainer, dict]:
    """Train ``name`` briefly; a dict value sets fields of the named operator
    (``seeding={"n_seed": 17}``), any other value a field of the strategy."""
    from dataclasses import replace

    config = get_method(name).config
    strategy = config.pipeline.strategy
    strategy = replace(strategy, **{k: replace(getattr(strategy, k), **v) if isinstance(v, dict) else v
                                    for k, v in strategy_fields.items()})
    config = replace(config, data="builtin:tiny", max_steps=STEPS, run_dir=run_dir, quiet=True,
                     tensorboard=False, eval_count=1, save_eval_images=False, checkpoint_every=1000,
                     schedule=SHORT_SCHEDULE, pipeline=replace(config.pipeline, strategy=strategy))
    trainer = config.setup()
    initial = trainer.pipeline.model.num_gaussians
    metrics = trainer.train()
    metrics["initial_gaussians"] = initial
    return trainer, metrics


def test_schedule_of_these_tests():
    trainer_schedule = SHORT_SCHEDULE.resolve(STEPS)
    assert (trainer_schedule.refine_start, trainer_schedule.refine_stop, trainer_schedule.refine_every) == (0, 15, 10)


def test_seeding_adds_exactly_n_seed_per_densification_step(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-seed", tmp_path, seeding={"n_seed": 17})
    counts = m["strategy_counts"]
    assert counts["seeded"] == 17  # one seeding step (10) in the window
    assert m["exploration"]["seeds_alive"] >= 0
    assert "random_split" not in counts or counts["random_split"] == 0
    assert m["num_gaussians"] == m["initial_gaussians"] + counts["cloned"] + counts["split"] + 17 - counts["pruned"]


def test_splitting_splits_n_split_every_step_of_the_window(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-split", tmp_path, splitting={"n_split": 5})
    counts = m["strategy_counts"]
    assert counts["random_split"] == 5 * 14  # steps 1..14
    assert counts.get("seeded", 0) == 0
    # a split replaces one Gaussian by two: +1 each, like ADC's split
    assert m["num_gaussians"] == (m["initial_gaussians"] + counts["cloned"] + counts["split"]
                                  + counts["random_split"] - counts["pruned"])


def test_seedsplit_does_both(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-seedsplit", tmp_path, seeding={"n_seed": 9}, splitting={"n_split": 3})
    counts = m["strategy_counts"]
    assert counts["seeded"] == 9 and counts["random_split"] == 3 * 14
    assert m["num_gaussians"] == (m["initial_gaussians"] + counts["cloned"] + counts["split"]
                                  + counts["random_split"] + counts["seeded"] - counts["pruned"])


def test_ray_perturbation_moves_gaussians_every_step(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-ray", tmp_path)
    assert m["strategy_counts"]["perturbed"] > 0
    assert m["strategy_counts"]["cloned"] + m["strategy_counts"]["split"] > 0


@pytest.mark.parametrize("name", ["exploregs-mcmc", "exploregs-mcmc-ray"])
def test_mcmc_grows_five_percent_and_never_deletes(tmp_path, tiny_scene_dir, name):
    trainer, m = train_method(name, tmp_path, cap_max=10_000)
    n0 = m["initial_gaussians"]
    counts = m["strategy_counts"]
    grown = int(1.05 * int(1.05 * n0))  # MCMC refines until 25/30 of the run: steps 10 and 20
    assert counts["added"] == grown - n0
    assert m["num_gaussians"] == grown  # relocation reuses dead Gaussians, never deletes
    assert counts["perturbed"] > 0
    capped_trainer, capped = train_method(name, tmp_path / "capped", cap_max=n0 + 3)
    assert capped["num_gaussians"] == n0 + 3
    assert torch.isfinite(capped_trainer.pipeline.params["means"]).all()


def test_guided_seeds_land_on_training_rays_and_are_seen(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-guided", tmp_path, seeding={"n_seed": 12})
    counts = m["strategy_counts"]
    assert counts["seeded"] == 12
    assert m["num_gaussians"] == m["initial_gaussians"] + counts["cloned"] + counts["split"] + 12 - counts["pruned"]
    views = trainer.pipeline.strategy_state["views"]
    assert len(views) == min(len(trainer.pipeline.datamanager.train_cameras), 14)  # one map per view trained
    assert m["exploration"]["seeds_unseen"] == 0  # every guided seed lies in a training view


def test_occlusion_aware_splitting_spends_the_split_budget(tmp_path, tiny_scene_dir):
    trainer, m = train_method("exploregs-occlusion", tmp_path, splitting={"n_split": 5})
    counts = m["strategy_counts"]
    assert counts["random_split"] == 5 * 14
    stats = trainer.pipeline.strategy_state["stats"]
    assert {"vis_weight", "vis_alpha", "occ_error"} <= set(stats)
    assert bool((stats["vis_weight"] <= stats["vis_alpha"] * (1 + 1e-5) + 1e-7).all())  # T <= 1
    trainer, m = train_method("exploregs-guided-occlusion", tmp_path / "both", seeding={"n_seed": 7},
                               splitting={"n_split": 2})
    assert m["strategy_counts"]["seeded"] == 7 and m["strategy_counts"]["random_split"] == 2 * 14


def test_mcmc_explore_with_the_automatic_cap_grows_then_stops(tmp_path, tiny_scene_dir):
    """400 steps on the tiny scene, refinement every 25 steps until step 333: the count grows 5%
    per refinement while the loss falls by 3% per window, then stays at the cap the rule chose;
    explored seeds are in the set and the fit is sound. Resumed from the middle of a loss window
    (step 160), the run ends with the same bits and the same cap."""
    import math
    import shutil
    from dataclasses import replace

    from exploregs_plugin.callbacks import TrainingCallback

    class Counts(TrainingCallback):
        def __init__(self):
            self.n = {}

        def after_step(self, trainer, step, stats):
            self.n[step] = trainer.pipeline.model.num_gaussians

    config = get_method("exploregs-mcmc-explore").config
    strategy = replace(config.pipeline.strategy, cap_max="auto", auto_min_drop=0.03, explore_share=0.1,
                       explore_split=1.0, explore_box=1.0, explore_guided=1.0)
    config = replace(config, data="builtin:tiny", max_steps=400, run_dir=tmp_path / "run", quiet=True,
                     tensorboard=False, eval_count=2, save_eval_images=False, checkpoint_every=160,
                     schedule=ScheduleConfig(min_refine_every=25), pipeline=replace(config.pipeline, strategy=strategy))
    counts = Counts()
    trainer = config.setup(callbacks=[counts])
    n0 = trainer.pipeline.model.num_gaussians
    m = trainer.train()
    cap = m["exploration"]["auto_cap"]
    assert n0 < cap == m["num_gaussians"]
    assert counts.n[26] == int(1.05 * n0)  # the first refinement (step 25) grows
    stopped = min(step for step, n in counts.n.items() if n == cap)
    assert stopped < 300 and all(counts.n[s] == cap for s in range(stopped, 401))  # then it never grows again
    assert m["strategy_counts"]["explored"] > 0 and m["exploration"]["seeds_alive"] > 0
    assert math.isfinite(m["psnr"]) and m["psnr"] > 16.0
    resumed_dir = tmp_path / "resumed"
    shutil.copytree(tmp_path / "run", resumed_dir)
    for late in sorted((resumed_dir / "checkpoints").glob("*.pt"))[1:]:
        late.unlink()  # keep step-0000160.pt
    assert sorted(p.name for p in (resumed_dir / "checkpoints").glob("*.pt")) == ["step-0000160.pt"]
    resumed = Trainer.from_run(resumed_dir, max_steps=None, quiet=True)
    assert stopped > 160 and resumed.pipeline.strategy_state["auto_steps"] > 0  # inside a window, before the stop
    resumed.train()
    assert resumed.pipeline.strategy_state["auto_cap"] == cap
    for name, p in trainer.pipeline.params.items():
        assert torch.equal(p, resumed.pipeline.params[name]), name
