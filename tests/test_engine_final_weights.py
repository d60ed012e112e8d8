"""The cuts' weights from the training renders of the epoch before each (engine/final_weights.py): the
settled cut's after growth, the end-of-run cut's in the last epoch."""

from __future__ import annotations

import random

import torch

from exploregs_plugin.data.datamanager import in_last_epoch
from exploregs_plugin.engine import count_trial, final_weights
from exploregs_plugin.engine.pipeline import Pipeline
from exploregs_plugin.engine.trainer import TrainerConfig
from exploregs_plugin.model.significance import add_view_, visibility_totals
from exploregs_plugin.schedule import ScheduleConfig

VIEWS = 8  # builtin:tiny's training views


def _last_whole_epoch(length: int, draws: int) -> list[bool]:
    """Brute force: deal ``draws`` views one by one from a fresh order, ``length`` an epoch, and
    mark the draws of the last epoch dealt whole."""
    whole = draws // length  # epochs 0 .. whole - 1 are dealt whole
    return [whole > 0 and d // length == whole - 1 for d in range(draws)]


def test_the_draws_marked_are_the_last_whole_epoch_each_view_once():
    rng = random.Random(0)
    for _ in range(500):
        length, batch, steps = rng.randint(1, 9), rng.randint(1, 4), rng.randint(1, 12)
        draws, marked = steps * batch, []
        for step in range(steps):  # asked a batch at a time, before the draw, as the pipeline asks
            dealt = step * batch
            position = (dealt - 1) % length + 1 if dealt else 0  # the datamanager's: length once an epoch is done
            marked += in_last_epoch(position, length, draws - dealt, batch)
        assert marked == _last_whole_epoch(length, draws), (length, batch, steps)
        assert sum(marked) in (0, length)
    assert in_last_epoch(1, 4, 7, 7) == [False, False, False, True, True, True, True]
    assert in_last_epoch(1, 4, 6, 6) == [True, True, True, False, False, False]  # with the one dealt before
    assert in_last_epoch(0, 4, 3, 3) == [False, False, False]


def test_no_draw_is_marked_while_views_are_held_out(tiny_scene_dir):
    from exploregs_plugin.data import DataManagerConfig

    dm = DataManagerConfig(data="builtin:tiny").setup()
    assert dm.last_epoch_draws(2, VIEWS) == [True, True]
    dm.hold_out([0])
    assert dm.last_epoch_draws(2, VIEWS) == [False, False]
    dm.return_held()
    assert dm.last_epoch_draws(1, VIEWS + 1) == [True] and dm.last_epoch_draws(1, 2 * VIEWS) == [False]


def _trainer(run_dir, steps: int, **overrides):
    fields = dict(data="builtin:tiny", max_steps=steps, run_dir=run_dir, quiet=True, tensorboard=False, eval_count=1,
                  checkpoint_every=10_000, save_eval_images=False, schedule=ScheduleConfig(min_refine_every=10))
    return TrainerConfig(**{**fields, **overrides}).setup()


def test_each_cut_reads_each_views_render_of_the_epoch_before_it_after_growth(tmp_path, monkeypatch):
    from exploregs_plugin.data.datamanager import DataManager

    marked, seen, notes, read, before = [], [], [], [], []
    real_marks, real_draw = Pipeline._final_window_draws, DataManager.next_train_indices
    real_add, real_note, real_totals, real_cut = (final_weights.add_window_view, Pipeline.final_cut_note,
                                                  final_weights.window_totals, Pipeline._final_cut)

    def marks(pipeline, step):
        marked.append(step)
        return real_marks(pipeline, step)

    def draw(dm, count):
        indices = real_draw(dm, count)
        marked.append(indices)
        return indices

    def add(state, visibility, view):  # the view of the step, rendered with the parameters it was drawn with
        step, (index,) = marked[-2], marked[-1]
        params = {k: v.detach() for k, v in pipeline.params.items()}  # before the step's optimiser step
        fresh = visibility_totals(params, [pipeline.datamanager.train_cameras[index]], pipeline.model.config.raster,
                                  pipeline.background)
        seen.append((step, index, torch.allclose(visibility.double(), fresh[:, :3], rtol=1e-5, atol=1e-6)
                     and view == index))
        real_add(state, visibility, view)

    def note(pipeline, step):
        said = real_note(pipeline, step)
        notes.extend([said] if said else [])
        return said

    def cut(pipeline, step, last=True):
        before.append(pipeline.model.num_gaussians)
        return real_cut(pipeline, step, last=last)

    def no_pass(pipeline):
        raise AssertionError("the cut rendered the views again")

    monkeypatch.setattr(Pipeline, "_final_window_draws", marks)
    monkeypatch.setattr(DataManager, "next_train_indices", draw)
    monkeypatch.setattr(final_weights, "add_window_view", add)
    monkeypatch.setattr(Pipeline, "final_cut_note", note)
    monkeypatch.setattr(Pipeline, "_final_cut", cut)
    monkeypatch.setattr(count_trial, "training_visibility", no_pass)
    monkeypatch.setattr(final_weights, "window_totals",
                        lambda state, views: read.append(real_totals(state, views)) or read[-1])
    # growth stops at step 24, the settled cut comes after 38 steps (0.8 of the run); epochs of 8
    # draws: the settled cut's is steps 24-31 (the last whole one before it), the end-of-run cut's 40-47
    trainer = _trainer(tmp_path / "run", 48)
    pipeline = trainer.pipeline
    assert pipeline.strategy.settled_cut_iter == 38
    metrics = trainer.train()
    assert [s for s, _, _ in seen] == [*range(24, 32), *range(40, 48)] and all(ok for _, _, ok in seen), seen
    assert sorted(i for _, i, _ in seen[:VIEWS]) == sorted(i for _, i, _ in seen[VIEWS:]) == list(range(VIEWS))
    assert [r.shape for r in read] == [(n, 4) for n in before]  # whole sums of CUT_COLUMNS at both cuts
    assert metrics["num_gaussians"] < before[1] < before[0]  # both cut
    assert notes == [f"after step 38: the cut weighs the {before[0]:,} Gaussians by their weights in the last "
                     f"epoch's renders of the {VIEWS} training views; the rest of the run trains those it keeps",
                     f"after step 48: the end-of-run cut weighs the {before[1]:,} Gaussians by their weights in "
                     f"the last epoch's renders of the {VIEWS} training views before the final evaluation"]
    # metrics.json keeps each cut's line; count_decision is the last
    lines = metrics["cut_lines"]
    assert len(lines) == 2 and metrics["count_decision"] == lines[1]
    assert lines[0].startswith(f"count: {before[1]:,} of {before[0]:,} Gaussians kept after step 38, for the rest "
                               f"of the run: ")
    assert lines[1].startswith(f"count: {metrics['num_gaussians']:,} of {before[1]:,} Gaussians kept after the last "
                               f"step (48): ")
    state = pipeline.strategy_state
    assert final_weights.FINAL_WEIGHTS not in state["stats"] and final_weights.FINAL_VIEWS not in state


def test_a_window_opened_inside_its_epoch_renders_only_the_views_it_lacks(tmp_path, monkeypatch):
    """Growth stops at step 10 and the settled cut comes after 16 steps: its epoch (draws 8-15) began
    before growth ended, so its window holds the draws of steps 10-15 and the cut renders the two
    views drawn at steps 8 and 9; the end-of-run cut's epoch (16-23) does not end within the run, so
    it renders every view."""
    from exploregs_plugin.data.datamanager import DataManager

    passes, partial, drawn, real_draw = [], [], [], DataManager.next_train_indices
    real_pass, real_partial = count_trial.training_visibility, count_trial.views_visibility
    monkeypatch.setattr(count_trial, "training_visibility", lambda p: passes.append(p.model.num_gaussians) or real_pass(p))
    monkeypatch.setattr(count_trial, "views_visibility", lambda p, views: partial.append(list(views)) or real_partial(p, views))
    monkeypatch.setattr(DataManager, "next_train_indices", lambda dm, count: drawn.extend(real_draw(dm, count)) or drawn[-count:])
    trainer = _trainer(tmp_path / "run", 20)
    trainer.train()
    assert len(drawn) == 20 and sorted(drawn[8:16]) == list(range(VIEWS))  # steps 8-15: one epoch
    assert partial[0] == sorted(drawn[8:10])  # the settled cut rendered only what its window lacked
    assert len(passes) == 1  # the end-of-run cut: a whole pass
    assert final_weights.FINAL_VIEWS not in trainer.pipeline.strategy_state
    assert final_weights.FINAL_SEEN not in trainer.pipeline.strategy_state


def test_a_completed_window_holds_each_view_once_as_a_pass_would():
    """Sums of some views completed with the render of the others equal the sums of them all
    (the same statistics per view), and a window that cannot name its views is not completed."""
    per_view = [torch.tensor([[s, s, p], [0.5 * s, s, 0.5 * p]], dtype=torch.float64)
                for s, p in ((1.0, 0.25), (3.0, 0.5), (2.0, 0.75), (0.5, 0.125))]
    whole = {"stats": {}}
    for i, view in enumerate(per_view):
        final_weights.add_window_view(whole, view, i)
    part = {"stats": {}}
    for i in (2, 0):
        final_weights.add_window_view(part, per_view[i], i)
    assert final_weights.missing_views(part, 4) == [1, 3] and final_weights.window_totals(part, 4) is None
    rendered = torch.zeros(2, 4, dtype=torch.float64)  # as visibility_totals sums the views it renders
    for i in (1, 3):
        add_view_(rendered, per_view[i])
    final_weights.complete_window(part, rendered, [1, 3])
    assert torch.equal(final_weights.window_totals(part, 4), final_weights.window_totals(whole, 4))
    assert final_weights.missing_views(part, 4) == []
    unnamed = {"stats": {}}
    final_weights.add_window_view(unnamed, per_view[0])  # a checkpoint's sums that do not name their views
    assert final_weights.missing_views(unnamed, 4) is None
    twice = {"stats": {}}
    for i in (1, 1):
        final_weights.add_window_view(twice, per_view[i], i)
    assert final_weights.missing_views(twice, 4) is None


def test_summing_the_weights_changes_no_bit_of_the_run_and_the_sums_are_the_same_on_one_and_two_threads(
        tmp_path, monkeypatch):
    def no_cut(pipeline, step, last=True):  # the runs differ only here; the settled cut clears its window
        if not last:
            final_weights.clear_window(pipeline.strategy_state)
        return 0, []

    monkeypatch.setattr(Pipeline, "_final_cut", no_cut)

    def run(name: str, threads: int = 1):
        trainer = _trainer(tmp_path / name, 40, num_threads=threads)
        trainer.train()
        state = trainer.pipeline.strategy_state
        return {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}, state

    summed, state = run("summed")
    assert final_weights.window_views(state) == VIEWS  # the last epoch's window was summed (no cut read it)
    _, on_two = run("two-threads", threads=2)
    assert torch.equal(final_weights.window_totals(state, VIEWS), final_weights.window_totals(on_two, VIEWS))
    monkeypatch.setattr(Pipeline, "_final_window_draws", lambda pipeline, step: [False] * pipeline.batch_size)
    plain, _ = run("plain")
    assert summed.keys() == plain.keys() and all(torch.equal(summed[k], plain[k]) for k in summed)


def test_sums_of_a_checkpoint_whose_window_held_three_columns_are_never_whole():
    """A checkpoint written inside the last epoch by a version whose window summed [N, 3] (no view
    weight) resumes without an error, and the cut renders the views itself instead of reading an
    order it cannot form."""
    old = torch.tensor([[1.0, 1.0, 0.5], [2.0, 2.0, 0.25]], dtype=torch.float64)
    state = {"stats": {final_weights.FINAL_WEIGHTS: old.clone()}, final_weights.FINAL_VIEWS: 1}
    final_weights.add_window_view(state, torch.tensor([[1.0, 1.0, 0.75], [0.0, 0.0, 0.0]]))
    assert final_weights.window_views(state) == 2 and torch.equal(state["stats"][final_weights.FINAL_WEIGHTS], old)
    assert final_weights.window_totals(state, 2) is None
    fresh = {"stats": {}}
    for _ in range(2):
        final_weights.add_window_view(fresh, torch.tensor([[1.0, 1.0, 0.75], [0.0, 0.0, 0.0]]))
    assert final_weights.window_totals(fresh, 2).tolist() == [[2.0, 2.0, 0.75, 1.0], [0.0, 0.0, 0.0, 0.0]]


def test_a_run_resumed_before_or_after_the_settled_cut_ends_with_the_same_bits(tmp_path):
    """Checkpoints at step 28 (inside the settled cut's window, steps 24-31: its sums are carried)
    and at step 40 (after the settled cut, after step 38) resume to the uninterrupted run's last bits."""
    import shutil

    from exploregs_plugin.engine.training_loop import Trainer

    trainer = _trainer(tmp_path / "run", 48, checkpoint_every=4, keep_checkpoints=12)
    whole = trainer.train()
    params = {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}
    assert trainer.pipeline.strategy.settled_cut_iter == 38 and trainer.op_totals["pruned"] > 0
    inside = torch.load(tmp_path / "run" / "checkpoints" / "step-0000028.pt", weights_only=False)["strategy_state"]
    assert inside[final_weights.FINAL_VIEWS] == 4  # steps 24-27 summed
    for step in (28, 40):
        copy = tmp_path / f"from-{step}"
        (copy / "checkpoints").mkdir(parents=True)
        shutil.copy(tmp_path / "run" / "config.yml", copy / "config.yml")
        shutil.copy(tmp_path / "run" / "checkpoints" / f"step-{step:07d}.pt", copy / "checkpoints")
        resumed = Trainer.from_run(copy, quiet=True)
        assert resumed.start_step == step
        again = resumed.train()
        assert again["psnr"] == whole["psnr"] and again["num_gaussians"] == whole["num_gaussians"], step
        assert again["cut_lines"] == whole["cut_lines"] and len(whole["cut_lines"]) == 2, step  # kept in the checkpoint
        assert all(torch.equal(v.detach(), params[k]) for k, v in resumed.pipeline.params.items()), step



def test_a_run_resumed_inside_a_window_opened_inside_its_epoch_ends_with_the_same_bits(tmp_path):
    """The 20-step run above: a checkpoint at step 12 holds the settled cut's window of steps 10
    and 11 with the views it names; resumed, the cut renders the same lacking views and the run
    ends with the uninterrupted run's bits."""
    import shutil

    from exploregs_plugin.engine.training_loop import Trainer

    trainer = _trainer(tmp_path / "run", 20, checkpoint_every=4, keep_checkpoints=12)
    whole = trainer.train()
    params = {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}
    inside = torch.load(tmp_path / "run" / "checkpoints" / "step-0000012.pt", weights_only=False)["strategy_state"]
    assert inside[final_weights.FINAL_VIEWS] == 2 and len(inside[final_weights.FINAL_SEEN]) == 2
    copy = tmp_path / "from-12"
    (copy / "checkpoints").mkdir(parents=True)
    shutil.copy(tmp_path / "run" / "config.yml", copy / "config.yml")
    shutil.copy(tmp_path / "run" / "checkpoints" / "step-0000012.pt", copy / "checkpoints")
    resumed = Trainer.from_run(copy, quiet=True)
    again = resumed.train()
    assert again["cut_lines"] == whole["cut_lines"] and again["num_gaussians"] == whole["num_gaussians"]
    assert all(torch.equal(v.detach(), params[k]) for k, v in resumed.pipeline.params.items())
