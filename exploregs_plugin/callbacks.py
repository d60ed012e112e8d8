"""Hooks into the training loop: the one way for the viewer, the branch-gradient logger and
analysis probes to act between training steps, so there is one loop (``Trainer.train``). The
caller passes callbacks to the Trainer, and a config adds those it asks for
(``TrainerConfig.callbacks``).

A callback overrides the hooks it needs; every hook has a default that does nothing. The
trainer is passed in (typed loosely here: this module sits below the trainer in the layers).
"""

from __future__ import annotations

from typing import Any


class TrainingCallback:
    """Called by :meth:`exploregs_plugin.engine.training_loop.Trainer.train`, in this order::

        on_train_start(trainer)                  # before the first step (start_step on resume)
        for each step:
            before_step(trainer, step)           # may block (the viewer's pause)
            ... one training step ...
            after_step(trainer, step + 1, stats) # steps completed; before evaluation/checkpoint
        on_train_end(trainer)                    # after the final evaluation and checkpoint
        close()                                  # always, also after an error or Ctrl-C

    Time spent in callbacks is not training time.
    """

    def on_train_start(self, trainer: Any) -> None:
        """Before the first step of this call to ``train``."""

    def before_step(self, trainer: Any, step: int) -> None:
        """Before step ``step`` (0-based)."""

    def after_step(self, trainer: Any, step: int, stats: dict[str, Any]) -> None:
        """After ``step`` steps completed; ``stats`` is what the pipeline's train_step returned."""

    def on_train_end(self, trainer: Any) -> None:
        """After the final evaluation and checkpoint."""

    def close(self) -> None:
        """Release what the callback holds (threads, servers); called once, whatever happened."""
