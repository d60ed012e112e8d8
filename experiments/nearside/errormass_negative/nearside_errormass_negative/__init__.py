"""Error-mass densification (a negative result on ``builtin:nearside``; see docs/results.md).

Installed on its own (``pip install ./experiments/nearside/errormass_negative``), it registers the
strategy ``error-mass`` through the ``exploregs.strategies`` entry point:
``eg-train exploregs-default --strategy error-mass [--strategy.error-share 0.5]``.
"""

from .strategy import ERROR_MASS, ErrorMassStrategy, choose_growth, error_mass

__all__ = ["ERROR_MASS", "ErrorMassStrategy", "choose_growth", "error_mass"]
