"""antimatter15 ``.splat`` files: 32 bytes per Gaussian, no header, no SH beyond the DC colour.

Record layout (little-endian), as antimatter15/splat's ``convert.py`` writes and its viewer reads::

    bytes  0-11   position x y z          3 x float32
    bytes 12-23   scale sigma_x..z        3 x float32, linear (exp of the log-scale)
    bytes 24-27   colour r g b, alpha     4 x uint8: round(clamp(0.5 + C0 sh0, 0, 1) 255),
                                                     round(sigmoid(opacity) 255)
    bytes 28-31   rotation w x y z        4 x uint8: round(q / |q| 128 + 128) clamped to 0..255

Records are sorted by importance, volume x opacity descending (exp(s0 + s1 + s2) sigmoid(o)),
as the converter does, so a viewer that streams the file draws the big opaque Gaussians first.
Decoding: colour (byte / 255 - 0.5) / C0, alpha logit(byte / 255) (ends as in
``packing.byte_to_opacity``), rotation (byte - 128) / 128 normalised, log of the scale.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from torch import Tensor

from exploregs_plugin.io.packing import (
    SH_C0,
    byte_to_opacity,
    linear_scales,
    log_sigmoid,
    opacity_to_byte,
    params_from_arrays,
    quantize_unorm,
    read_file_bytes,
    splat_arrays,
    unit_quaternions,
    write_file_atomic,
)
from exploregs_plugin.io.ply import PlyFormatError

RECORD = np.dtype([("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))])
# smallest positive normal float32: a stored scale of 0 (or below) reads as this, log = -87.3,
# instead of log(0) = -inf
SCALE_FLOOR = float(np.finfo(np.float32).tiny)


def importance_order(log_scales: np.ndarray, opacity_logits: np.ndarray) -> np.ndarray:
    """Indices by volume x opacity descending, computed as logs so nothing overflows:
    log(exp(s0 + s1 + s2) sigmoid(o)) = s0 + s1 + s2 + log_sigmoid(o). Ties keep their order."""
    key = log_scales.sum(axis=1) + log_sigmoid(opacity_logits)
    return np.argsort(-key, kind="stable")


def encode_splat(params: Mapping[str, Tensor], path: str | Path = "parameters") -> np.ndarray:
    """Raw parameters (finite) -> structured [N] array of :data:`RECORD`, in importance order."""
    a = splat_arrays(params, path)
    order = importance_order(a.scales, a.opacities)
    records = np.zeros(a.count, dtype=RECORD)
    records["position"] = a.means[order]
    records["scale"] = linear_scales(a.scales[order])
    colour = np.clip(0.5 + SH_C0 * a.sh0[order], 0.0, 1.0)
    records["rgba"][:, :3] = quantize_unorm(colour, 255)
    records["rgba"][:, 3] = opacity_to_byte(a.opacities[order])
    # q in [-1, 1] -> q 128 + 128 in [0, 256]; 256 (only q = 1) clamps to 255
    records["rotation"] = np.clip(np.rint(unit_quaternions(a.quats[order]) * 128.0 + 128.0), 0, 255)
    return records


def write_splat(path: Path, params: Mapping[str, Tensor]) -> int:
    """Write raw parameters (already in the frame to store, all finite) as a ``.splat`` file;
    SH bands above 0 are not stored. Returns the bytes written."""
    path = Path(path)
    return write_file_atomic(path, [encode_splat(params, path).tobytes()])


def decode_splat(records: np.ndarray) -> dict[str, Tensor]:
    """Structured [N] array of :data:`RECORD` -> raw float32 parameters (SH degree 0)."""
    n = records.shape[0]
    scales = records["scale"].astype(np.float64)
    # NaN stays NaN (the reader's caller drops the row); 0 and negative read as the floor
    log_scales = np.log(np.where(np.isnan(scales), np.nan, np.maximum(scales, SCALE_FLOOR)))
    rgba = records["rgba"].astype(np.float64)
    quats = unit_quaternions((records["rotation"].astype(np.float64) - 128.0) / 128.0)
    return params_from_arrays(records["position"], log_scales, quats, byte_to_opacity(records["rgba"][:, 3]),
                              (rgba[:, :3] / 255.0 - 0.5) / SH_C0, np.zeros((n, 0, 3)))


def read_splat(path: Path) -> tuple[dict[str, Tensor], int]:
    """Read a ``.splat`` file -> (raw float32 parameters, SH degree 0). Rows with non-finite
    positions or scales are returned as they are (``read_scene`` drops and counts them)."""
    path = Path(path)
    data = read_file_bytes(path, "a .splat file")
    if len(data) % RECORD.itemsize:
        raise PlyFormatError(path, f"size {len(data)} bytes is not a multiple of {RECORD.itemsize}; "
                                   f"not a .splat file (32-byte records), or truncated")
    return decode_splat(np.frombuffer(data, dtype=RECORD)), 0
