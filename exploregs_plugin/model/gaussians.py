"""Gaussian scene model: parameters, initialisation, and the camera-level render call."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

import torch
from torch import Tensor, nn

from exploregs_plugin.cameras import Camera
from exploregs_plugin.model.neighbours import knn_mean_distance
from exploregs_plugin.model.optim import ParamGroup
from exploregs_plugin.rasterizer import RasterSettings, rasterize
from exploregs_plugin.rasterizer.sh import SH_C0, rgb_to_sh0  # noqa: F401 (SH_C0: the colour convention)

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


@dataclass
class GaussianModelConfig:
    """How the Gaussian set is initialised and rendered."""

    sh_degree: int = 3
    """Largest spherical-harmonics degree (0-3)."""
    init_opacity: float = 0.1
    """Opacity of every initial Gaussian."""
    init_scale: float = 1.0
    """Initial scale = this x mean distance to the 3 nearest neighbouring points."""
    raster: RasterSettings = field(default_factory=RasterSettings)
    """Rasterizer constants."""

    def setup(
        self,
        points: Tensor | None,
        points_rgb: Tensor | None,
        seed: int = 0,
    ) -> "GaussianModel":
        """points: [P, 3] initial means; points_rgb: [P, 3] colours in [0, 1] (None: grey);
        ``seed``: the run's seed, for models that draw initial values (the static one draws none)."""
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {self.sh_degree}")
        if not 0.0 < self.init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        if points is None or points.shape[0] == 0:
            # the datamanager gives random points where a dataset has none (--datamanager.random-init)
            raise ValueError("the Gaussian model needs initial points, and the dataset gave none")
        means = points.float()
        rgb = points_rgb.float() if points_rgb is not None else torch.full_like(means, 0.5)
        params = init_params(means, rgb, self.sh_degree, self.init_opacity, self.init_scale)
        return GaussianModel(self, params)


def init_params(
    means: Tensor, rgb: Tensor, sh_degree: int, opacity: float, scale_mult: float
) -> nn.ParameterDict:
    """3DGS initialisation: isotropic scale from the 3-NN mean distance (so the rotation is
    irrelevant and starts as the identity), opacity ``opacity``, SH DC from the point colour.

    means: [N, 3], rgb: [N, 3] in [0, 1].
    """
    n = means.shape[0]
    if not torch.isfinite(means).all():
        raise ValueError("initial points contain non-finite coordinates")
    dist = knn_mean_distance(means)
    # Coincident points would give log(0): floor at a small fraction of the typical spacing.
    positive = dist[dist > 0]
    floor = float(positive.median()) * 1e-3 if positive.numel() else 1e-3
    dist = dist.clamp_min(max(floor, 1e-7))
    log_scales = torch.log(dist * scale_mult).unsqueeze(1).repeat(1, 3)
    quats = torch.zeros(n, 4, device=means.device)
    quats[:, 0] = 1.0
    logit = math.log(opacity / (1.0 - opacity))
    n_rest = (sh_degree + 1) ** 2 - 1
    return nn.ParameterDict(
        {
            "means": nn.Parameter(means.clone().float()),
            "scales": nn.Parameter(log_scales.float()),
            "quats": nn.Parameter(quats),
            "opacities": nn.Parameter(torch.full((n,), logit, device=means.device)),
            "sh0": nn.Parameter(rgb_to_sh0(rgb.clamp(0.0, 1.0).float())),
            "shN": nn.Parameter(torch.zeros(n, n_rest, 3, device=means.device)),
        }
    )


class ModelPart(nn.Module):
    """A trained part of a model beside the Gaussians' rows (a dynamic model's deformation field):
    its parameter groups, each with its learning-rate schedule, which join the Gaussians' Adams in
    the run's ``OptimizerSet``; what it does before each step; its regulariser. Its parameters and
    buffers (``state_dict``) go into checkpoints. A static model has no parts."""

    def param_groups(self, scene_extent: float, max_steps: int, lr_scale: float = 1.0) -> list[ParamGroup]:
        """Every trained tensor of the part in a group with its schedule (x scene extent, x batch factor)."""
        raise NotImplementedError(f"{type(self).__name__} must say how its parameters are trained")

    def begin_step(self, step: int, max_steps: int) -> None:
        """Called before each training step (the deformation ends its static warm-up here)."""

    def regularization_loss(self) -> Tensor | None:
        """The part's regulariser, added once per step (None: none)."""
        return None


class GaussianModel(nn.Module):
    """Holds the Gaussian parameters (raw, unactivated) and renders them from a camera; a model of
    a dynamic scene adds its trained parts (``parts``: name -> :class:`ModelPart`)."""

    def __init__(self, config: GaussianModelConfig, params: nn.ParameterDict,
                 parts: Mapping[str, ModelPart] | None = None) -> None:
        super().__init__()
        self.config = config
        self.params = params
        self.parts = nn.ModuleDict(dict(parts or {}))

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    def params_at(self, time: float | None) -> Mapping[str, Tensor]:
        """The raw parameters to render at ``time``: a static scene's are the same at every time."""
        return self.params

    # The model's parts, all of them in turn (none for a static scene).
    def part_parameters(self) -> list[tuple[str, nn.Parameter]]:
        """Named parameters trained beside the Gaussians' rows ("<part>.<parameter>")."""
        return [(f"{name}.{key}", p) for name, part in self.parts.items() for key, p in part.named_parameters()]

    def part_param_groups(self, scene_extent: float, max_steps: int, lr_scale: float = 1.0) -> list[ParamGroup]:
        """Every part's parameter groups, in the order of the parts."""
        return [group for part in self.parts.values() for group in part.param_groups(scene_extent, max_steps, lr_scale)]

    def begin_step(self, step: int, max_steps: int) -> None:
        for part in self.parts.values():
            part.begin_step(step, max_steps)

    def regularization_loss(self) -> Tensor | None:
        """The sum of the parts' regularisers (None when no part has one)."""
        terms = [term for term in (part.regularization_loss() for part in self.parts.values()) if term is not None]
        return sum(terms[1:], terms[0]) if terms else None

    def parts_state(self) -> dict[str, dict[str, Tensor]]:
        """A copy of every part's parameters and buffers, for a checkpoint."""
        return {name: {k: v.detach().clone() for k, v in part.state_dict().items()} for name, part in self.parts.items()}

    def load_parts_state(self, state: Mapping[str, Mapping[str, Tensor]]) -> None:
        """Copy :meth:`parts_state` into the parts' own tensors (on their device)."""
        if set(state) != set(self.parts):
            raise ValueError(f"the checkpoint holds the model parts {sorted(state)}, this model has {sorted(self.parts)}")
        for name, part in self.parts.items():
            part.load_state_dict(dict(state[name]))

    def render(
        self,
        camera: Camera,
        sh_degree: int | None = None,
        background: Tensor | None = None,
        visibility_stats: bool = False,
    ) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Render from ``camera`` (at its time, for a dynamic scene): image [H, W, 3], alpha
        [H, W, 1], depth [H, W, 1], info; with ``visibility_stats``, the info's per-Gaussian
        visibility statistics too, whatever the config asks (the same image: they are sums kept
        beside it)."""
        return render_params(
            self.params_at(camera.time), camera, sh_degree if sh_degree is not None else self.config.sh_degree,
            background, self.raster_settings(visibility_stats),
        )

    def raster_settings(self, visibility_stats: bool = False) -> RasterSettings:
        """The config's renderer settings, with the visibility statistics asked for where given."""
        settings = self.config.raster
        return replace(settings, visibility_stats=True) if visibility_stats and not settings.visibility_stats else settings


def activate(params: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(means, quats, scales, opacities, sh [N, K, 3]) as every rasterizer takes them.

    scales = exp(log-scales), opacities = sigmoid(logits), sh = [sh0 | shN] along the coefficient
    axis; means and quats pass through (the rasterizer normalises quaternions). The results stay in
    the autograd graph: a caller that only reads them calls this under ``torch.no_grad()``.
    """
    return (*activate_geometry(params), torch.cat([params["sh0"], params["shN"]], dim=1))


def activate_geometry(params: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(means, quats, scales, opacities) of :func:`activate`, without the SH coefficients."""
    return params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"])


def activate_detached(params: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """:func:`activate` cut from the autograd graph, for readers of a model (analysis, benchmarks).

    ``no_grad`` keeps exp/sigmoid/cat out of the graph; ``detach`` is still needed because means and
    quats pass through :func:`activate` as the parameters themselves."""
    with torch.no_grad():
        return tuple(t.detach() for t in activate(params))  # type: ignore[return-value]


def render_params(
    params: Mapping[str, Tensor],
    camera: Camera,
    sh_degree: int,
    background: Tensor | None,
    settings: RasterSettings | None = None,
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Activate raw parameters and rasterize them (shared by the model, viewer and exports). The SH
    coefficients go as the pair (sh0, shN): the compiled kernels read both where they are, and only
    the other renderers concatenate them (about 1.5 ms of a 60 ms step at 20,000 Gaussians of degree
    3: the [N, 16, 3] copy and the copies of its gradient's two slices)."""
    return rasterize(*activate_geometry(params), (params["sh0"], params["shN"]), camera, sh_degree=sh_degree,
                     background=background, settings=settings)


def render_camera(
    params: Mapping[str, Tensor],
    camera: Camera,
    sh_degree: int,
    background: Tensor | None,
    settings: RasterSettings | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render raw parameters from ``camera`` without gradients, as numpy on the host:
    image [H, W, 3], alpha [H, W], depth [H, W]."""
    with torch.no_grad():
        image, alpha, depth, _ = render_params(params, camera, sh_degree, background, settings=settings)
    return (image.float().cpu().numpy(), alpha[..., 0].float().cpu().numpy(),
            depth[..., 0].float().cpu().numpy())
