"""Backgrounds: the named colours of ``--datamanager.background``, each layout's convention, and
the background a dataset without alpha evidently has (read off its images' borders).

Synthetic benchmarks (NeRF-synthetic, D-NeRF) store RGBA images whose alpha is composited on
white by convention; a copy whose alpha was dropped (RGB on black, say) can only be trained on
the colour it was flattened on, so the loader looks at the images' outermost pixels to say which.
"""

from __future__ import annotations

import numpy as np

NAMED = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
"""The named background colours (``random`` is not a colour: see DataManagerConfig)."""

LAYOUT_BACKGROUND = {"blender": "white"}
"""A layout's conventional background (the NeRF-synthetic and D-NeRF papers composite on white);
layouts not listed keep black."""

EVIDENT_SHARE = 0.9
"""Share of the border pixels that must have one named colour for the scene to evidently have it."""

EVIDENT_TOLERANCE = 8
"""A pixel has a named colour when every channel is within this many 8-bit steps of it (PNG
quantisation and a little anti-aliasing of the object's silhouette)."""


def default_background(layout: str | None) -> str:
    """The named background of ``layout`` (``"blender"``: white; any other: black)."""
    return LAYOUT_BACKGROUND.get(layout or "", "black")


def border_pixels(image: np.ndarray) -> np.ndarray:
    """The outermost ring of ``image`` [H, W, 3] as [2 (H + W) - 4, 3] (every pixel once)."""
    if image.shape[0] < 3 or image.shape[1] < 3:
        return image.reshape(-1, image.shape[-1])
    return np.concatenate([image[0], image[-1], image[1:-1, 0], image[1:-1, -1]], axis=0)


def border_shares(images: list[np.ndarray]) -> dict[str, float]:
    """Share of the border pixels of ``images`` (uint8 [H, W, 3] each) that have each named colour."""
    ring = np.concatenate([border_pixels(im) for im in images], axis=0).astype(np.int16)
    shares = {}
    for name, colour in NAMED.items():
        target = np.round(np.asarray(colour) * 255.0).astype(np.int16)
        shares[name] = float(np.mean(np.all(np.abs(ring - target) <= EVIDENT_TOLERANCE, axis=1)))
    return shares


def evident_background(images: list[np.ndarray]) -> tuple[str | None, dict[str, float]]:
    """(the named colour at least :data:`EVIDENT_SHARE` of the border pixels have, or None;
    the share of each named colour)."""
    shares = border_shares(images)
    name = max(shares, key=shares.get)
    return (name if shares[name] >= EVIDENT_SHARE else None), shares
