"""When a training run reads its watches: the collapse watch (:mod:`exploregs_plugin.engine.collapse`) and
the non-finite record (:mod:`exploregs_plugin.engine.nonfinite`) stop a run that went bad, before it
writes a checkpoint of that state, at the cost of few reads of the device (docs/architecture.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from exploregs_plugin.engine.collapse import CollapseError, CollapseWatch, deliberate_setback
from exploregs_plugin.engine.pipeline import NonFiniteError, Pipeline
from exploregs_plugin.engine.run_logger import host_values
from exploregs_plugin.schedule import Schedule


class RunWatches:
    """The watches of one run. A step's PSNR and loss stay on the device until a read point (the
    log line, an evaluation, a checkpoint, the last step: :meth:`reads_at`); there the steps since
    the last one are read in one go and judged in order, as each would have been at its own step,
    so the error names the step that collapsed. The run trains on to the read point meanwhile (at
    most ``log_every`` steps), which the checkpoints never see: the trainer reads before it saves.
    ``last_checkpoint`` tells the errors where the run can be taken up again."""

    def __init__(self, pipeline: Pipeline, schedule: Schedule, collapse_watch: bool, log_every: int,
                 checkpoint_every: int, last_checkpoint: Callable[[], Path | None]) -> None:
        self.pipeline, self.schedule = pipeline, schedule
        self.collapse_watch, self.log_every, self.checkpoint_every = collapse_watch, log_every, checkpoint_every
        self.last_checkpoint = last_checkpoint
        self.collapse = CollapseWatch()
        self._collapse_due: list[tuple[int, Any, Any, bool, Any]] = []  # steps the watch has not judged yet

    def reads_at(self, step: int, eval_steps: set[int]) -> bool:
        """Whether the trainer reads the device after ``step``: at its log line, an evaluation, a
        periodic checkpoint and the last step. Elsewhere a step queues its work and goes on."""
        done = step + 1
        return (done % max(1, self.log_every) == 0 or done == self.schedule.max_steps or done in eval_steps
                or done % self.checkpoint_every == 0)

    def check(self, step: int, stats: dict[str, Any], read: bool = True) -> None:
        """Queue ``step``'s PSNR and loss for the collapse watch (see :class:`CollapseWatch`); with
        ``read`` (a read point), judge every queued step and the non-finite record."""
        if self.collapse_watch:
            views = stats.get("views", ())
            restart = deliberate_setback(stats["counts"], self.pipeline.model.num_gaussians)
            # a coarse-to-fine level ends: the next step's PSNR is of other (full-size) targets,
            # which the records of the easier coarse ones must not judge
            restart = restart or self.schedule.downscale_at(step + 1) != self.schedule.downscale_at(step)
            self._collapse_due.append((step, stats["psnr"], stats["loss"], restart,
                                       views[0] if len(views) == 1 else None))
        if read:
            self.read()

    def read(self) -> None:
        """The read point: the non-finite record and the collapse watch's pending steps (one read
        of the device each). Raises the error of the first step that went bad."""
        bad = self.pipeline.nonfinite_error()
        due, self._collapse_due = self._collapse_due, []
        values = host_values({f"{name}{i}": value for i, (_, psnr, loss, _, _) in enumerate(due)
                              for name, value in (("psnr", psnr), ("loss", loss))})
        for i, (step, _, _, restart, view) in enumerate(due):
            if bad is not None and bad.step <= step:
                break  # that step stopped the run before the watch saw it
            reason = self.collapse.update(step, values[f"psnr{i}"], values[f"loss{i}"], restart=restart, view=view)
            if reason is not None:
                raise CollapseError(f"step {step}: {reason}. Training stopped; {self.last_good()}")
        self._raise_if_nonfinite(bad)

    def after_failed_step(self, err: BaseException) -> None:
        """A step after the run went non-finite may fail for that reason (a strategy's draw from
        NaN weights): the step that first went non-finite is the one to report, not ``err``."""
        self._raise_if_nonfinite(self.pipeline.nonfinite_error(), cause=err)

    def _raise_if_nonfinite(self, bad: NonFiniteError | None, cause: BaseException | None = None) -> None:
        """Raise ``bad``, the pipeline's error of the first step whose loss or parameters went
        non-finite, as the run's error (None: nothing went non-finite)."""
        if bad is not None:
            raise NonFiniteError(f"{bad} (a learning rate too high, or non-finite values in the data?). "
                                 f"Training stopped; {self.last_good()}", bad.step) from (cause or bad)

    def last_good(self) -> str:
        """Where the run can be taken up again, for error messages."""
        checkpoint = self.last_checkpoint()
        if checkpoint is None:
            return "no checkpoint was written yet"
        return f"the last good checkpoint is {checkpoint}"
