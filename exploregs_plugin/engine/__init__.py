"""The training engine: the loop and what it drives and watches.

- ``trainer``: ``TrainerConfig``, every eg-train flag (what ``config.yml`` records); its
  ``setup()`` builds the ``Trainer`` of ``training_loop``, the one loop (steps, logging,
  evaluations, checkpoints, callbacks);
- ``pipeline``: datamanager + model + optimizers + strategy, ``Pipeline.train_step``; the training
  loss as a list of terms (``loss_terms``); the paired cut of ``cap_max validated``
  (``count_trial``);
- what watches a run: ``watches`` (the read points), ``collapse`` (a collapsing PSNR or loss),
  ``nonfinite`` (the first non-finite step, recorded on the device), ``stopping`` (signals at a
  step boundary), ``thread_follower`` (the thread count follows the idle CPUs);
- what a run writes: ``run_folder`` (its folder), ``run_logger`` (tensorboard and the console line).

A plugin takes the configs it composes from here: ``from exploregs_plugin.engine import
TrainerConfig, PipelineConfig`` (also ``Trainer`` and ``Pipeline``); they load on first use, so
importing one module of the engine does not import the rest.
"""

from __future__ import annotations

from exploregs_plugin.runtime.lazy_names import lazy_names

_PUBLIC = {"TrainerConfig": ".trainer", "Trainer": ".training_loop", "PipelineConfig": ".pipeline",
           "Pipeline": ".pipeline"}

__all__ = sorted(_PUBLIC)
__getattr__ = lazy_names(__name__, _PUBLIC)
