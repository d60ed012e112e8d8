"""ExploreGS's exploration operators inside other trainers.

``exploregs_plugin.integrations.gsplat``: Random Seeding and Random Splitting as gsplat
strategies (subclasses of ``gsplat.strategy.DefaultStrategy``), for gsplat's simple_trainer and
nerfstudio's splatfacto. Nothing is imported here, so this package imports without gsplat; see
docs/integrations.md.
"""
