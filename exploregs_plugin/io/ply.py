"""Gaussian scenes as standard 3DGS PLY files: export, import, frame mapping.

The layout is the one the original 3DGS code writes and most viewers and editors read: one
``vertex`` element, one float32 property per value, in this order::

    x y z                    mean
    nx ny nz                 unused normals (written as 0)
    f_dc_0 f_dc_1 f_dc_2     SH DC coefficient, one per colour channel
    f_rest_0 .. f_rest_{M-1} higher SH coefficients, channel-major: f_rest_{c*(K-1)+k} holds
                             coefficient k+1 of channel c (all red ones, then green, then blue)
    opacity                  logit of the opacity
    scale_0 scale_1 scale_2  log of the per-axis standard deviation
    rot_0 .. rot_3           rotation quaternion w x y z (unnormalised)

with M = 3 (K - 1), K = (degree + 1)^2, so M is 0, 9, 24 or 45 for SH degree 0..3.

Training happens in a normalised frame, ``x_norm = (x_orig + translation) * scale`` (see
``exploregs_plugin.data.parsed``). The normalisation has no rotation, so only means and scales
change between frames (SH and quaternions are frame-independent)::

    x_orig     = x_norm / scale - translation
    sigma_orig = sigma_norm / scale          ->  log sigma_orig = log sigma_norm - log(scale)

Import applies the inverse. Mapping is computed in float64 and rounded once to float32.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from torch import Tensor

from exploregs_plugin.io.atomic import atomic_path

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")
REQUIRED_FIELDS = (
    "x", "y", "z",
    "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity",
    "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
)
NORMAL_FIELDS = ("nx", "ny", "nz")
MAX_SH_DEGREE = 3
_REST = re.compile(r"^f_rest_(\d+)$")


class PlyFormatError(ValueError):
    """A PLY file (or the scene to write into one) is not usable; the message names the file."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{where}: {problem}")


@dataclass(frozen=True)
class PlyExport:
    """What :func:`export_ply` wrote: ``written`` Gaussians, ``dropped`` non-finite ones."""

    path: Path
    written: int
    dropped: int
    sh_degree: int


@dataclass
class PlyScene:
    """Gaussians read from a PLY: raw parameters (same keys and shapes as the model's).

    params: means [N, 3], scales [N, 3] (log), quats [N, 4] (wxyz), opacities [N] (logit),
    sh0 [N, 1, 3], shN [N, K-1, 3]; float32 tensors. ``dropped``: rows left out as non-finite.
    """

    path: Path
    params: dict[str, Tensor]
    sh_degree: int
    dropped: int

    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])


# ----------------------------------------------------------------------------- frames
def normalization_terms(normalization: Any) -> tuple[np.ndarray, float]:
    """(translation [3] float64, scale) from a ``Normalization``, a ``(translation, scale)``
    pair, or None (identity). Rejects a non-finite translation and a scale that is not > 0."""
    if normalization is None:
        return np.zeros(3), 1.0
    if hasattr(normalization, "translation") and hasattr(normalization, "scale"):
        translation, scale = normalization.translation, normalization.scale
    else:
        try:
            translation, scale = normalization
        except (TypeError, ValueError) as err:
            raise ValueError(
                f"normalization must be a Normalization or a (translation, scale) pair, got {normalization!r}"
            ) from err
    if isinstance(translation, Tensor):
        translation = translation.detach().cpu().numpy()
    translation = np.asarray(translation, dtype=np.float64).reshape(-1)
    scale = float(scale)
    if translation.shape != (3,) or not np.isfinite(translation).all():
        raise ValueError(f"normalization translation must be 3 finite numbers, got {translation}")
    if not (math.isfinite(scale) and scale > 0.0):
        raise ValueError(f"normalization scale must be finite and > 0, got {scale}")
    return translation, scale


def _map_frame(params: Mapping[str, Tensor], normalization: Any, to_original: bool) -> dict[str, Tensor]:
    translation, scale = normalization_terms(normalization)
    out = {name: params[name].detach().cpu().float().clone() for name in PARAM_NAMES}
    if np.all(translation == 0.0) and scale == 1.0:
        return out
    means = params["means"].detach().cpu().double()
    log_scales = params["scales"].detach().cpu().double()
    t = torch.from_numpy(translation)
    if to_original:
        out["means"] = (means / scale - t).float()
        out["scales"] = (log_scales - math.log(scale)).float()
    else:
        out["means"] = ((means + t) * scale).float()
        out["scales"] = (log_scales + math.log(scale)).float()
    return out


def to_original_frame(params: Mapping[str, Tensor], normalization: Any) -> dict[str, Tensor]:
    """Raw parameters from the normalised training frame to the dataset's own coordinates.

    means: [N, 3] -> x / scale - translation; scales: [N, 3] log -> log - log(scale); the other
    parameters are copied. Returns detached float32 CPU tensors.
    """
    return _map_frame(params, normalization, to_original=True)


def to_normalized_frame(params: Mapping[str, Tensor], normalization: Any) -> dict[str, Tensor]:
    """Inverse of :func:`to_original_frame`: (x + translation) * scale, log + log(scale)."""
    return _map_frame(params, normalization, to_original=False)


def finite_rows(params: Mapping[str, Tensor]) -> Tensor:
    """[N] bool: True where every value of the Gaussian in every parameter is finite."""
    n = params["means"].shape[0]
    keep = torch.ones(n, dtype=torch.bool)
    for name in PARAM_NAMES:
        value = params[name].detach()
        if value.shape[0] != n:
            raise ValueError(f"parameter '{name}' has {value.shape[0]} rows, 'means' has {n}")
        if value.numel():  # shN of a degree-0 scene has no values at all
            keep &= torch.isfinite(value.reshape(n, -1)).all(dim=1)
    return keep


def drop_nonfinite(params: Mapping[str, Tensor]) -> tuple[dict[str, Tensor], int]:
    """Remove Gaussians with any NaN or inf value; returns (params, number removed)."""
    keep = finite_rows(params)
    dropped = int((~keep).sum())
    if dropped == 0:
        return {name: params[name] for name in PARAM_NAMES}, 0
    return {name: params[name][keep] for name in PARAM_NAMES}, dropped


# ----------------------------------------------------------------------------- layout
def sh_degree_for_rest(count: int) -> int:
    """SH degree whose higher coefficients fill ``count`` f_rest fields: 3 ((d+1)^2 - 1) = count."""
    for degree in range(MAX_SH_DEGREE + 1):
        if 3 * ((degree + 1) ** 2 - 1) == count:
            return degree
    valid = ", ".join(f"{3 * ((d + 1) ** 2 - 1)} (degree {d})" for d in range(MAX_SH_DEGREE + 1))
    raise ValueError(f"{count} f_rest fields match no SH degree; expected one of {valid}")


def ply_field_names(sh_degree: int) -> list[str]:
    """Vertex property names of the standard layout for ``sh_degree`` (0-3), in file order."""
    if not 0 <= sh_degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh_degree must be in 0..{MAX_SH_DEGREE}, got {sh_degree}")
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", *NORMAL_FIELDS, "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def check_shapes(params: Mapping[str, Tensor], where: str | Path) -> int:
    """Validate the parameter shapes; returns the SH degree."""
    missing = [name for name in PARAM_NAMES if name not in params]
    if missing:
        raise PlyFormatError(where, f"parameters {missing} are missing (need {', '.join(PARAM_NAMES)})")
    n = params["means"].shape[0]
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3)}
    for name, shape in expected.items():
        if tuple(params[name].shape) != shape:
            raise PlyFormatError(where, f"parameter '{name}' has shape {tuple(params[name].shape)}, expected {shape}")
    rest = params["shN"]
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
        raise PlyFormatError(where, f"parameter 'shN' has shape {tuple(rest.shape)}, expected ({n}, K-1, 3)")
    try:
        return sh_degree_for_rest(3 * rest.shape[1])
    except ValueError as err:
        raise PlyFormatError(where, f"shN has {rest.shape[1]} coefficients per channel: {err}") from err


def params_to_vertices(params: Mapping[str, Tensor]) -> np.ndarray:
    """Raw parameters -> structured float32 array [N] with the fields of :func:`ply_field_names`.

    shN [N, K-1, 3] is written channel-major: shN[n, k, c] -> f_rest_{c (K-1) + k}.
    """
    degree = check_shapes(params, "parameters")
    n = params["means"].shape[0]

    def cpu(name: str) -> np.ndarray:
        return params[name].detach().cpu().float().numpy()

    rest = cpu("shN").transpose(0, 2, 1).reshape(n, -1)  # [N, 3, K-1] -> [N, 3 (K-1)]
    columns = [cpu("means"), np.zeros((n, 3), np.float32), cpu("sh0").reshape(n, 3), rest,
               cpu("opacities").reshape(n, 1), cpu("scales"), cpu("quats")]
    table = np.concatenate(columns, axis=1)
    names = ply_field_names(degree)
    vertices = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertices[name] = table[:, i]
    return vertices


def vertices_to_params(vertices: np.ndarray, where: str | Path = "vertex data") -> tuple[dict[str, Tensor], int]:
    """Structured array of a PLY ``vertex`` element -> (raw float32 parameters, SH degree).

    Accepts any property order, extra properties (ignored), missing normals, and any numeric
    property type. Raises :class:`PlyFormatError` for a missing field or an f_rest set that is
    not 0..M-1 with M = 3 ((d+1)^2 - 1).
    """
    names = vertices.dtype.names or ()
    missing = [f for f in REQUIRED_FIELDS if f not in names]
    if missing:
        raise PlyFormatError(
            where, f"vertex element lacks {', '.join(missing)}; a 3DGS PLY needs x y z, f_dc_0..2, "
                   f"f_rest_* (optional), opacity, scale_0..2, rot_0..3"
        )
    rest_ids = sorted(int(m.group(1)) for name in names if (m := _REST.match(name)))
    if rest_ids != list(range(len(rest_ids))):
        gaps = sorted(set(range(max(rest_ids) + 1)) - set(rest_ids))
        raise PlyFormatError(where, f"f_rest fields are not numbered 0..{len(rest_ids) - 1} (missing f_rest_{gaps[0]})")
    try:
        degree = sh_degree_for_rest(len(rest_ids))
    except ValueError as err:
        raise PlyFormatError(where, str(err)) from err
    used = list(REQUIRED_FIELDS) + [f"f_rest_{i}" for i in rest_ids]
    for name in used:
        kind = vertices.dtype[name].kind
        if kind not in "fiu":
            raise PlyFormatError(where, f"property '{name}' is not a scalar number (numpy kind {kind!r})")

    def stack(fields: Sequence[str]) -> np.ndarray:
        return np.stack([np.asarray(vertices[f], dtype=np.float32) for f in fields], axis=1) if fields else \
            np.zeros((len(vertices), 0), np.float32)

    n = len(vertices)
    n_coeff = (degree + 1) ** 2 - 1
    rest = stack([f"f_rest_{i}" for i in rest_ids]).reshape(n, 3, n_coeff).transpose(0, 2, 1)
    params = {
        "means": torch.from_numpy(stack(["x", "y", "z"])),
        "scales": torch.from_numpy(stack(["scale_0", "scale_1", "scale_2"])),
        "quats": torch.from_numpy(stack(["rot_0", "rot_1", "rot_2", "rot_3"])),
        "opacities": torch.from_numpy(stack(["opacity"])[:, 0].copy()),
        "sh0": torch.from_numpy(stack(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3)),
        "shN": torch.from_numpy(np.ascontiguousarray(rest)),
    }
    return params, degree


# ----------------------------------------------------------------------------- files
def export_ply(
    path: Path,
    params: Mapping[str, Tensor],
    normalization: Any = None,
    *,
    text: bool = False,
    comments: Sequence[str] = (),
) -> PlyExport:
    """Write ``params`` (raw, normalised frame) as a standard 3DGS PLY in the original frame.

    normalization: the dataset's ``x_norm = (x_orig + translation) * scale`` (None: write the
    coordinates as they are). Gaussians with any non-finite value after mapping are dropped and
    counted. ``text``: ASCII instead of binary little-endian. The file is written to a
    temporary name and renamed, so a failed write never leaves half a PLY behind.
    """
    path = Path(path)
    degree = check_shapes(params, path)
    mapped, dropped = drop_nonfinite(to_original_frame(params, normalization))
    if mapped["means"].shape[0] == 0:
        raise PlyFormatError(path, f"no Gaussians to write ({dropped} had non-finite values)")
    element = PlyElement.describe(params_to_vertices(mapped), "vertex")
    header = [f"ExploreGS 3DGS scene, SH degree {degree}", *comments]
    try:
        with atomic_path(path) as tmp:
            PlyData([element], text=text, byte_order="<", comments=header).write(str(tmp))
    except OSError as err:
        raise PlyFormatError(path, f"could not write: {err}") from err
    return PlyExport(path, int(mapped["means"].shape[0]), dropped, degree)


def read_ply(path: Path, normalization: Any = None, *, keep_nonfinite: bool = False) -> PlyScene:
    """Read a 3DGS PLY (ours or another tool's; SH degree 0-3 from the f_rest count).

    normalization: when given, map the file's coordinates into that normalised frame
    (``(x + translation) * scale``, log-scales + log(scale)); None keeps them as stored.
    Gaussians with non-finite values are dropped and counted unless ``keep_nonfinite``.
    """
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(path, "file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as err:  # plyfile raises parse errors, ValueError, UnicodeError ... for foreign files
        raise PlyFormatError(path, f"not a readable PLY file ({type(err).__name__}: {err})") from err
    elements = {element.name: element for element in ply.elements}
    if "vertex" not in elements:
        found = ", ".join(elements) or "none"
        raise PlyFormatError(path, f"has no 'vertex' element (elements: {found}); not a 3DGS PLY")
    names = elements["vertex"].data.dtype.names or ()
    if "chunk" in elements or any(name.startswith("packed_") for name in names):
        raise PlyFormatError(path, "is a compressed (packed/chunked) splat PLY; decompress it to the standard "
                                   "3DGS layout first")
    vertices = elements["vertex"].data
    if len(vertices) == 0:
        raise PlyFormatError(path, "holds no Gaussians (the vertex element is empty)")
    params, degree = vertices_to_params(vertices, path)
    return scene_read(path, params, degree, normalization, keep_nonfinite)


def scene_read(path: Path, params: dict[str, Tensor], sh_degree: int, normalization: Any = None,
               keep_nonfinite: bool = False) -> PlyScene:
    """The :class:`PlyScene` of parameters decoded from the file ``path`` (any format): mapped into
    the normalised frame of ``normalization`` when given, non-finite rows dropped and counted
    unless ``keep_nonfinite``."""
    if normalization is not None:
        params = to_normalized_frame(params, normalization)
    dropped = 0
    if not keep_nonfinite:
        params, dropped = drop_nonfinite(params)
        if params["means"].shape[0] == 0:
            raise PlyFormatError(path, f"all {dropped} Gaussians have non-finite values")
    return PlyScene(Path(path), params, sh_degree, dropped)
