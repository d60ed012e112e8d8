"""Run gsplat's ``examples/simple_trainer.py`` with ExploreGS's strategies, unchanged on disk::

    python -m exploregs_plugin.integrations.simple_trainer PATH/TO/gsplat/examples/simple_trainer.py \\
        seedsplit --data_dir DATA --result_dir RESULTS

Everything after the script's path goes to simple_trainer's own command line. Two things are
added while the script runs (and removed when it ends):

- its ``configs`` dict (the subcommands of ``tyro.extras.overridable_config_cli``) gains the
  entries of :data:`ENTRIES`: a copy of simple_trainer's own ``default`` or ``mcmc`` config with
  one of our strategies (so ``mcmc-ray`` keeps gsplat's ``init_opa``, ``init_scale``,
  ``opacity_reg`` and ``scale_reg`` for MCMC); the new fields become ``--strategy.*`` options;
- ``gsplat.rendering.rasterization`` returns, in its ``info``, the ``viewmats`` it was called with:
  gsplat's info has no camera, and the ray noise needs its centre (``camera_centers`` in
  :mod:`exploregs_plugin.integrations.gsplat_info`). simple_trainer imports the function from
  there, so every render of the run carries its cameras.

simple_trainer decides what to call from the strategy's type (``isinstance(strategy,
DefaultStrategy)`` or ``MCMCStrategy``), which our classes subclass; its code is not changed.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import runpy
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..strategies.base import StrategyError
from .patching import attribute_set_to
from .into_gsplat import (
    GsplatMCMCRayStrategy,
    GsplatRayStrategy,
    GsplatSeedSplitStrategy,
    GsplatSeedStrategy,
    GsplatSplitStrategy,
)

ENTRIES: dict[str, tuple[str, type, str]] = {
    "seedsplit": ("default", GsplatSeedSplitStrategy,
                  "3DGS densification + Random Splitting + Random Seeding (ExploreGS)."),
    "seed": ("default", GsplatSeedStrategy, "3DGS densification + Random Seeding (ExploreGS, far side)."),
    "split": ("default", GsplatSplitStrategy, "3DGS densification + Random Splitting (ExploreGS, near side)."),
    "ray": ("default", GsplatRayStrategy, "3DGS densification + position noise along the viewing ray (ExploreGS)."),
    "mcmc-ray": ("mcmc", GsplatMCMCRayStrategy, "3DGS-MCMC with its position noise along the viewing ray (ExploreGS)."),
}
"""Subcommand -> (simple_trainer's config it copies, our strategy class, description)."""

USAGE = (
    "usage: python -m exploregs_plugin.integrations.simple_trainer PATH/TO/simple_trainer.py "
    f"{{{','.join(['default', 'mcmc', *ENTRIES])}}} [simple_trainer's options]"
)


def exploregs_configs(configs: Mapping[str, tuple[str, Any]]) -> dict[str, tuple[str, Any]]:
    """simple_trainer's ``configs`` plus :data:`ENTRIES`, each a copy of its base config whose
    strategy is ours (``verbose=True``, as simple_trainer builds its own)."""
    out = dict(configs)
    for name, (base, cls, description) in ENTRIES.items():
        if base not in configs:
            raise StrategyError(f"simple_trainer's configs have no '{base}' entry to base '{name}' on: {sorted(configs)}")
        out[name] = (description, dataclasses.replace(configs[base][1], strategy=cls(verbose=True)))
    return out


def with_camera(rasterization: Callable[..., Any]) -> Callable[..., Any]:
    """gsplat's ``rasterization`` whose returned ``info`` (the last element) also holds the
    ``viewmats`` [..., C, 4, 4] it rendered."""
    signature = inspect.signature(rasterization)

    @functools.wraps(rasterization)
    def rasterization_with_camera(*args: Any, **kwargs: Any) -> Any:
        out = rasterization(*args, **kwargs)
        out[-1]["viewmats"] = signature.bind(*args, **kwargs).arguments["viewmats"]
        return out

    return rasterization_with_camera


def run(argv: Sequence[str]) -> dict[str, Any]:
    """Run the simple_trainer script ``argv[0]`` as ``__main__`` with ``argv[1:]`` as its command
    line; returns its globals."""
    if not argv or not argv[0].endswith(".py"):
        raise SystemExit(USAGE)
    script = Path(argv[0]).resolve()
    if not script.is_file():
        raise SystemExit(f"{script} is not a file; {USAGE}")
    import gsplat.rendering  # noqa: PLC0415 - only when running: the module above needs gsplat anyway
    import tyro.extras  # noqa: PLC0415

    overridable = tyro.extras.overridable_config_cli

    def overridable_with_ours(configs: Mapping[str, tuple[str, Any]], *args: Any, **kwargs: Any) -> Any:
        return overridable(exploregs_configs(configs), *args, **kwargs)

    saved_argv, saved_path = sys.argv, list(sys.path)
    sys.argv = [str(script), *argv[1:]]
    sys.path.insert(0, str(script.parent))  # simple_trainer imports datasets/ and utils.py beside it
    try:
        with attribute_set_to(tyro.extras, "overridable_config_cli", overridable_with_ours), \
                attribute_set_to(gsplat.rendering, "rasterization", with_camera(gsplat.rendering.rasterization)):
            return runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv, sys.path[:] = saved_argv, saved_path


def main() -> None:
    run(sys.argv[1:])


if __name__ == "__main__":
    main()
