"""The count decided on held-out views (MCMC's ``cap_max 'validated'``): the rule's pure parts (held-out
views, candidate counts, the pick by paired deficit), the strategy's ceiling and trial, the trial's
isolation, and a run on the tiny scene (views held out until the decision, deterministic, resumed
with the same decision)."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch

from exploregs_plugin.engine import count_trial
from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.io.config_files import config_from_dict
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.schedule import ScheduleConfig
from exploregs_plugin.strategies import DefaultStrategy, MCMCStrategy, StrategyError, row_ops
from exploregs_plugin.strategies.count_rule import (candidate_counts, held_out_count, held_out_indices, paired_deficit,
                                                    pick_count)
from exploregs_plugin.strategies.synthetic import adam_steps, make_gaussians, make_optimizers, synthetic_views
from exploregs_plugin.engine.trainer import Trainer

WINDOW = dict(refine_start_iter=2, refine_stop_iter=200, refine_every=10, reset_every=100, count_trial_steps=5)


# torch on one thread for these tests (conftest's one_thread): on sets of a few hundred Gaussians a
# second thread only waits for work, and the thread count changes no bit
# (test_the_decision_and_the_run_are_the_same_bits_on_one_and_two_threads). A run that sets its own
# count (num_threads, as every run of _config does) keeps it.
pytestmark = pytest.mark.usefixtures("one_thread")


# ------------------------------------------------------------------------------ the rule
def test_held_out_views_are_spread_over_the_capture_and_few():
    assert [held_out_count(n) for n in (3, 7, 8, 24, 36, 71, 96, 400)] == [0, 0, 2, 2, 3, 5, 8, 8]
    assert held_out_indices(7) == []
    assert held_out_indices(8) == [2, 6]
    assert held_out_indices(62) == [6, 18, 31, 43, 55]
    for n in (8, 13, 62, 250):
        idx = held_out_indices(n)
        gaps = [b - a for a, b in zip(idx, idx[1:])]
        assert len(set(idx)) == len(idx) and 0 <= idx[0] and idx[-1] < n
        assert max(gaps) - min(gaps) <= 1  # evenly spread


def test_candidates_are_the_cuts_of_the_count_largest_first_without_repeats():
    assert candidate_counts(1000, (1.0, 0.7, 0.5, 0.35, 0.25)) == [1000, 700, 500, 350, 250]
    assert candidate_counts(1000, (0.5, 0.25)) == [1000, 500, 250]  # the whole set is always tried
    assert candidate_counts(3, (1.0, 0.7, 0.5, 0.35, 0.25)) == [3, 2, 1]  # floors, at least 1, no repeats


def test_the_paired_deficit_is_the_mean_per_view_loss_plus_its_standard_error():
    best = [25.0, 26.0, 24.0, 27.0]
    assert paired_deficit(best, best) == 0.0
    assert paired_deficit(best, [p - 0.2 for p in best]) == pytest.approx(0.2)  # no spread: no error
    # deficits 0.0, 0.4, 0.0, 0.4: mean 0.2, sd 0.2309, se 0.1155
    assert paired_deficit(best, [25.0, 25.6, 24.0, 26.6]) == pytest.approx(0.2 + 0.4 / math.sqrt(12.0))
    assert paired_deficit([20.0], [19.5]) == pytest.approx(0.5)  # one view: the deficit alone
    assert math.isnan(paired_deficit(best, [25.0, float("nan"), 24.0, 27.0]))
    with pytest.raises(ValueError, match="same views"):
        paired_deficit(best, best[:3])


def test_the_pick_is_the_fewest_gaussians_that_the_views_agree_cost_little():
    counts = [1000, 700, 500, 250]
    whole = [25.0, 26.0, 24.0, 27.0]
    steady = [p - 0.05 for p in whole]  # 0.05 dB lower on every view
    split = [25.0, 25.8, 24.0, 26.8]  # mean 0.1 lower, but only on two views: 0.1 + se 0.058
    poor = [p - 0.5 for p in whole]
    assert counts[pick_count(counts, [whole, steady, steady, poor], 0.1)] == 500
    assert counts[pick_count(counts, [whole, steady, split, poor], 0.1)] == 700  # se keeps 500 out
    assert counts[pick_count(counts, [whole, poor, poor, poor], 0.1)] == 1000
    assert counts[pick_count(counts, [whole, poor, poor, poor], 0.6)] == 250
    # the best need not be the largest; a non-finite candidate is never kept; none finite: the largest
    assert counts[pick_count(counts, [poor, whole, poor, poor], 0.1)] == 700
    assert counts[pick_count(counts, [whole, whole, [float("nan")] * 4, whole], 0.1)] == 250
    assert counts[pick_count(counts, [whole, whole, whole, [float("inf")] * 4], 0.1)] == 500
    assert counts[pick_count(counts, [[float("nan")] * 4] * 4, 0.1)] == 1000
    with pytest.raises(ValueError, match="one score list per candidate"):
        pick_count(counts, [whole], 0.1)


# ------------------------------------------------------------------------------ the strategy
def _set(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    params = make_gaussians(n, g)
    with torch.no_grad():
        params["opacities"].copy_(torch.logit(0.2 + 0.7 * torch.rand(n, generator=g)))
    optimizers = make_optimizers(params)
    adam_steps(params, optimizers, g)
    return params, optimizers


def _run(strategy, steps=300, decide=None):
    """``steps`` synthetic steps of ``strategy`` from a set of 100. At a trial the counts are
    handed to ``decide(counts)``, which returns the held-out PSNRs per candidate, and the set is
    cut to the kept count (as the pipeline does). Returns (count after each step, the trials' steps
    and counts, whether views were held out before each step, the state)."""
    params, optimizers = _set(100)
    state = strategy.initialize_state()
    counts, trials, held = {}, [], {}
    for step in range(3, steps):
        held[step] = strategy.holds_out_views(state, step)
        views = synthetic_views(torch.zeros(params["means"].shape[0], 2),
                                torch.ones(params["means"].shape[0], dtype=torch.bool), 32, 32,
                                torch.tensor([0.0, 0.0, -3.0]))
        strategy.step_post_backward(params, optimizers, state, step, views, lr=1.6e-4,
                                    generator=torch.Generator().manual_seed(step))
        trial = strategy.count_trial_due(state, step, params["means"].shape[0])
        if trial is not None:
            trials.append((step, trial))
            kept = strategy.decide_count(state, step, trial.counts, decide(trial.counts))
            keep = torch.zeros(params["means"].shape[0], dtype=torch.bool)
            keep[:kept] = True
            row_ops.remove(params, optimizers, state["stats"], ~keep)
        counts[step] = params["means"].shape[0]
    return counts, trials, held, state


def test_the_set_grows_to_the_ceiling_and_the_trial_comes_at_the_last_refinement():
    """Refinements every 10 steps from step 10 to 190; 5% growth from 100 to the ceiling, 2 x 100.
    The views are held out until the trial at step 190, the last refinement. The held-out PSNR
    (3 views) rises with the count up to 130 Gaussians and is flat beyond, so the pick is 140
    (0.7 x 200: no worse than the whole set on any view); 100 is 0.38 dB short on every view."""
    strategy = MCMCStrategy(cap_max="validated", count_ceiling=2.0, count_cuts=(1.0, 0.7, 0.5), count_tolerance=0.1,
                            **WINDOW)

    def scores(counts):
        return [[20.0 + v + math.log2(min(n, 130) / 130.0) for v in (0.0, 1.0, 2.0)] for n in counts]

    counts, trials, held, state = _run(strategy, decide=scores)
    assert max(counts.values()) == 200 and state["count_start"] == 100
    assert [s for s, _ in trials] == [190] and trials[0][1].counts == [200, 140, 100] and trials[0][1].steps == 5
    assert all(held[s] for s in range(3, 191)) and not any(held[s] for s in range(191, 300))
    assert state["count_cap"] == 140 and all(counts[s] == 140 for s in range(190, 300))
    assert [c for c, _, _ in state["count_trial"]] == [200, 140, 100]
    assert state["count_trial"][1][2] == scores([140])[0] and state["count_trial"][1][1] == pytest.approx(21.0)
    assert strategy.exploration_summary(state) == {"auto_cap": 140}
    note = strategy.count_decision(state)
    assert note.startswith("count chosen: 140 of 200 Gaussians (step 190)") and "3 held-out views" in note
    assert "may need" not in note  # 140 lies between the candidates' ends


@pytest.mark.parametrize("strategy, widen", [(MCMCStrategy(cap_max="validated", **WINDOW), "--strategy.count-ceiling"),
                                             (DefaultStrategy(cap_max="validated", **WINDOW), "--strategy.grow-grad2d")])
def test_a_pick_at_an_end_of_the_candidates_says_the_count_may_lie_beyond(strategy, widen):
    """Kept the smallest cut (every cut scored as well as the best): the scene may need fewer, and
    the line names the field that tries fewer; kept the whole set (every cut cost more than the
    tolerance): it may need more, and the line names what grows the set further."""
    flat = [[20.0, 21.0, 22.0]] * 3
    state = strategy.initialize_state()
    assert strategy.decide_count(state, 190, [200, 140, 100], flat) == 100
    note = strategy.count_decision(state)
    assert "the smallest cut tried: the scene may need fewer" in note and "--strategy.count-cuts" in note
    state = strategy.initialize_state()
    falling = [[20.0, 21.0, 22.0], [19.0, 20.0, 21.0], [18.0, 19.0, 20.0]]
    assert strategy.decide_count(state, 190, [200, 140, 100], falling) == 200
    note = strategy.count_decision(state)
    assert "the whole set: the scene may need more" in note and widen in note and "count-cuts" not in note
    state = strategy.initialize_state()  # no finite score: the whole set, and not "may need more"
    assert strategy.decide_count(state, 190, [200, 140, 100], [[float("nan")] * 3] * 3) == 200
    note = strategy.count_decision(state)
    assert "no candidate scored a finite PSNR" in note and "may need" not in note


def test_views_are_held_out_until_the_decision_and_no_trial_comes_twice():
    strategy = MCMCStrategy(cap_max="validated", **WINDOW)
    state = strategy.initialize_state()
    assert strategy.last_refinement() == 190
    assert all(strategy.holds_out_views(state, s) for s in (0, 100, 190))
    assert strategy.count_trial_due(state, 180, 100) is None and strategy.count_trial_due(state, 190, 100) is not None
    strategy.decide_count(state, 190, [100, 70], [[20.0, 21.0], [19.0, 20.0]])
    assert state["count_cap"] == 100 and strategy.count_trial_due(state, 190, 100) is None
    assert not strategy.holds_out_views(state, 191)
    fixed = MCMCStrategy(cap_max=500, **WINDOW)
    assert not fixed.holds_out_views(fixed.initialize_state(), 0)
    assert fixed.count_trial_due(fixed.initialize_state(), 190, 100) is None


def test_the_rule_refuses_a_bad_ceiling_cut_tolerance_or_trial():
    for bad, name in ((dict(count_ceiling=0.5), "count_ceiling"), (dict(count_ceiling=float("nan")), "count_ceiling"),
                      (dict(count_cuts=()), "count_cuts"), (dict(count_cuts=(1.0, 0.0)), "count_cuts"),
                      (dict(count_cuts=(1.5,)), "count_cuts"), (dict(count_tolerance=-0.1), "count_tolerance"),
                      (dict(count_trial_steps=0), "count_trial_steps")):
        with pytest.raises(StrategyError, match=name):
            MCMCStrategy(cap_max="validated", **{**WINDOW, **bad})
    with pytest.raises(StrategyError, match="validated"):
        MCMCStrategy(cap_max="validate", **{k: v for k, v in WINDOW.items() if k != "count_trial_steps"})


def test_the_trial_takes_one_percent_of_the_run_unless_set():
    schedule = ScheduleConfig().resolve(30_000)
    assert MCMCStrategy(cap_max="validated").setup(schedule).count_trial_steps == 300
    assert MCMCStrategy(cap_max="validated", count_trial_steps=7).setup(schedule).count_trial_steps == 7
    assert MCMCStrategy(cap_max="validated").setup(ScheduleConfig().resolve(50)).count_trial_steps == 1


def test_a_config_saved_with_the_windowed_rule_still_loads():
    saved = {"_type": "exploregs_plugin.strategies.mcmc:MCMCStrategy", "cap_max": 30000, "count_window": 4,
             "count_min_gain": 0.05}
    strategy = config_from_dict(saved)
    assert isinstance(strategy, MCMCStrategy) and strategy.cap_max == 30000


# ------------------------------------------------------------------------------ a run
class _Record(TrainingCallback):
    def __init__(self):
        self.views, self.counts, self.held = {}, {}, {}

    def after_step(self, trainer, step, stats):
        self.views[step] = stats["views"]
        self.counts[step] = trainer.pipeline.model.num_gaussians
        self.held[step] = trainer.pipeline.datamanager.held_out


def _config(run_dir, **strategy_fields):
    config = get_method("exploregs-mcmc").config
    strategy = replace(config.pipeline.strategy, cap_max="validated", **strategy_fields)
    return replace(config, data="builtin:tiny", max_steps=300, run_dir=run_dir, quiet=True, tensorboard=False,
                   eval_count=1, save_eval_images=False, checkpoint_every=100, num_threads=1,
                   schedule=ScheduleConfig(min_refine_every=10), pipeline=replace(config.pipeline, strategy=strategy))


def _same(a, b) -> bool:
    """Nested dicts, lists and tensors with the same bits."""
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def _same_params(a, b):
    for name, p in a.pipeline.params.items():
        assert torch.equal(p, b.pipeline.params[name]), name


@pytest.fixture(scope="module")
def decided_run(tmp_path_factory, tiny_scene_dir):
    """The run of ``_config`` with a tolerance no cut can miss (1000 dB): (trainer, metrics, record,
    count and held-out views before the first step, run folder). It keeps a checkpoint every 50
    steps, so that a copy of its folder resumes from before the trial at step 240 (step 200) or
    after it (step 250). Shared by the tests below, which read the run and resume copies of its
    folder, never the folder itself."""
    record = _Record()
    config = replace(_config(tmp_path_factory.mktemp("decided") / "run", count_tolerance=1000.0),
                     checkpoint_every=50, keep_checkpoints=10)
    trainer = config.setup(callbacks=[record])
    start_count, held = trainer.pipeline.model.num_gaussians, trainer.pipeline.datamanager.held_out
    metrics = trainer.train()
    return SimpleNamespace(trainer=trainer, metrics=metrics, record=record, start_count=start_count, held=held,
                           run_dir=config.run_dir)


def _resume_from(run_dir, step, copy):
    """A copy of ``run_dir`` holding its checkpoint of ``step`` alone, resumed from it."""
    shutil.copytree(run_dir, copy)
    for checkpoint in (copy / "checkpoints").glob("*.pt"):
        if checkpoint.name != f"step-{step:07d}.pt":
            checkpoint.unlink()
    return Trainer.from_run(copy, max_steps=None, quiet=True)


def test_a_run_holds_views_out_until_the_decision_and_resumes_with_it(tmp_path, decided_run):
    """The tiny scene (8 training views; 2 held out), refinements every 10 steps until step 250, so
    the trial comes at step 240 (3 fine-tuning steps per candidate, 1% of 300). A tolerance no cut
    can miss (1000 dB) keeps the smallest candidate, a quarter of the count at step 240. The
    held-out views are not drawn before the decision and are drawn after, and a run resumed from
    step 250 (after the decision) keeps it. (That a second run of the same seed gives the same
    bits, its decision included, is the test on one and two threads below.)"""
    run = decided_run
    trainer, m, record, n0, held = run.trainer, run.metrics, run.record, run.start_count, run.held
    assert held == [2, 6]
    returned = min(s for s, h in record.held.items() if not h)
    assert returned == 241  # the trial at step 240 decided; the views return from step 241's draw on
    assert not {i for s in range(1, returned + 1) for i in record.views[s]} & set(held)
    assert set(held) <= {i for s in range(returned + 1, 301) for i in record.views[s]}
    state = trainer.pipeline.strategy_state
    tried = [c for c, _, _ in state["count_trial"]]
    assert state["count_start"] == n0 and tried[0] == record.counts[240] == 3 * n0  # grown to the ceiling
    assert tried == candidate_counts(tried[0], (1.0, 0.7, 0.5, 0.35, 0.25))
    assert all(math.isfinite(p) and len(views) == 2 for _, p, views in state["count_trial"])
    cap = m["exploration"]["auto_cap"]
    assert cap == tried[-1] == record.counts[241] == m["num_gaussians"]  # the callback's step s follows step s - 1
    assert m["count_decision"].startswith(f"count chosen: {cap:,} of {tried[0]:,} Gaussians (step 240)")

    resumed = _resume_from(run.run_dir, 250, tmp_path / "resumed-late")  # after the decision
    assert resumed.start_step == 250
    assert resumed.pipeline.datamanager.held_out == [] and resumed.pipeline.strategy_state["count_cap"] == cap
    resumed.train()
    _same_params(trainer, resumed)


def test_a_run_resumed_before_the_decision_holds_the_same_views_and_decides_alike(tmp_path, decided_run):
    run = decided_run
    trainer, m = run.trainer, run.metrics
    resumed = _resume_from(run.run_dir, 200, tmp_path / "resumed")  # before the trial at 240
    assert resumed.start_step == 200 and resumed.pipeline.datamanager.held_out == [2, 6]
    assert resumed.pipeline.strategy_state["count_cap"] is None
    r = resumed.train()
    assert r["exploration"]["auto_cap"] == m["exploration"]["auto_cap"] and r["count_decision"] == m["count_decision"]
    _same_params(trainer, resumed)


def test_the_trial_leaves_the_pipeline_as_it_was_and_pairs_its_candidates(tmp_path, tiny_scene_dir):
    """After a paired cut the parameters, Adam's moments, the strategy's state, the generator and
    the view order are those before it; two candidates of one count score the same bits (the same
    start, views and steps), and the whole set scores as the pipeline's own held-out PSNRs after
    the same steps."""
    trainer = _config(tmp_path / "run").setup()
    pipeline = trainer.pipeline
    for step in range(1, 121):  # refinements at 10, 20, ...: grown and trained, views still held out
        pipeline.train_step(step)
    assert pipeline.datamanager.held_out == [2, 6] and pipeline.model.num_gaussians > 400
    before = {k: v.clone() for k, v in pipeline.params.items()}
    adam = {k: {s: t.clone() for s, t in o.state[o.param_groups[0]["params"][0]].items()}
            for k, o in pipeline.optimizers.items()}
    generator, order = pipeline.generator.get_state(), pipeline.datamanager.state_dict()
    strategy_state = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in pipeline.strategy_state.items()
                      if k != "stats"}
    n = pipeline.model.num_gaussians
    scores, weights = count_trial.paired_cut(pipeline, 120, [n, n // 2, n // 2], 3)
    assert weights.shape == (n,) and len(scores) == 3 and all(len(s) == 2 for s in scores)
    assert scores[1] == scores[2]  # paired: one count, the same bits
    for k, v in before.items():
        assert torch.equal(pipeline.params[k], v), k
    for k, o in pipeline.optimizers.items():
        for s, t in o.state[o.param_groups[0]["params"][0]].items():
            assert torch.equal(t, adam[k][s]), (k, s)
    assert torch.equal(pipeline.generator.get_state(), generator) and _same(pipeline.datamanager.state_dict(), order)
    assert _same({k: v for k, v in pipeline.strategy_state.items() if k != "stats"}, strategy_state)
    assert pipeline.strategy is trainer.pipeline.strategy and type(pipeline.strategy).__name__ == "MCMCStrategy"
    # the whole set, fine-tuned 3 steps with nothing else changed, is what the trial scored for it
    pipeline.strategy = count_trial.HoldingStrategy().setup(pipeline.schedule)
    pipeline.strategy_state = pipeline.strategy.initialize_state(pipeline.scene_extent)
    for _ in range(3):
        pipeline.train_step(120)
    assert pipeline.held_out_psnrs(120) == scores[0]


def test_too_few_training_views_to_hold_out_fall_back_to_a_rule_that_reads_none(tmp_path, tiny_scene_dir, capsys):
    """A capture of 5 training views asks for a count decided on held-out views: MCMC decides it
    by the training loss's fall instead (cap_max 'auto'), Default and Seed+Split by the end-of-run
    cut; one line says which, no view is held out, and the run trains."""
    def five_views(config):
        return replace(config, pipeline=replace(config.pipeline, datamanager=replace(
            config.pipeline.datamanager, test_every=2, use_dataset_split=False)))  # 5 training views of 10

    mcmc = five_views(_config(tmp_path / "mcmc"))
    trainer = mcmc.setup()
    assert trainer.pipeline.strategy.cap_max == "auto" and trainer.pipeline.datamanager.held_out == []
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("count:"))
    assert line == ("count: tiny has 5 training views, fewer than the 8 a count decided on held-out views needs; "
                    "the training loss's fall (--strategy.cap-max auto) decides it instead")
    config = get_method("exploregs-seedsplit").config
    strategy = replace(config.pipeline.strategy, cap_max="validated")
    seedsplit = five_views(replace(config, data="builtin:tiny", max_steps=40, run_dir=tmp_path / "seedsplit",
                                   quiet=True, tensorboard=False, eval_count=1, save_eval_images=False,
                                   checkpoint_every=40, num_threads=1,
                                   pipeline=replace(config.pipeline, strategy=strategy)))
    trainer = seedsplit.setup()
    assert trainer.pipeline.strategy.cap_max is None and trainer.pipeline.datamanager.held_out == []
    assert "the end-of-run cut by significance (--strategy.final-weight-share 0.003) decides it instead" in \
        capsys.readouterr().out
    m = trainer.train()
    assert m["num_gaussians"] > 0 and m["count_decision"].startswith("count: ")


def test_the_datamanager_passes_over_held_views_and_keeps_them_in_its_state(tiny_dm):
    """Held views are never drawn, the order of the others is the seeded one with them left out,
    the held list travels in the state, and a bad list is refused."""
    from exploregs_plugin.data import DataManagerConfig

    plain = DataManagerConfig(data="builtin:tiny").setup()
    expected = [i for i in plain.next_train_indices(40) if i not in (1, 5)]
    tiny_dm.hold_out([5, 1])
    assert tiny_dm.held_out == [1, 5]
    drawn = tiny_dm.next_train_indices(len(expected))
    assert drawn == expected  # the same permutations, the held ones passed over
    state = tiny_dm.state_dict()
    again = DataManagerConfig(data="builtin:tiny").setup()
    again.load_state_dict(state)
    assert again.held_out == [1, 5] and again.next_train_indices(12) == tiny_dm.next_train_indices(12)
    tiny_dm.return_held()
    assert {1, 5} <= set(tiny_dm.next_train_indices(16))  # two epochs: every view again
    for bad in ([8], [-1], list(range(8))):
        with pytest.raises(ValueError, match="hold_out"):
            tiny_dm.hold_out(bad)
    del state["held_out"]  # a checkpoint from before held-out views holds none
    again.load_state_dict(state)
    assert again.held_out == []


def test_a_candidate_that_goes_non_finite_is_never_kept_and_does_not_stop_the_run(tmp_path, tiny_scene_dir,
                                                                                   monkeypatch):
    """The smallest candidate's set is given a NaN position after its cut: it scores NaN on every
    held-out view, the others score as before, and the run's own non-finite record (which the
    trainer raises on) stays clean."""
    trainer = _config(tmp_path / "run").setup()
    pipeline = trainer.pipeline
    for step in range(1, 61):
        pipeline.train_step(step)
    n = pipeline.model.num_gaussians
    clean, _ = count_trial.paired_cut(pipeline, 60, [n, n // 2], 3)
    real_cut = count_trial.cut

    def poisoned(pipeline, weights, count, stats):
        real_cut(pipeline, weights, count, stats)
        if count == n // 2:
            with torch.no_grad():
                pipeline.params["means"][0] = float("nan")

    monkeypatch.setattr(count_trial, "cut", poisoned)
    scores, _ = count_trial.paired_cut(pipeline, 60, [n, n // 2], 3)
    assert scores[0] == clean[0] and all(math.isfinite(p) for p in clean[1])
    assert len(scores[1]) == 2 and all(math.isnan(p) for p in scores[1])
    assert pipeline.nonfinite_error() is None and torch.isfinite(pipeline.params["means"]).all()
    assert pick_count([n, n // 2], scores, 1000.0) == 0


def test_mcmc_explore_decides_its_count_the_same_way():
    from exploregs_plugin.strategies import MCMCExploreStrategy

    strategy = MCMCExploreStrategy(cap_max="validated", count_ceiling=1.5, explore_share=0.5, explore_split=1.0,
                                   explore_box=0.0, explore_guided=0.0, **WINDOW)
    counts, trials, _, state = _run(strategy, decide=lambda counts: [[20.0, 21.0] for _ in counts])
    assert max(counts.values()) == 150 and [s for s, _ in trials] == [190]
    assert state["count_cap"] == min(trials[0][1].counts)  # every cut as good: the smallest
    assert all(counts[s] == state["count_cap"] for s in range(190, 300))


def test_the_decision_and_the_run_are_the_same_bits_on_one_and_two_threads(tmp_path, tiny_scene_dir):
    """60 steps: the set grows at the refinements every 10 steps and the trial comes at the last,
    step 40, where the tolerance keeps a middle candidate (so the pick rests on the held-out
    scores); the run trains on with the kept set to its end."""
    runs = []
    for threads in (1, 2):
        trainer = replace(_config(tmp_path / f"threads-{threads}"), num_threads=threads, max_steps=60).setup()
        runs.append((trainer.train(), trainer))
    (first, a), (second, b) = runs
    assert first["count_decision"] == second["count_decision"] and first["count_decision"].startswith("count chosen")
    _same_params(a, b)


@pytest.mark.parametrize("method", ["exploregs-default", "exploregs-seedsplit"])
def test_default_and_seed_split_decide_their_count_the_same_way(tmp_path, tiny_scene_dir, method):
    """cap_max 'validated' on the growing methods: no ceiling (their thresholds bound growth), the
    same held-out views and the same trial at their last refinement (step 40 of 100: refinement
    stops at half the run), and a tolerance no cut can miss keeps the smallest candidate. The tiny
    scene at a quarter of its size (16 x 12 pixels) and 100 steps: the rule is the same at any size
    and length, and the growing sets (400 Gaussians to 3,000 and 9,000 by step 40; over 10,000 by
    step 140 of 300 steps, at twice and more the cost per step) cost less to train."""
    config = get_method(method).config
    strategy = replace(config.pipeline.strategy, cap_max="validated", count_tolerance=1000.0)
    config = replace(config, data="builtin:tiny", data_factor=4, max_steps=100, run_dir=tmp_path / "run", quiet=True,
                     tensorboard=False, eval_count=1, save_eval_images=False, checkpoint_every=100, num_threads=1,
                     schedule=ScheduleConfig(min_refine_every=10), pipeline=replace(config.pipeline, strategy=strategy))
    record = _Record()
    trainer = config.setup(callbacks=[record])
    assert trainer.pipeline.strategy.last_refinement() == 40 and trainer.pipeline.datamanager.held_out == [2, 6]
    m = trainer.train()
    assert min(s for s, h in record.held.items() if not h) == 41
    assert not {i for s in range(1, 42) for i in record.views[s]} & {2, 6}
    tried = [c for c, _, _ in trainer.pipeline.strategy_state["count_trial"]]
    assert tried == candidate_counts(tried[0], (1.0, 0.7, 0.5, 0.35, 0.25))
    assert m["exploration"]["auto_cap"] == tried[-1] == record.counts[41]
    assert m["count_decision"].startswith(f"count chosen: {tried[-1]:,} of {tried[0]:,} Gaussians (step 40)")
