"""The pipeline: datamanager + model + optimizers + strategy, and one training step."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor, nn

from exploregs_plugin.engine import count_trial, final_weights
from exploregs_plugin.data import DataManagerConfig
from exploregs_plugin.runtime.device import make_generator, restore_generator, to_device
from exploregs_plugin.runtime.distributed import World
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.model.gaussians import render_params
from exploregs_plugin.engine.loss_terms import DepthTerm, LossTerm, PhotometricTerm, ViewLossInput, view_loss
from exploregs_plugin.model.losses import VIEW_PSNR, DepthSpace, pooled_psnr, psnr_on_device
from exploregs_plugin.engine.nonfinite import NonFiniteError, NonFiniteWatch
from exploregs_plugin.model.optim import Optimizer, OptimizerConfig, OptimizerSet, batch_betas, batch_lr_scale
from exploregs_plugin.strategies.observation import ViewError, ViewObservation, observe_render
from exploregs_plugin.rasterizer import BackendError, backend_problem, resolve_backend
from exploregs_plugin.rasterizer.composite import single_threaded_ops
from exploregs_plugin.schedule import Schedule
from exploregs_plugin.strategies import DefaultStrategy
from exploregs_plugin.strategies.count_rule import CHECK_VIEWS, MIN_VIEWS, VALIDATED, evenly_spread, held_out_indices
from exploregs_plugin.strategies.requirements import ABSOLUTE_GRADIENT, VIEW_ERRORS, VISIBILITY_STATS


def gather_observations(world: World, views: list[ViewObservation], n: int,
                        absolute: bool = False) -> list[ViewObservation]:
    """Every rank's views, in the order of the global batch, as the strategies read them.

    Each observation keeps what the densification statistics need: the gradient of its 2D means
    (``means2d_grad`` [N, 2], None where none reached them), ``radii`` and (when the renderer
    made it) ``visibility`` [N, 3], ``camera_center`` [3], its size, ``n_cameras`` and, for
    guided exploration, its error map; with ``absolute`` (the strategy requires
    ``ABSOLUTE_GRADIENT``) also the absolute gradient sums [N, 2]. Every rank gets the same bits,
    own views included, so every rank's strategy makes the same decisions. Tensors travel in
    all-gathers; only the error maps (guided exploration) are pickled."""
    device = views[0].radii.device
    kept = [view.screen_gradient() if view.gradient_kept() else None for view in views]
    grads = torch.stack([g if g is not None else torch.zeros(n, 2, device=device) for g in kept]).to(torch.float32)
    sums = None
    if absolute:
        own = [view.screen_gradient(absolute=True) if g is not None else None for view, g in zip(views, kept)]
        sums = torch.cat(world.all_gather(torch.stack(
            [a if a is not None else torch.zeros(n, 2, device=device) for a in own]).to(torch.float32)))
    # per view: has_grad, width, height, n_cameras, camera centre (float64 keeps the centre's bits)
    header = torch.stack([torch.cat([
        torch.tensor([float(g is not None), view.width, view.height, view.n_cameras], dtype=torch.float64, device=device),
        view.camera_center.detach().to(device, torch.float64).reshape(3)]) for view, g in zip(views, kept)])
    grads = torch.cat(world.all_gather(grads))
    radii = torch.cat(world.all_gather(torch.stack([view.radii.detach() for view in views])))
    visibility = None
    if views[0].visibility is not None:
        visibility = torch.cat(world.all_gather(torch.stack([view.visibility.detach() for view in views])))
    header = torch.cat(world.all_gather(header)).cpu()
    centers = header[:, 4:7].to(device, views[0].camera_center.dtype)
    errors = None
    if views[0].error is not None:
        local = [view.error.to("cpu") for view in views]
        errors = [error.to(device) for rank_errors in world.all_gather_object(local) for error in rank_errors]
    return [
        ViewObservation(
            width=int(width), height=int(height), radii=radii[i], camera_center=centers[i],
            means2d_grad=grads[i] if has_grad else None, n_cameras=int(n_cameras),
            means2d_absgrad=sums[i] if sums is not None and has_grad else None,
            downscale=views[0].downscale,  # one step, one coarse-to-fine level on every rank
            visibility=None if visibility is None else visibility[i], error=None if errors is None else errors[i],
        )
        for i, (has_grad, width, height, n_cameras) in enumerate(header[:, :4].tolist())
    ]


def resolve_batch_size(batch_size: int | None, world_size: int = 1) -> int:
    """The global batch: ``batch_size``, or one view per rank when unset; a multiple of the ranks."""
    batch = world_size if batch_size is None else int(batch_size)
    if batch < 1:
        raise ValueError(f"--batch-size must be >= 1, got {batch}")
    if batch % world_size:
        raise ValueError(f"--batch-size {batch} cannot be shared by {world_size} ranks: use a multiple "
                         f"of {world_size}")
    return batch


def renderer_for(model: GaussianModelConfig, requires: frozenset[str]) -> GaussianModelConfig:
    """The model's config with its renderer asked for what the strategy requires (its
    ``requirements()``): visibility statistics cost a second accumulation per pixel and the
    absolute gradient sums two more in the backward, so they are computed only for a strategy
    that reads them."""
    if VISIBILITY_STATS in requires and not model.raster.visibility_stats:
        model = replace(model, raster=replace(model.raster, visibility_stats=True))
    if ABSOLUTE_GRADIENT in requires and not model.raster.absgrad:
        model = replace(model, raster=replace(model.raster, absgrad=True))
    return model


def strategy_for_renderer(strategy: Any, model: GaussianModelConfig, device: torch.device) -> tuple[Any, list[str]]:
    """The strategy to train with on the renderer that ``model`` resolves to on ``device``, and
    the lines that say what changed: a strategy that reads the compositing-weight sums only for
    an option (Default's significance prune) runs without it on a renderer that has no such sums
    (gsplat's kernels), rather than falling back to a slower renderer."""
    if VISIBILITY_STATS not in strategy.requirements() or model.raster.visibility_stats:
        return strategy, []
    if resolve_backend(model.raster, device) != "gsplat":
        return strategy, []
    without = getattr(strategy, "without_visibility", lambda: None)()
    if without is None:
        return strategy, []  # required by the class: the backend check below says why it cannot run
    return without, [f"note: {type(strategy).__name__}'s significance prune is off: gsplat's kernels do not sum each "
                     f"Gaussian's compositing weight (--model.raster.backend cpp or torch do)"]


def strategy_for_views(strategy: Any, n_train: int, scene_name: str) -> tuple[Any, list[str]]:
    """The strategy to train with on ``n_train`` training views, and the line that says what
    changed: a count to be decided on held-out views (cap_max 'validated') needs at least
    ``MIN_VIEWS`` of them; a smaller capture gets the strategy's rule that reads the training views
    only (:meth:`Strategy.without_held_out_views`), not a refusal."""
    if getattr(strategy, "cap_max", None) != VALIDATED or held_out_indices(n_train):
        return strategy, []
    without, rule = strategy.without_held_out_views()
    return without, [f"count: {scene_name} has {n_train} training views, fewer than the {MIN_VIEWS} a count decided "
                     f"on held-out views needs; {rule} decides it instead"]


@dataclass
class PipelineConfig:
    """Everything a training step needs: data, model, optimizer, densification strategy, loss."""

    datamanager: DataManagerConfig = field(default_factory=DataManagerConfig)
    """Which dataset to load and how."""
    model: GaussianModelConfig = field(default_factory=GaussianModelConfig)
    """How the Gaussian set is initialised and rendered."""
    optim: OptimizerConfig = field(default_factory=OptimizerConfig)
    """3DGS learning rates (Kerbl et al. 2023 reference values)."""
    strategy: Any = field(default_factory=DefaultStrategy)
    """Densification / exploration strategy (its fields are set with --strategy.NAME)."""
    ssim_lambda: float = 0.2
    """Loss = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM)."""
    random_background: bool = False
    """Composite each training image on a random colour (needs images with an alpha channel)."""
    depth_loss_weight: float = 0.0
    """Weight of an L1 loss between rendered expected depth and the dataset's depth maps (0 = off)."""
    depth_loss_space: DepthSpace = "depth"
    """Compare depth ('depth', z) or inverse depth ('inverse', 1/z: far pixels weigh less)."""
    batch_size: int | None = None
    """Training views per step, shared among the ranks (a multiple of their number); unset: one
    per rank. The schedule counts images seen: B views per step take 1/B of the steps."""
    batch_rule: bool = True
    """With B > 1 views per step, learning rates x sqrt(B) and Adam's betas ^ B (Grendel's rule)."""

    def loss_terms(self) -> list[LossTerm]:
        """The per-view loss terms this config asks for, in the order they are summed (a pipeline
        variant may replace one, as the depth-degradation experiment does)."""
        terms: list[LossTerm] = [PhotometricTerm(self.ssim_lambda)]
        if self.depth_loss_weight > 0.0:
            terms.append(DepthTerm(self.depth_loss_weight, self.depth_loss_space))
        return terms

    def setup(self, schedule: Schedule, seed: int, device: torch.device | str = "cpu",
              world: World = World()) -> "Pipeline":
        return Pipeline(self, schedule, seed, torch.device(device), world)


class Pipeline:
    """Thin state holder; the maths lives in model, losses, rasterizer and strategies.

    Parameters, Adam state, strategy state and the run's generator live on ``device``; the
    datamanager keeps its images on the host, and each step moves its one view there."""

    def __init__(self, config: PipelineConfig, schedule: Schedule, seed: int,
                 device: torch.device = torch.device("cpu"), world: World = World()) -> None:
        self.config = config
        self.schedule = schedule
        self.device = device
        self.world = world
        self.batch_size = resolve_batch_size(config.batch_size, world.size)
        if schedule.views_per_step != self.batch_size:
            raise ValueError(f"the schedule was resolved for {schedule.views_per_step} views per step but the "
                             f"batch has {self.batch_size}: resolve it with views_per_step={self.batch_size}")
        self.lr_scale = batch_lr_scale(self.batch_size, config.batch_rule)
        strategy_config, notes = strategy_for_renderer(config.strategy, config.model, device)
        for note in notes if world.is_main else ():
            print(note, flush=True)
        self.requires = strategy_config.requirements()
        model_config = renderer_for(config.model, self.requires)
        problem = backend_problem(model_config.raster, device)
        if problem is not None:
            raise BackendError(problem)
        self.generator = make_generator(device, seed)
        self.generator_restored = True  # False after loading a generator state of another device type
        self.nonfinite = NonFiniteWatch()  # read by the trainer at its read points (nonfinite_error)
        # One run seed drives everything, the camera order and random initial points included.
        self.datamanager = replace(config.datamanager, seed=seed).setup()
        dm = self.datamanager
        self.scene_extent = float(dm.scene_extent)
        self.background = dm.background.to(device)
        self.model = model_config.setup(*to_device((dm.points, dm.points_rgb), device), seed=seed)
        # the end-of-run cut needs each Gaussian's compositing weight summed: gsplat's kernels do not
        self.sums_weights = resolve_backend(model_config.raster, device) != "gsplat"
        self.optim = self._make_optimizer_set()
        self.loss_terms = config.loss_terms()
        strategy_config, notes = strategy_for_views(strategy_config, len(dm.train_cameras), dm.scene_name)
        for note in notes if world.is_main else ():
            print(note, flush=True)
        self.strategy = strategy_config.setup(schedule)
        self.strategy.check_sanity(self.model.params, self.optimizers)
        # Scene centre = mean training-camera centre (seeding measures distances from it).
        centers = torch.stack([camera.camera_center for camera in dm.train_cameras])
        self.strategy_state = to_device(self.strategy.initialize_state(
            scene_scale=self.scene_extent, scene_center=centers.mean(dim=0)), device)
        if self.strategy.holds_out_views(self.strategy_state, 0):
            self._hold_out_views()
        if config.random_background and not dm.has_alpha:
            raise ValueError("random_background needs a dataset whose images have an alpha channel")
        # --datamanager.background random asks for the same as random_background
        self.random_background = config.random_background or dm.random_background
        if dm.is_dynamic and not self.model.parts and world.is_main:
            print(f"note: {dm.scene_name}: the frames carry times (a dynamic scene), which this static method "
                  "ignores: it trains every frame as one still scene (the exploregs-4d-* methods use them)", flush=True)

    def _make_optimizer_set(self) -> OptimizerSet:
        """The Gaussians' Adams (the strategies re-index them with the rows) and the parameter
        groups of the model's parts (a deformation field's, out of the strategies' reach), stepped as one."""
        gaussians = self.config.optim.setup(self.params, self.scene_extent, self.batch_size, self.config.batch_rule)
        groups = self.model.part_param_groups(self.scene_extent, self.schedule.max_steps, self.lr_scale)
        return OptimizerSet(gaussians, self.means_lr_at, groups, batch_betas(self.batch_size, self.config.batch_rule))

    @property
    def optimizers(self) -> dict[str, Optimizer]:
        """One Adam per Gaussian parameter name: what the strategies see."""
        return self.optim.gaussians

    def trained_tensors(self) -> list[tuple[str, nn.Parameter]]:
        """Every trained parameter by name: the Gaussians' and the model's parts' (a deformation field's)."""
        return list(self.params.items()) + self.model.part_parameters()

    def exploration_summary(self) -> dict[str, int]:
        """Current totals a strategy reports about its exploration (e.g. seeds alive)."""
        return dict(self.strategy.exploration_summary(self.strategy_state))

    @property
    def params(self) -> nn.ParameterDict:
        return self.model.params

    def sh_degree_at(self, step: int) -> int:
        return min(step // self.schedule.sh_degree_interval, self.model.config.sh_degree)

    def means_lr_at(self, step: int) -> float:
        return self.config.optim.means_lr_at(step, self.schedule.max_steps, self.scene_extent) * self.lr_scale

    def train_step(self, step: int) -> dict[str, Any]:
        """Render the step's views, step the optimizers, then let the strategy change the set.

        A step takes ``batch_size`` training views (the global batch; each rank of a
        data-parallel run renders its share) and minimises their mean loss. Each view is
        back-propagated on its own (one view's graph in memory at a time), the ranks' gradients
        are summed with one all-reduce, and the strategy sees every view's observations.

        Nothing here reads the device: the step's ``loss``, ``psnr`` and ``terms`` are 0-dim
        float64 tensors on it, and a non-finite loss or parameter is recorded there
        (:attr:`nonfinite`); the trainer reads both where they are needed (:meth:`nonfinite_error`).

        torch's own operators run on one thread here; the compiled kernels (projection, SH,
        compositing, the loss, the non-finite watch) and the compositor's workers take the run's
        thread count explicitly (``thread_budget``). Why: torch cuts an elementwise operator over
        more than 32,768 elements into one chunk per thread, and each chunk's last elements go
        through the scalar sigmoid, exp, ... whose last bit can differ from the vectorised one; the
        cut moves with the thread count, and a run with more Gaussians than that would part ways on
        1 and 2 threads. On a GPU the step's operators run there; the host's (the data path) keep
        their threads."""
        if self.device.type != "cpu":
            return self._train_step(step)
        with single_threaded_ops():
            return self._train_step(step)

    def _train_step(self, step: int) -> dict[str, Any]:
        self.model.begin_step(step, self.schedule.max_steps)
        in_window = self._final_window_draws(step)  # before the draw: which of it the next cut reads
        indices = self.datamanager.next_train_indices(self.batch_size)  # every rank draws the whole batch
        # the backgrounds too, so that the run's generator advances alike on every rank
        backgrounds = [self._step_background() for _ in indices]
        share = self.batch_size // self.world.size
        mine = range(self.world.rank * share, (self.world.rank + 1) * share)
        totals: dict[str, Tensor] = {}
        views = [self._train_view(step, indices[p], backgrounds[p], p == mine.start, totals, any(in_window))
                 for p in mine]
        views = self._step_observations(views, totals)
        for view, counted, index in zip(views, in_window, indices):  # every view of the global batch, on every rank
            if counted:
                final_weights.add_window_view(self.strategy_state, view.visibility, index)
        self.nonfinite.loss(step, totals)
        means_lr = self._optimizer_step(step)
        self.check_finite(step)
        decided = self.strategy.count_decision(self.strategy_state)
        counts = self.strategy.step_post_backward(
            self.params, self.optimizers, self.strategy_state, step, views, lr=means_lr,
            generator=self.generator,
            # the data loss, a tensor as summed (MCMC's cap_max auto reads it once per refinement)
            loss=totals["loss"] - totals["reg"] if "reg" in totals else totals["loss"],
        )
        notes = self._count_note(decided)
        trial = self.strategy.count_trial_due(self.strategy_state, step, self.model.num_gaussians)
        if trial is not None:  # MCMC's cap_max 'validated', at its last refinement
            count_trial.decide(self, step, trial)
        notes += self._return_held_views(step)
        if step + 1 == self._next_cut(step):  # the settled cut, or the end-of-run cut
            cut, line = self._final_cut(step, last=step + 1 == self.schedule.max_steps)
            counts = {**(counts or {}), "pruned": (counts or {}).get("pruned", 0) + cut}  # the run's totals balance
            notes += line
        return {
            "loss": totals["loss"],
            "terms": {k: v for k, v in totals.items() if k not in ("loss", "psnr")},
            "psnr": totals["psnr"],
            "views": tuple(int(i) for i in indices),
            "counts": dict(counts or {}),
            "means_lr": means_lr,
            "notes": notes,
        }

    def _final_cut(self, step: int, last: bool = True) -> tuple[int, list[str]]:
        """After the run's last step, before its final evaluation (or, ``last`` False, after
        ``step`` where the strategy's settled cut comes: :meth:`Strategy.settled_cut_step`): the
        strategy's cut by each Gaussian's compositing weight over every training view (summed by
        the training renders of the epoch before it, or one pass without gradients;
        :meth:`Strategy.final_cut`); returns the rows removed and the count line it writes. None
        for a dynamic model (its Gaussians move with time) or on gsplat's kernels, which do not sum
        the weights (a note, after the last step)."""
        share = self.strategy.final_cut_share()
        if not self._final_cut_runs():
            return 0, []
        if not self.sums_weights:
            return 0, [f"note: the end-of-run cut (--strategy.final-weight-share {share:g}) is off: gsplat's "
                       f"kernels do not sum each Gaussian's compositing weight"] if last else []
        views = self._final_cut_views()
        totals = final_weights.window_totals(self.strategy_state, views)
        missing = None if self.datamanager.held_out else final_weights.missing_views(self.strategy_state, views)
        if totals is None and missing:  # the window opened inside its epoch: render the views it lacks
            final_weights.complete_window(self.strategy_state, count_trial.views_visibility(self, missing), missing)
            totals = final_weights.window_totals(self.strategy_state, views)
        if totals is None:  # no window after growth ended: render every view once more
            totals = count_trial.training_visibility(self)
        checked = evenly_spread(len(self.datamanager.train_cameras), CHECK_VIEWS)
        cut = self.strategy.final_cut(self.params, self.optimizers, self.strategy_state, totals, step, last=last,
                                      score_without=lambda rows: self.view_psnrs(checked, step, without=rows))
        final_weights.clear_window(self.strategy_state)
        return cut, [self.strategy.count_decision(self.strategy_state)]

    def _final_cut_runs(self) -> bool:
        """Whether the end-of-run cut applies: a strategy with a share to cut, a static model."""
        return self.strategy.final_cut_share() > 0.0 and not self.model.parts

    def _final_cut_views(self) -> int:
        """The training views whose weights the end-of-run cut sums: those still trained on (a
        held-out view must not choose what is kept; at the last step none is held out)."""
        return len(self.datamanager.train_cameras) - len(self.datamanager.held_out)

    def _settled_cut_step(self) -> int | None:
        """The count of steps after which the strategy's cut also runs (:meth:`Strategy.settled_cut_step`),
        where the end-of-run cut runs at all (:meth:`_final_cut_runs`); None: no such cut."""
        return self.strategy.settled_cut_step(self.schedule.max_steps) if self._final_cut_runs() else None

    def _next_cut(self, step: int) -> int:
        """The count of steps after which the next cut at or after ``step`` comes: the settled
        cut's, or the run's (the cut after the last step)."""
        settled = self._settled_cut_step()
        return settled if settled is not None and step < settled else self.schedule.max_steps

    def _final_window_draws(self, step: int) -> list[bool]:
        """Which of this step's draws are views of the complete epoch that ends before the next
        cut (:meth:`_next_cut`), whose training renders sum that cut's weights
        (:mod:`final_weights`): none before the strategy stops growing (its rows must be the
        cut's), below full size, or where no cut comes (or gsplat's kernels, which do not sum the
        weights)."""
        batch = self.batch_size
        if (not self._final_cut_runs() or not self.sums_weights or step < self.strategy.refine_stop_iter
                or self.schedule.downscale_at(step) != 1):
            return [False] * batch
        return self.datamanager.last_epoch_draws(batch, (self._next_cut(step) - step) * batch)

    def final_cut_note(self, step: int) -> str | None:
        """The line said before ``step`` when a cut comes after it (the end-of-run cut after the
        last step, or the settled cut): the cut renders ``CHECK_VIEWS``
        training views per share it tries (and, where its window holds part of an epoch, the views it
        lacks; where it has none, every training view once more), which on a large capture takes minutes
        (220 views at 800 x 533: about 143 s with the views' pass, docs/strategies.md) that the
        progress bar would otherwise spend silent."""
        if step + 1 != self._next_cut(step) or not self._final_cut_runs():
            return None
        settled = step + 1 < self.schedule.max_steps
        if not self.sums_weights:
            return None  # no cut: the step says so after it
        views = self._final_cut_views()
        summed = final_weights.window_views(self.strategy_state) + sum(self._final_window_draws(step))
        completes = summed > 0 and not self.datamanager.held_out and (
            final_weights.window_views(self.strategy_state) == 0
            or final_weights.missing_views(self.strategy_state, views) is not None)
        how = (f"by their weights in the last epoch's renders of the {views} training views" if summed == views
               else f"by their weights in the last epoch's renders of {summed} of the {views} training views "
                    f"and one render of each of the other {views - summed}" if completes
               else f"over the {views} training views (one render each)")
        if settled:
            return (f"after step {step + 1}: the cut weighs the {self.model.num_gaussians:,} Gaussians {how}; the rest "
                    f"of the run trains those it keeps")
        return (f"after step {step + 1}: the end-of-run cut weighs the {self.model.num_gaussians:,} Gaussians {how} "
                f"before the final evaluation")

    def _count_note(self, before: str) -> list[str]:
        """The strategy's line on the count it kept, once, at the step it was written (a count
        decided on held-out views is said when they return, by :meth:`_return_held_views`)."""
        after = self.strategy.count_decision(self.strategy_state)
        return [after] if after and after != before and not self.datamanager.held_out else []

    def _hold_out_views(self) -> None:
        """Keep :func:`held_out_indices` of the training views out of training while the strategy
        decides (:meth:`Strategy.holds_out_views`)."""
        n = len(self.datamanager.train_cameras)
        held = held_out_indices(n)
        if not held:
            raise ValueError(f"{type(self.strategy).__name__}: a count decided on held-out views needs at least "
                             f"{MIN_VIEWS} training views; {self.datamanager.scene_name} has {n} (give --strategy.cap-max "
                             f"a number)")
        self.datamanager.hold_out(held)

    def held_out_psnrs(self, step: int) -> list[float]:
        """PSNR (dB) of each held-out training view (in the datamanager's order): :meth:`view_psnrs`."""
        return self.view_psnrs(self.datamanager.held_out, step)

    def view_psnrs(self, indices: list[int], step: int, without: Tensor | None = None) -> list[float]:
        """PSNR (dB) of each of these training views, in order, rendered without gradients at the
        step's SH degree on the dataset's background, without the rows of ``without`` ([N] bool)
        where given (a static model: the cut's check): one read of the device."""
        params = None
        if without is not None:
            params = {k: v.detach()[~without] for k, v in self.params.items()}
        squared = []
        with torch.no_grad():
            for index in indices:
                camera, target, _ = self.datamanager.train_item(index, self.device)
                if params is None:
                    image = self.model.render(camera, self.sh_degree_at(step), self.background)[0]
                else:
                    image = render_params(params, camera, self.sh_degree_at(step), self.background,
                                          self.model.config.raster)[0]
                squared.append((((image.double() - target.double()) ** 2).sum(), target.numel()))
        values = torch.stack([s for s, _ in squared]).tolist() if squared else []
        return [pooled_psnr(value, count) for value, (_, count) in zip(values, squared)]

    def _return_held_views(self, step: int) -> list[str]:
        """Once the strategy no longer holds views out, they return to training; the line that
        says so (and why growth stopped) is returned for the trainer to print."""
        if not self.datamanager.held_out or self.strategy.holds_out_views(self.strategy_state, step + 1):
            return []
        held = len(self.datamanager.held_out)
        self.datamanager.return_held()
        reason = self.strategy.count_decision(self.strategy_state) or (
            f"the refinements ended before a count was decided ({self.model.num_gaussians:,} Gaussians at step "
            f"{step + 1})")
        return [f"{reason}; the {held} held-out views return to training"]

    def _train_view(self, step: int, index: int, background: Tensor, first: bool,
                    totals: dict[str, Tensor], visibility_stats: bool = False) -> ViewObservation:
        """Render one training view, back-propagate its share of the step's loss, add its values
        to ``totals``; returns what the strategy observes of this view (with ``visibility_stats``,
        the renderer's visibility statistics too)."""
        batch = self.batch_size
        downscale = self.schedule.downscale_at(step)  # coarse-to-fine: the step's level (1 = full size)
        camera, target, extras = self.datamanager.train_item(index, self.device, downscale)
        target = self._target_on(background, target, extras)
        # the keyword only when asked: a model variant's render may take the three arguments alone
        asked = {"visibility_stats": True} if visibility_stats else {}
        image, _, depth, info = self.model.render(camera, self.sh_degree_at(step), background, **asked)
        error = None
        if VIEW_ERRORS in self.requires:  # guided exploration: where this view is still wrong
            error = ViewError(index, camera.viewmat, camera.K, target, (image.detach() - target).abs().mean(dim=-1))
        # n_cameras = B: the strategies undo the 1/B of the batch's mean loss in the 2D-mean gradients
        view = observe_render(info, n_cameras=batch, error=error, downscale=downscale)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, step, view)
        loss, terms = view_loss(self.loss_terms, ViewLossInput(image, target, depth, extras, index))
        view_psnr = terms.pop(VIEW_PSNR, None)  # the loss kernel's, computed in its pass (on a CPU)
        if batch > 1:
            loss = loss / batch  # the batch's mean loss (its gradient is the mean of the views')
            terms = {k: v / batch for k, v in terms.items()}
        if first and self.world.is_main:  # the regularisers enter once per step
            reg = self._regularisers()
            loss = loss + reg
            terms["reg"] = reg.detach()
        loss.backward()
        # the totals stay on the device (float64): the trainer reads them where it logs them; the
        # PSNR (float64) goes through float32 first, as it always has. Without grad recording, no
        # detach is needed, and a 0-dim value is not reshaped: each operator costs a dispatch.
        with torch.no_grad():
            if view_psnr is None:
                view_psnr = psnr_on_device(image, target)
            psnr = (view_psnr / batch if batch > 1 else view_psnr).to(torch.float32)
            for key, value in {"loss": loss, "psnr": psnr, **terms}.items():
                value = (value.reshape(()) if value.dim() else value).to(torch.float64)
                totals[key] = totals[key] + value if key in totals else value
        return view

    def _target_on(self, background: Tensor, target: Tensor, extras: dict[str, Any]) -> Tensor:
        """The training image on this step's background. The dataset composited it on b0 with
        alpha a: t = c a + b0 (1 - a), so on a new background b it is t + (b - b0)(1 - a)."""
        if not self.random_background:
            return target
        return target + (background - self.background) * (1.0 - extras["alpha"].to(self.device))

    def _regularisers(self) -> Tensor:
        """The strategy's regulariser (MCMC's) plus the model's (a deformation field's planes)."""
        reg = self.strategy.regularization_loss(self.params)
        model_reg = self.model.regularization_loss()
        return reg if model_reg is None else reg + model_reg

    def _step_observations(self, views: list[ViewObservation], totals: dict[str, Tensor]) -> list[ViewObservation]:
        """What the strategy observes of the step: every view in the order of the global batch;
        across ranks, the gradients and totals are summed first (one all-reduce) and the
        observations gathered (the one place they are reduced)."""
        if self.world.is_distributed:
            totals.setdefault("reg", torch.zeros((), dtype=torch.float64))  # rank 0 adds it: same keys everywhere
            self._all_reduce_gradients(totals)
            return gather_observations(self.world, views, self.model.num_gaussians,
                                       absolute=ABSOLUTE_GRADIENT in self.requires)
        return views

    def _optimizer_step(self, step: int) -> float:
        """Step every optimizer at this step's learning rates; returns the means' learning rate."""
        return self.optim.step(step)

    def _step_background(self) -> Tensor:
        if not self.random_background:
            return self.background
        return torch.rand(3, generator=self.generator, device=self.device)

    def _all_reduce_gradients(self, totals: dict[str, Tensor]) -> None:
        """Sum the parameters' gradients and the step's loss terms over the ranks (one all-reduce).

        A parameter without a gradient on every rank keeps none (Adam then skips it, as it does
        in one process); one that has a gradient on some rank gets zeros elsewhere."""
        tensors = [p for _, p in self.trained_tensors()]
        present = torch.tensor([p.grad is not None for p in tensors], dtype=torch.float32, device=self.device)
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in tensors]
        keys = sorted(totals)
        scalars = torch.stack([totals[k] for k in keys]).to(self.device, torch.float32)
        flat = [g.to(torch.float32) for g in grads] + [present, scalars]
        self.world.all_reduce_sum_(flat)
        for param, grad, summed, seen in zip(tensors, grads, flat, flat[-2].tolist()):  # one read
            param.grad = summed.to(grad.dtype) if seen > 0 else None
        for k, value in zip(keys, flat[-1]):
            totals[k] = value.to(torch.float64)

    def check_finite(self, step: int) -> None:
        """Record, on the device, whether a trained tensor went non-finite at ``step`` (no read:
        :meth:`nonfinite_error` reads the record)."""
        self.nonfinite.params(step, self.trained_tensors(), self.model.num_gaussians)

    def nonfinite_error(self) -> NonFiniteError | None:
        """The error of the first step whose loss or parameters went non-finite, or None (one read
        of the device)."""
        return self.nonfinite.error()

    def state_dict(self) -> dict[str, Any]:
        state = {
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            **self.optim.state_dict(),  # "optimizers" and, with model parts, "field_optimizer"
            "strategy_state": self.strategy_state,
            "generator": self.generator.get_state(),
            "datamanager": self.datamanager.state_dict(),
        }
        if self.model.parts:  # a dynamic model: its deformation field
            state["parts"] = self.model.parts_state()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint, saved on any device, onto this pipeline's device. The Gaussian
        count may differ from the fresh initialisation."""
        missing = set(self.params.keys()) - set(state["params"])
        if missing:
            raise ValueError(f"checkpoint lacks parameters {sorted(missing)}")
        for name, value in state["params"].items():
            self.params[name] = nn.Parameter(value.to(self.device, copy=True))
        # checkpoints made before models had parts hold the deformation field as "field"
        parts = state.get("parts", {"deformation": state["field"]} if "field" in state else {})
        if self.model.parts and not parts:
            raise ValueError("the checkpoint holds no deformation field: it was made by a static method")
        if parts and not self.model.parts:
            raise ValueError("the checkpoint holds a deformation field: load it with its dynamic (4D) method's config")
        self.model.load_parts_state(parts)  # copied into the parts' own tensors
        self.optim = self._make_optimizer_set()  # the Adams hold the loaded tensors
        self.optim.load_state_dict(state)  # Adam's moments follow their parameter's device
        self.strategy_state = to_device(state["strategy_state"], self.device)
        # a generator state from another device type cannot be loaded: the stream is then
        # reseeded from it (deterministic, not bit-identical to an uninterrupted run)
        self.generator_restored = restore_generator(self.generator, state["generator"])
        self.datamanager.load_state_dict(state["datamanager"])

