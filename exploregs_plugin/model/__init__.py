"""Gaussian scene model: parameters, initialisation, losses and optimizers."""

from exploregs_plugin.model.gaussians import (
    PARAM_NAMES,
    GaussianModel,
    GaussianModelConfig,
    render_params,
)

__all__ = ["PARAM_NAMES", "GaussianModel", "GaussianModelConfig", "render_params"]
