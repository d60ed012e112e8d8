"""ExploreGS's strategies and other trainers, each adapter named by its direction.

- ``into_gsplat``: our exploration operators as gsplat strategies, for gsplat's simple_trainer
  (``simple_trainer``: a launcher that adds them to it) and nerfstudio's splatfacto
  (``nerfstudio``: the method ``exploregs-splatfacto``).
- ``from_gsplat``: gsplat's own strategies inside eg-train (``--strategy gsplat-default`` /
  ``gsplat-mcmc``), with ``from_gsplat_cpu``'s CPU stand-ins for gsplat's CUDA-only MCMC helpers.
- ``gsplat_info``: gsplat's render info and our observations, converted both ways.

Nothing is imported here, so this package imports without gsplat; see docs/integrations.md.
"""
