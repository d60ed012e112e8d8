"""A training step does not wait for the device: its values are read only at the read points.

On a GPU every read of a device value (``.item()``, ``float``, ``bool``, ``.cpu()``, a nonzero,
...) makes the host wait for the kernels queued before it. On the CPU such a read costs nothing,
so these tests count them instead: a torch function mode sees each way of reading during the run,
and every read is charged to the step during which it happened."""

from __future__ import annotations

import math
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import torch
from torch.overrides import TorchFunctionMode

from exploregs_plugin.callbacks import TrainingCallback
from exploregs_plugin.engine.collapse import CollapseError, CollapseWatch
from exploregs_plugin.method_configs import get_method
from exploregs_plugin.engine.nonfinite import NonFiniteWatch
from exploregs_plugin.schedule import ScheduleConfig

STEPS = 40
LOG_EVERY = 10
_READS = ("item", "__float__", "__int__", "__index__", "__bool__", "__format__", "__array__", "tolist", "numpy", "cpu")


class HostReads(TorchFunctionMode):
    """Counts the reads of tensor values by the host while active, by step (``step``, set by the
    caller) and by place (the nearest line of exploregs_plugin).

    A torch function mode sees every torch function and Tensor method, dunders included, without
    touching the Tensor class (a patched and restored ``Tensor.__getitem__`` leaves a Python-level
    sequence slot on it, and later ``torch.tensor([[t, 0], ...])`` calls fail). Counted: ``item``,
    ``float``, ``int``, ``index``, ``bool``, ``format``, numpy's ``__array__``, ``tolist``,
    ``numpy``, ``cpu``, ``to("cpu")`` (a device named by the string: the step's own ``to(device)``
    calls name the run's device), and the ops whose output size is read from the device:
    ``nonzero``, one-argument ``torch.where`` and indexing with a bool tensor. Not counted: torch's
    optimizers reading Adam's step count (a CPU tensor also on CUDA), the datamanager
    (``exploregs_plugin/data``: the images and the camera order live on the host) and the renderer
    (``exploregs_plugin/rasterizer``: the CPU and torch renderers size their work from the device,
    a nonzero of the visible Gaussians per view; on a GPU the gsplat backend is the one to train
    with, and its kernels size their own)."""

    def __init__(self) -> None:
        super().__init__()
        self.step: int | None = None
        self.by_step: Counter[int] = Counter()
        self.places: Counter[tuple[int, str, str]] = Counter()

    def _count(self, kind: str) -> None:
        if self.step is None:
            return
        frame = sys._getframe(2)  # the caller of the torch function (above __torch_function__)
        if frame.f_code.co_filename.replace("\\", "/").endswith("torch/optim/optimizer.py"):
            return  # _get_value: Adam's step count, on the host
        while frame is not None and "exploregs_plugin" not in frame.f_code.co_filename:
            frame = frame.f_back
        if frame is None:
            return  # not a read of the run's code (this test's own)
        path = frame.f_code.co_filename.replace("\\", "/")
        if "/exploregs_plugin/data/" in path or "/exploregs_plugin/rasterizer/" in path:
            return
        self.by_step[self.step] += 1
        self.places[(self.step, kind, f"{path.rsplit('/exploregs_plugin/', 1)[-1]}:{frame.f_lineno}")] += 1

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        if name in _READS or name == "nonzero":
            self._count(name)
        elif name == "to":
            target = kwargs.get("device", args[1] if len(args) > 1 else None)
            if isinstance(target, str) and target.startswith("cpu"):
                self._count("to('cpu')")
        elif name == "where" and len(args) + len(kwargs) == 1:
            self._count("where(cond)")
        elif name == "__getitem__" and len(args) == 2:
            keys = args[1] if isinstance(args[1], tuple) else (args[1],)
            if any(isinstance(k, torch.Tensor) and k.dtype == torch.bool for k in keys):
                self._count("[bool mask]")
        return func(*args, **kwargs)


class _ChargeToStep(TrainingCallback):
    """Charges the reads to the step that is running (from its before_step to the next one's)."""

    def __init__(self, reads: HostReads) -> None:
        self.reads = reads

    def before_step(self, trainer: Any, step: int) -> None:
        self.reads.step = step


def counted_run(method: str, run_dir: Path, **pipeline: Any) -> tuple[HostReads, Any]:
    """A STEPS-step run of ``method`` on builtin:tiny (refinement every 10 steps, a log line every
    LOG_EVERY, one evaluation and one checkpoint, at the end) with its host reads counted."""
    config = get_method(method).config
    dm = replace(config.pipeline.datamanager, data="builtin:tiny")
    config = replace(config, pipeline=replace(config.pipeline, datamanager=dm, **pipeline), max_steps=STEPS,
                     run_dir=run_dir, quiet=True, tensorboard=False, eval_count=1, checkpoint_every=1000,
                     log_every=LOG_EVERY, save_eval_images=False,
                     schedule=ScheduleConfig(min_refine_every=10, min_reset_every=30))
    reads = HostReads()
    trainer = config.setup(callbacks=[_ChargeToStep(reads)])
    with reads:
        trainer.train()
    return reads, trainer


def read_points(trainer: Any) -> set[int]:
    """The steps after which the trainer reads: its log lines (the last step's included)."""
    return {s for s in range(STEPS) if (s + 1) % LOG_EVERY == 0 or s + 1 == STEPS}


def refinement_steps(strategy: Any) -> set[int]:
    """The steps at which a strategy changes the Gaussian set (it must learn the new count): its
    refinements and, where it makes one, the settled cut's (after step 27 of 40 for Default's)."""
    settled = strategy.settled_cut_step(STEPS)
    return {s for s in range(STEPS) if strategy.refine_start_iter < s < strategy.refine_stop_iter
            and s % strategy.refine_every == 0} | ({settled - 1} if settled is not None else set())


# Reads of a step outside the log lines and refinements, at most: none, or for Seed+Split one in
# the window of its random splitting (every step there: how many rows may be drawn).
# MCMC's automatic cap sums the loss as a tensor and reads it once per refinement.
@pytest.mark.parametrize("method, most, strategy", [
    ("exploregs-default", 0, {}), ("exploregs-mcmc", 0, {}), ("exploregs-seedsplit", 1, {}),
    ("exploregs-mcmc-explore", 0, {}), ("exploregs-mcmc-explore", 0, {"cap_max": "auto"})])
def test_a_step_reads_the_device_only_at_the_log_line_and_refinements(tmp_path, tiny_scene_dir, method, most, strategy):
    changed = replace(get_method(method).config.pipeline.strategy, **strategy)
    reads, trainer = counted_run(method, tmp_path / "run", strategy=changed)
    logged, refined = read_points(trainer), refinement_steps(trainer.pipeline.strategy)
    assert refined and not refined & logged  # both kinds of step are seen, apart
    quiet = [s for s in range(STEPS) if s not in logged | refined]
    # elsewhere a step reads nothing, or one value (12 to 21 reads before)
    assert {s: reads.by_step[s] for s in quiet if reads.by_step[s] > most} == {}, \
        [place for place in reads.places if place[0] in quiet]
    # a log line reads the non-finite record, the collapse watch's steps and the logged values,
    # one read each (the last step also the evaluation's and the checkpoint's)
    for step in sorted(logged - {STEPS - 1}):
        assert 3 <= reads.by_step[step] <= 3 + most, [place for place in reads.places if place[0] == step]
    assert all(reads.by_step[s] > 0 for s in refined)  # a refinement learns what it grew and pruned


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
def test_the_nonfinite_record_names_the_first_bad_step_when_read_later(monkeypatch, compiled):
    from exploregs_plugin.engine import nonfinite
    from exploregs_plugin.kernels import cpp_problem

    if compiled and cpp_problem() is not None:
        pytest.skip(f"compiled kernels unavailable: {cpp_problem()}")
    monkeypatch.setattr(nonfinite, "_compiled", lambda tensors, dtypes: compiled)
    watch = NonFiniteWatch()
    opacities = torch.zeros(5)
    field = torch.zeros(4)
    named = [("opacities", opacities), ("deformation.grid", field)]

    def totals(loss: float) -> dict[str, torch.Tensor]:
        return {"loss": torch.tensor(loss, dtype=torch.float64), "psnr": torch.tensor(20.0, dtype=torch.float64),
                "l1": torch.tensor(0.5, dtype=torch.float64)}

    for step, loss in enumerate([0.3, 0.2]):
        watch.loss(step, totals(loss))
        watch.params(step, named, 5)
    assert watch.error() is None
    opacities[1:3] = math.inf  # step 2: two Gaussians of five
    watch.loss(2, totals(0.2))
    watch.params(2, named, 5)
    opacities[:] = math.nan  # later steps: everything, and the loss, go bad; the record keeps step 2
    field[0] = math.nan
    for step in (3, 4):
        watch.loss(step, totals(math.nan))
        watch.params(step, named, 7)
    error = watch.error()
    assert str(error) == "step 2: parameter 'opacities' has non-finite values in 2 of 5 Gaussians" and error.step == 2
    # a loss that goes bad at the step its parameters do is named first; a part's values are counted
    watch = NonFiniteWatch()
    watch.loss(0, totals(math.inf))
    watch.params(0, named, 5)
    assert str(watch.error()) == "step 0: the loss is inf (terms: l1=0.5)"
    watch = NonFiniteWatch()
    opacities.zero_()
    watch.loss(0, totals(0.1))
    watch.params(0, named, 5)
    assert str(watch.error()) == "step 0: parameter 'deformation.grid' has 1 non-finite values"


def test_the_collapse_watch_read_at_the_log_line_names_the_step_that_collapsed(tmp_path, tiny_scene_dir):
    from exploregs_plugin.scripts.train import parse_config

    trainer = parse_config(["exploregs-default", "--data", "builtin:tiny", "--max-steps", "30", "--quiet",
                            "--no-tensorboard", "--run-dir", str(tmp_path / "run")]).setup()
    psnrs = [20.0] * 5 + [2.0] * 15
    expected, watch = None, CollapseWatch()
    for step, psnr in enumerate(psnrs):  # as judged at each step
        reason = watch.update(step, psnr, 0.3)
        expected = expected or (reason and f"step {step}: {reason}.")
    assert expected is not None and not expected.startswith("step 19")
    for step, psnr in enumerate(psnrs[:-1]):  # tensors, left on the device until the read
        stats = {"psnr": torch.tensor(psnr, dtype=torch.float64), "loss": torch.tensor(0.3, dtype=torch.float64),
                 "counts": {}, "views": ()}
        trainer.watches.check(step, stats, read=False)
    with pytest.raises(CollapseError) as raised:
        trainer.watches.check(len(psnrs) - 1, {"psnr": 2.0, "loss": 0.3, "counts": {}, "views": ()}, read=True)
    assert str(raised.value).startswith(expected)
