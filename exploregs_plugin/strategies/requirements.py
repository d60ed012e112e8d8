"""What a strategy or an operator can ask the renderer for, beyond the 2D-mean gradient and radii
that every view's observation carries."""

from __future__ import annotations

from .errors import StrategyError

VIEW_ERRORS = "view_errors"
"""Each view's ``ViewObservation.error``: its index, camera, target and error map."""
VISIBILITY_STATS = "visibility_stats"
"""``ViewObservation.visibility`` [N, 3]: each Gaussian's summed compositing weight alpha T and
alpha over the view's pixels, and its largest alpha T at one pixel (the peak)."""
ABSOLUTE_GRADIENT = "absolute_gradient"
"""``ViewObservation.screen_gradient(absolute=True)`` [N, 2]: each Gaussian's sums over the view's
pixels of |dL/dx| and |dL/dy| of each pixel (AbsGS; ``RasterSettings.absgrad``)."""
REQUIREMENTS = frozenset({VIEW_ERRORS, VISIBILITY_STATS, ABSOLUTE_GRADIENT})
"""Everything a strategy or operator can declare in its ``requires``."""


def merged_requires(cls: type, declared: frozenset[str]) -> frozenset[str]:
    """What ``cls`` requires: its own ``requires`` plus every base's (a subclass that declares
    ``requires`` adds to its bases' instead of hiding them in the MRO); unknown names refused."""
    required = frozenset().union(declared, *(getattr(base, "requires", frozenset()) for base in cls.__mro__[1:]))
    unknown = required - REQUIREMENTS
    if unknown:
        raise StrategyError(f"{cls.__name__}.requires names {sorted(unknown)}; known: {sorted(REQUIREMENTS)}")
    return required
