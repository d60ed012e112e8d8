"""nerfstudio's splatfacto with Random Seeding + Random Splitting: the method ``exploregs-splatfacto``.

Registered under nerfstudio's ``nerfstudio.method_configs`` entry point (``pyproject.toml``), so
``ns-train exploregs-splatfacto --data DATA`` finds it when this package and nerfstudio are
installed in the same environment. The method is nerfstudio's own ``splatfacto`` (its trainer,
data, optimizers and model config, copied from nerfstudio's registry) whose model swaps the
``DefaultStrategy`` it builds for
:class:`~exploregs_plugin.integrations.into_gsplat.GsplatSeedSplitStrategy` with every one of
splatfacto's gsplat settings (``GsplatSeedSplitStrategy.from_default``). The exploration settings
are model options, which configure eg-train's operators (``RandomSplitting``, ``RandomSeeding``):
``--pipeline.model.n-seed``, ``--pipeline.model.n-split``, ``--pipeline.model.split-every``,
``--pipeline.model.seed-prune-scale3d``, ``--pipeline.model.exploration-seed``.

Import order. nerfstudio loads the entry point while its own ``nerfstudio.configs.method_configs``
module is still being imported (``discover_methods`` runs at its end), and that module is where
splatfacto's config lives. So ``exploregs_splatfacto`` is made on first access (module
``__getattr__``) from the module nerfstudio is importing, and this module never imports
``method_configs`` at import time, which would import it back in a cycle.
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import sys
from dataclasses import dataclass, field
from typing import Any

try:
    from nerfstudio.engine.trainer import TrainerConfig
    from nerfstudio.models.splatfacto import SplatfactoModel, SplatfactoModelConfig
    from nerfstudio.plugins.types import MethodSpecification
except ImportError as exc:  # one line, whatever part of nerfstudio failed to import
    raise ImportError(
        f"exploregs_plugin.integrations.nerfstudio needs nerfstudio: pip install nerfstudio==1.1.5 ({exc})"
    ) from None

from ..strategies.budget import PAPER_N_SEED, PAPER_N_SPLIT, PAPER_SPLIT_EVERY
from ..strategies.seeding import RandomSeeding
from ..strategies.splitting import RandomSplitting
from .into_gsplat import GsplatSeedSplitStrategy

__all__ = ["METHOD_NAME", "ExploreSplatfactoModel", "ExploreSplatfactoModelConfig", "exploregs_splatfacto_config"]

METHOD_NAME = "exploregs-splatfacto"
DESCRIPTION = "splatfacto + Random Seeding + Random Splitting (ExploreGS)."


@dataclass
class ExploreSplatfactoModelConfig(SplatfactoModelConfig):
    """splatfacto's model config plus the exploration fields (paper defaults)."""

    _target: type = field(default_factory=lambda: ExploreSplatfactoModel)
    n_seed: int = PAPER_N_SEED
    """Seeds added every refine_every steps inside splatfacto's refine window (Random Seeding's
    rule: also in the pause after an opacity reset, where splatfacto does not refine; 0 disables)."""
    n_split: int = PAPER_N_SPLIT
    """Gaussians split per splitting step, drawn in proportion to their mean scale (0 disables)."""
    split_every: int = PAPER_SPLIT_EVERY
    """Random Splitting interval in steps, inside splatfacto's refine window."""
    seed_prune_scale3d: float = RandomSeeding.prune_scale3d
    """While seeding, the world-size prune threshold (x scene scale) instead of cull_scale_thresh
    (RandomSeeding.prune_scale3d)."""
    exploration_seed: int = 0
    """Seed of the exploration's own torch.Generator."""


class ExploreSplatfactoModel(SplatfactoModel):
    """splatfacto whose densification strategy is :class:`GsplatSeedSplitStrategy`."""

    config: ExploreSplatfactoModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()  # builds splatfacto's DefaultStrategy from its config
        self.strategy = GsplatSeedSplitStrategy.from_default(
            self.strategy,
            splitting=RandomSplitting(n_split=self.config.n_split, every=self.config.split_every),
            seeding=RandomSeeding(n_seed=self.config.n_seed, prune_scale3d=self.config.seed_prune_scale3d),
            seed=self.config.exploration_seed,
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)


def _registered_splatfacto() -> TrainerConfig:
    """nerfstudio's splatfacto config, from the method_configs module being imported if it is."""
    module = sys.modules.get("nerfstudio.configs.method_configs")
    if module is None or not hasattr(module, "method_configs"):
        module = importlib.import_module("nerfstudio.configs.method_configs")
    return module.method_configs["splatfacto"]


def exploregs_splatfacto_config() -> TrainerConfig:
    """A copy of splatfacto's TrainerConfig named ``exploregs-splatfacto`` whose model config is
    :class:`ExploreSplatfactoModelConfig` with splatfacto's model settings."""
    config = copy.deepcopy(_registered_splatfacto())  # nerfstudio's own entry stays untouched
    model = config.pipeline.model
    settings = {f.name: getattr(model, f.name) for f in dataclasses.fields(SplatfactoModelConfig)
                if f.init and f.name != "_target"}
    config.method_name = METHOD_NAME
    config.pipeline.model = ExploreSplatfactoModelConfig(**settings)
    return config


def __getattr__(name: str) -> Any:
    # exploregs_splatfacto, the entry point's object, is made on first access (see the module
    # docstring); a re-entrant access while method_configs imports keeps the first one made.
    if name != "exploregs_splatfacto":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    spec = MethodSpecification(config=exploregs_splatfacto_config(), description=DESCRIPTION)
    return globals().setdefault(name, spec)
