"""ExploreGS: 3D Gaussian Splatting with explicit exploration, trained on CPU."""

__version__ = "0.1.0"
