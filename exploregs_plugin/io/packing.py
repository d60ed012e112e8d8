"""Pieces shared by the packed web splat formats (.splat, .spz, PlayCanvas compressed PLY).

Raw parameters in and out are the model's (see :class:`exploregs_plugin.io.ply.PlyScene`):
means [N, 3], scales [N, 3] (log sigma), quats [N, 4] (wxyz, unnormalised), opacities [N]
(logit), sh0 [N, 1, 3], shN [N, K-1, 3]. The formats store activated, quantised values; the
helpers here do the activations with every division, log and exp guarded, and write files
atomically (temporary name, then rename), as :func:`exploregs_plugin.io.ply.export_ply` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import torch
from torch import Tensor

from exploregs_plugin.io.atomic import atomic_path
from exploregs_plugin.io.ply import PlyFormatError, check_shapes

# The formats store colours, and our renderer draws them, as c = 0.5 + SH_C0 sh0 with
# SH_C0 = Y_0^0 = 1 / (2 sqrt(pi)); io knows formats only, so the constant is stated here
# (tests check it equals the renderer's exploregs_plugin.rasterizer.sh.SH_C0).
SH_C0 = 0.5 / math.sqrt(math.pi)
# A quaternion with |q|^2 <= QUAT_NORM2_MIN is the identity rotation, as the renderer treats it
# (exploregs_plugin.rasterizer.projection.QUAT_NORM2_MIN; a test checks they agree).
QUAT_NORM2_MIN = 1e-24

# float32 exp() is finite and > 0 exactly for log values inside this range (log of the largest
# float32, 3.4028235e38, is 88.72; of the smallest normal, 1.1754944e-38, is -87.34): linear
# scales are written from log-scales clipped to it, so a huge or tiny scale never becomes inf or 0.
LOG_SCALE_MIN_F32 = -87.0
LOG_SCALE_MAX_F32 = 88.0
# logit(p) with p = byte / 255 is infinite at bytes 0 and 255. Those two bytes stand for the
# intervals p in [0, 0.5/255) and [254.5/255, 1]; they decode to the centres of those intervals
# (0.25/255, 254.75/255), so decoding and re-encoding gives the same byte and |p_decoded - p| stays
# <= 0.5/255 for every byte.
ALPHA_END = 0.25 / 255.0


@dataclass
class SplatArrays:
    """Raw parameters as float64 numpy arrays (the maths of quantisation is done in float64).

    sh0: [N, 3] (the DC coefficient per channel), shN: [N, K-1, 3]; the rest as in the model.
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh0: np.ndarray
    shN: np.ndarray
    sh_degree: int

    @property
    def count(self) -> int:
        return int(self.means.shape[0])


def splat_arrays(params: Mapping[str, Tensor], path: str | Path) -> SplatArrays:
    """Validated float64 copies of ``params`` for the writer of ``path``.

    Raises :class:`PlyFormatError` for wrong shapes, no Gaussians, or a non-finite value (the
    caller, :func:`exploregs_plugin.io.scene_files.write_scene`, drops non-finite rows first).
    """
    degree = check_shapes(params, path)

    def cpu(name: str) -> np.ndarray:
        return params[name].detach().cpu().double().numpy()

    n = int(params["means"].shape[0])
    arrays = SplatArrays(cpu("means"), cpu("scales"), cpu("quats"), cpu("opacities"),
                         cpu("sh0").reshape(n, 3), cpu("shN"), degree)
    if n == 0:
        raise PlyFormatError(path, "no Gaussians to write")
    for name in ("means", "scales", "quats", "opacities", "sh0", "shN"):
        if not np.isfinite(getattr(arrays, name)).all():
            raise PlyFormatError(path, f"parameter '{name}' has non-finite values; drop those Gaussians "
                                       f"first (write_scene does)")
    return arrays


def params_from_arrays(means: np.ndarray, scales: np.ndarray, quats: np.ndarray, opacities: np.ndarray,
                       sh0: np.ndarray, shN: np.ndarray) -> dict[str, Tensor]:
    """Decoded arrays -> raw float32 parameter tensors (sh0 [N, 3] -> [N, 1, 3])."""
    n = means.shape[0]

    def tensor(value: np.ndarray, shape: tuple[int, ...]) -> Tensor:
        return torch.from_numpy(np.array(value, dtype=np.float32).reshape(shape))  # a copy: writable

    return {"means": tensor(means, (n, 3)), "scales": tensor(scales, (n, 3)), "quats": tensor(quats, (n, 4)),
            "opacities": tensor(opacities, (n,)), "sh0": tensor(sh0, (n, 1, 3)),
            "shN": tensor(shN, (n, shN.shape[1] if shN.ndim == 3 else 0, 3))}


def unit_quaternions(quats: np.ndarray) -> np.ndarray:
    """[N, 4] -> q / |q|; a quaternion with |q|^2 <= QUAT_NORM2_MIN becomes the identity (1, 0, 0, 0),
    as the renderer treats it (``exploregs_plugin.rasterizer.projection.quats_to_rotmats``)."""
    norm2 = (quats * quats).sum(axis=1, keepdims=True)
    identity = np.zeros_like(quats)
    identity[:, 0] = 1.0
    safe = np.where(norm2 > QUAT_NORM2_MIN, quats, identity)
    return safe / np.sqrt((safe * safe).sum(axis=1, keepdims=True))


def sigmoid(x: np.ndarray) -> np.ndarray:
    """1 / (1 + exp(-x)) without overflow: exp only ever sees -|x| (<= 0)."""
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def log_sigmoid(x: np.ndarray) -> np.ndarray:
    """log(sigmoid(x)) = -log(1 + exp(-x)), finite for every finite x."""
    return -np.logaddexp(0.0, -x)


def quantize_unorm(value: np.ndarray, levels: int) -> np.ndarray:
    """value in [0, 1] -> nearest integer of value * levels, clamped to 0..levels (int64)."""
    return np.clip(np.rint(value * levels), 0, levels).astype(np.int64)


def opacity_to_byte(logit: np.ndarray) -> np.ndarray:
    """Opacity logits -> uint8 round(sigmoid(logit) * 255); |byte/255 - sigmoid| <= 0.5/255."""
    return quantize_unorm(sigmoid(logit), 255).astype(np.uint8)


def byte_to_opacity(byte: np.ndarray) -> np.ndarray:
    """uint8 alpha -> opacity logit; bytes 0 and 255 decode to their intervals' centres (ALPHA_END)."""
    p = np.clip(np.asarray(byte, dtype=np.float64) / 255.0, ALPHA_END, 1.0 - ALPHA_END)
    return np.log(p) - np.log1p(-p)


def linear_scales(log_scales: np.ndarray) -> np.ndarray:
    """exp(log sigma) with the log clipped to [LOG_SCALE_MIN_F32, LOG_SCALE_MAX_F32]: finite, > 0 in float32."""
    return np.exp(np.clip(log_scales, LOG_SCALE_MIN_F32, LOG_SCALE_MAX_F32))


def read_file_bytes(path: Path, what: str) -> bytes:
    """The bytes of ``path``; a missing or unreadable file is a :class:`PlyFormatError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(path, "file not found")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise PlyFormatError(path, f"could not read: {err}") from err
    if not data:
        raise PlyFormatError(path, f"is empty; not {what}")
    return data


def write_file_atomic(path: Path, parts: Iterable[bytes]) -> int:
    """Write the concatenated ``parts`` to ``path`` through a temporary name and a rename (so a
    failure never leaves half a file); returns the bytes written. OSError -> PlyFormatError."""
    size = 0
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as out:
            for part in parts:
                size += out.write(part)
    except OSError as err:
        raise PlyFormatError(path, f"could not write: {err}") from err
    return size
