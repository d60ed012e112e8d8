"""The pipeline: datamanager + model + optimizers + strategy, and one training step."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor, nn

from exploregs_plugin.data import DataManagerConfig
from exploregs_plugin.device import make_generator, restore_generator, to_device
from exploregs_plugin.data.depth_supervision import DepthSupervisionConfig
from exploregs_plugin.model import GaussianModelConfig
from exploregs_plugin.model.losses import DepthSpace, depth_l1, photometric_loss, psnr
from exploregs_plugin.model.optim import OptimizerConfig, set_lr
from exploregs_plugin.rasterizer import BackendError, backend_problem
from exploregs_plugin.schedule import Schedule
from exploregs_plugin.strategies import DefaultStrategy


class NonFiniteError(RuntimeError):
    """Training produced a NaN or inf (in the loss or in a parameter)."""


@dataclass
class PipelineConfig:
    """Everything a training step needs: data, model, optimizer, densification strategy, loss."""

    datamanager: DataManagerConfig = field(default_factory=DataManagerConfig)
    model: GaussianModelConfig = field(default_factory=GaussianModelConfig)
    optim: OptimizerConfig = field(default_factory=OptimizerConfig)
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
    depth_supervision: DepthSupervisionConfig = field(default_factory=DepthSupervisionConfig)
    """Degrade the depth maps before the depth loss (noise, smooth bias) to play a monocular estimate."""

    def setup(self, schedule: Schedule, seed: int, device: torch.device | str = "cpu") -> "Pipeline":
        return Pipeline(self, schedule, seed, torch.device(device))


class Pipeline:
    """Thin state holder; the maths lives in model, losses, rasterizer and strategies.

    Parameters, Adam state, strategy state and the run's generator live on ``device``; the
    datamanager keeps its images on the host, and each step moves its one view there."""

    def __init__(self, config: PipelineConfig, schedule: Schedule, seed: int,
                 device: torch.device = torch.device("cpu")) -> None:
        self.config = config
        self.schedule = schedule
        self.device = device
        problem = backend_problem(config.model.raster, device)
        if problem is not None:
            raise BackendError(problem)
        self.generator = make_generator(device, seed)
        self.generator_restored = True  # False after loading a generator state of another device type
        # One run seed drives everything, the camera order and random initial points included.
        self.datamanager = replace(config.datamanager, seed=seed).setup()
        dm = self.datamanager
        self.scene_extent = float(dm.scene_extent)
        self.background = dm.background.to(device)
        self.model = config.model.setup(*to_device((dm.points, dm.points_rgb), device))
        self.optimizers = config.optim.setup(self.model.params, self.scene_extent)
        self.strategy = config.strategy.setup(schedule)
        self.strategy.check_sanity(self.model.params, self.optimizers)
        # Scene centre = mean training-camera centre (seeding measures distances from it).
        centers = torch.stack([camera.camera_center for camera in dm.train_cameras])
        self.strategy_state = to_device(self.strategy.initialize_state(
            scene_scale=self.scene_extent, scene_center=centers.mean(dim=0)), device)
        if config.random_background and not dm.has_alpha:
            raise ValueError("random_background needs a dataset whose images have an alpha channel")

    def exploration_summary(self) -> dict[str, int]:
        """Current totals a strategy reports about its exploration (e.g. seeds alive)."""
        return dict(self.strategy.exploration_summary(self.strategy_state))

    @property
    def params(self) -> nn.ParameterDict:
        return self.model.params

    def sh_degree_at(self, step: int) -> int:
        return min(step // self.schedule.sh_degree_interval, self.model.config.sh_degree)

    def means_lr_at(self, step: int) -> float:
        return self.config.optim.means_lr_at(step, self.schedule.max_steps, self.scene_extent)

    def train_step(self, step: int) -> dict[str, Any]:
        """Render one training view, step the optimizers, then let the strategy change the set."""
        index, camera, target, extras = self.datamanager.next_train()
        target = target.to(self.device, non_blocking=True)
        background = self.background
        if self.config.random_background:
            # The target was composited on the dataset background b0 with alpha a:
            # t = c a + b0 (1 - a), so on a new background b it is t + (b - b0)(1 - a).
            background = torch.rand(3, generator=self.generator, device=self.device)
            target = target + (background - self.background) * (1.0 - extras["alpha"].to(self.device))
        image, _, depth, info = self.model.render(camera, self.sh_degree_at(step), background)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, step, info)

        loss, terms = photometric_loss(image, target, self.config.ssim_lambda)
        if self.strategy.wants_view_errors:  # guided exploration: where this view is still wrong
            info["view"] = {"index": index, "viewmat": camera.viewmat, "K": camera.K, "target": target,
                            "error": (image.detach() - target).abs().mean(dim=-1)}
        if self.config.depth_loss_weight > 0.0:
            if "depth" not in extras:
                raise ValueError("depth_loss_weight > 0 but the dataset has no depth maps")
            gt_depth = self.config.depth_supervision.apply(extras["depth"], index).to(self.device)
            depth_term = depth_l1(depth, gt_depth, self.config.depth_loss_space)
            loss = loss + self.config.depth_loss_weight * depth_term
            terms["depth"] = depth_term.detach()
        reg = self.strategy.regularization_loss(self.params)
        loss = loss + reg
        terms["reg"] = reg.detach()
        if not math.isfinite(float(loss.detach())):
            raise NonFiniteError(f"step {step}: the loss is {float(loss.detach())} (terms: "
                                 + ", ".join(f"{k}={float(v):.4g}" for k, v in terms.items()) + ")")
        loss.backward()

        means_lr = self.means_lr_at(step)
        set_lr(self.optimizers["means"], means_lr)
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        self.check_finite(step)
        counts = self.strategy.step_post_backward(
            self.params, self.optimizers, self.strategy_state, step, info, lr=means_lr, generator=self.generator
        )
        return {
            "loss": float(loss.detach()),
            "terms": {k: float(v) for k, v in terms.items()},
            "psnr": psnr(image, target),
            "counts": dict(counts or {}),
            "means_lr": means_lr,
        }

    def check_finite(self, step: int) -> None:
        for name, p in self.params.items():
            # One reduction per tensor: NaN and inf propagate through a sum, so a finite sum
            # means finite entries. Only a non-finite sum (or float32 overflow of a large one)
            # pays for the element-wise scan.
            if p.numel() == 0 or bool(torch.isfinite(p.detach().sum())):
                continue
            bad = ~torch.isfinite(p.detach())
            if not bool(bad.any()):
                continue
            rows = int(bad.reshape(p.shape[0], -1).any(dim=1).sum()) if p.ndim else 1
            raise NonFiniteError(
                f"step {step}: parameter '{name}' has non-finite values in {rows} of {p.shape[0]} Gaussians"
            )

    def state_dict(self) -> dict[str, Any]:
        return {
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "strategy_state": self.strategy_state,
            "generator": self.generator.get_state(),
            "datamanager": self.datamanager.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a checkpoint, saved on any device, onto this pipeline's device. The Gaussian
        count may differ from the fresh initialisation."""
        missing = set(self.params.keys()) - set(state["params"])
        if missing:
            raise ValueError(f"checkpoint lacks parameters {sorted(missing)}")
        for name, value in state["params"].items():
            self.params[name] = nn.Parameter(value.to(self.device, copy=True))
        self.optimizers = self.config.optim.setup(self.params, self.scene_extent)
        for name, opt in self.optimizers.items():
            opt.load_state_dict(state["optimizers"][name])  # Adam's moments follow their parameter's device
        self.strategy_state = to_device(state["strategy_state"], self.device)
        # a generator state from another device type cannot be loaded: the stream is then
        # reseeded from it (deterministic, not bit-identical to an uninterrupted run)
        self.generator_restored = restore_generator(self.generator, state["generator"])
        self.datamanager.load_state_dict(state["datamanager"])

