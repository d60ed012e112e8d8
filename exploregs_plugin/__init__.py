"""ExploreGS: 3D Gaussian Splatting with explicit exploration, trained on CPU."""

from exploregs_plugin.runtime.threads import prefer_passive_waiting as _prefer_passive_waiting

# First, before any module of the package imports torch: the OpenMP runtime reads its
# environment once, when torch loads it (see exploregs_plugin/runtime/threads.py for why).
_prefer_passive_waiting()

__version__ = "0.1.0"
