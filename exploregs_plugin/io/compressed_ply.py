"""PlayCanvas compressed PLY (``.compressed.ply``), as SuperSplat and splat-transform write it
(``src/lib/writers/write-compressed-ply.ts``, ``compressed-chunk.ts``; read by ``decompress-ply.ts``).

Binary little-endian PLY with these elements, in this order::

    chunk   ceil(N / 256) rows, float32: min_x min_y min_z max_x max_y max_z,
            min_scale_x..z max_scale_x..z (log-scales, clamped to [-20, 20]),
            min_r min_g min_b max_r max_g max_b (colour 0.5 + C0 sh0, not clamped)
    vertex  N rows, uint32: packed_position, packed_rotation, packed_scale, packed_color
    sh      N rows, uint8 f_rest_0 .. f_rest_{M-1} (only for SH degree > 0; standard PLY order)

Gaussian i belongs to chunk i // 256; every value v of a chunk's range [lo, hi] is stored as
t = (v - lo) / (hi - lo) in [0, 1] (0 where hi = lo), as round(t (2^b - 1)) with b bits:

    packed_position  x 11 bits << 21 | y 10 bits << 11 | z 11 bits
    packed_scale     the same layout, of the log-scales
    packed_color     r 8 << 24 | g 8 << 16 | b 8 << 8 | alpha 8, alpha = sigmoid(opacity) (absolute)
    packed_rotation  smallest three of the unit quaternion in rot_0..rot_3 (w x y z) order: the
                     largest |component|'s index in bits 30-31, then the other three (largest
                     made positive), each as a 10-bit unorm of q_i sqrt(1/2) + 0.5, first highest
    sh               byte = clamp(floor((c / 8 + 0.5) 256), 0, 255); decoded 0 -> -4, 255 -> 4,
                     else ((byte + 0.5) / 256 - 0.5) 8

Order: the reference sorts Gaussians along a Morton (Z-order) curve so each chunk is compact;
this writer does too, with 21 bits per axis over the scene's bounding box (the reference
starts at 10 bits and refines crowded cells; both are Z-order curves, and any order reads).
Files from before per-chunk colours (12 chunk properties, colour an absolute unorm) also read.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from plyfile import PlyData, PlyElement
from torch import Tensor

from exploregs_plugin.io.packing import (
    SH_C0,
    byte_to_opacity,
    opacity_to_byte,
    params_from_arrays,
    quantize_unorm,
    splat_arrays,
    unit_quaternions,
    write_file_atomic,
)
from exploregs_plugin.io.ply import PlyFormatError, sh_degree_for_rest

CHUNK_SIZE = 256
POSITION_FIELDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")
SCALE_FIELDS = ("min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
COLOR_FIELDS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
PACKED_FIELDS = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
SCALE_LIMIT = 20.0  # the reference clamps chunk scale ranges to [-20, 20] ("sometimes values are at infinity")
BITS_11_10_11 = (11, 10, 11)
ROTATION_BITS = 10
SH_RANGE = 8.0  # sh bytes cover c in [-4, 4]
HEADER_LIMIT = 1 << 16


# ----------------------------------------------------------------------------- order
def _spread_bits(v: np.ndarray) -> np.ndarray:
    """21-bit integers -> their bits at every third position (bit k -> bit 3k) of a uint64."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def morton_order(means: np.ndarray) -> np.ndarray:
    """Indices sorting [N, 3] points along the Z-order curve of their bounding box (21 bits per
    axis; an axis with no extent contributes 0). Stable, so equal codes keep their order."""
    lo = means.min(axis=0)
    extent = means.max(axis=0) - lo
    levels = float((1 << 21) - 1)
    scale = np.divide(levels, extent, out=np.zeros(3), where=extent > 0)
    cells = np.clip(np.floor((means - lo) * scale), 0, levels)
    x, y, z = (_spread_bits(cells[:, axis]) for axis in range(3))
    code = x | (y << np.uint64(1)) | (z << np.uint64(2))
    return np.argsort(code, kind="stable")


# ----------------------------------------------------------------------------- packing
def _chunk_ranges(values: np.ndarray, chunks: int) -> tuple[np.ndarray, np.ndarray]:
    """[N, 3] -> per-chunk (min, max) [C, 3], rounded to the float32 the file stores. The last
    chunk is padded with its last row, as the reference does (same min/max as without padding)."""
    rows = np.minimum(np.arange(chunks * CHUNK_SIZE), values.shape[0] - 1)
    grouped = values[rows].reshape(chunks, CHUNK_SIZE, 3)
    return (grouped.min(axis=1).astype(np.float32).astype(np.float64),
            grouped.max(axis=1).astype(np.float32).astype(np.float64))


def _normalized(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(v - lo) / (hi - lo) per row's chunk, in [0, 1]; 0 where the chunk has no extent."""
    chunk = np.arange(values.shape[0]) // CHUNK_SIZE
    lo, width = lo[chunk], (hi - lo)[chunk]
    t = np.divide(values - lo, width, out=np.zeros_like(values), where=width > 0)
    return np.clip(t, 0.0, 1.0)


def _pack_11_10_11(t: np.ndarray) -> np.ndarray:
    word = np.zeros(t.shape[0], dtype=np.uint32)
    for column, bits in enumerate(BITS_11_10_11):
        word = (word << np.uint32(bits)) | quantize_unorm(t[:, column], (1 << bits) - 1).astype(np.uint32)
    return word


def _unpack_11_10_11(word: np.ndarray) -> np.ndarray:
    columns, shift = [], 32
    for bits in BITS_11_10_11:
        shift -= bits
        columns.append(((word >> np.uint32(shift)) & np.uint32((1 << bits) - 1)) / ((1 << bits) - 1))
    return np.stack(columns, axis=1)


def pack_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz (any norm) -> uint32 smallest three (see the module docstring)."""
    q = unit_quaternions(quats_wxyz)
    rows = np.arange(q.shape[0])
    largest = np.argmax(np.abs(q), axis=1)
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]  # -q is the same rotation
    levels = (1 << ROTATION_BITS) - 1
    word = largest.astype(np.uint32)
    for i in range(4):
        # the other components lie in [-sqrt(1/2), sqrt(1/2)]: q sqrt(1/2) + 0.5 in [0, 1]
        code = quantize_unorm(q[:, i] * np.sqrt(0.5) + 0.5, levels).astype(np.uint32)
        word = np.where(largest != i, (word << np.uint32(ROTATION_BITS)) | code, word)
    return word


def unpack_rotations(word: np.ndarray) -> np.ndarray:
    """uint32 smallest three -> [N, 4] unit quaternions in rot_0..rot_3 (w x y z) order."""
    levels = (1 << ROTATION_BITS) - 1
    largest = (word >> np.uint32(30)).astype(np.int64)
    small = np.stack([((word >> np.uint32(shift)) & np.uint32(levels)) / levels for shift in (20, 10, 0)], axis=1)
    small = (small - 0.5) / np.sqrt(0.5)
    rest = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))
    q = np.empty((word.shape[0], 4))
    for which in range(4):
        rows = largest == which
        others = [i for i in range(4) if i != which]
        q[np.ix_(rows, others)] = small[rows]
        q[rows, which] = rest[rows]
    return q


def _sh_bytes(shN: np.ndarray) -> np.ndarray:
    """[N, K-1, 3] -> [N, 3 (K-1)] uint8 in PLY order (f_rest_{c (K-1) + k} = shN[:, k, c])."""
    flat = shN.transpose(0, 2, 1).reshape(shN.shape[0], -1)
    return np.clip(np.floor((flat / SH_RANGE + 0.5) * 256.0), 0, 255).astype(np.uint8)


def _sh_values(codes: np.ndarray) -> np.ndarray:
    """uint8 -> coefficients: 0 -> -4, 255 -> 4, else the centre of the byte's interval."""
    n = np.where(codes == 0, 0.0, np.where(codes == 255, 1.0, (codes.astype(np.float64) + 0.5) / 256.0))
    return (n - 0.5) * SH_RANGE


def encode_compressed_ply(params: Mapping[str, Tensor], path: str | Path = "parameters",
                          comments: Sequence[str] = ()) -> PlyData:
    """Raw parameters (finite) -> the compressed PLY (Morton order), as plyfile data."""
    a = splat_arrays(params, path)
    order = morton_order(a.means)
    n, chunks = a.count, -(-a.count // CHUNK_SIZE)
    means, colours = a.means[order], 0.5 + SH_C0 * a.sh0[order]
    scales = np.clip(a.scales[order], -SCALE_LIMIT, SCALE_LIMIT)
    ranges = [_chunk_ranges(v, chunks) for v in (means, scales, colours)]
    chunk = np.empty(chunks, dtype=[(f, "<f4") for f in POSITION_FIELDS + SCALE_FIELDS + COLOR_FIELDS])
    for fields, (lo, hi) in zip((POSITION_FIELDS, SCALE_FIELDS, COLOR_FIELDS), ranges):
        for j in range(3):
            chunk[fields[j]], chunk[fields[j + 3]] = lo[:, j], hi[:, j]
    vertex = np.empty(n, dtype=[(f, "<u4") for f in PACKED_FIELDS])
    vertex["packed_position"] = _pack_11_10_11(_normalized(means, *ranges[0]))
    vertex["packed_scale"] = _pack_11_10_11(_normalized(scales, *ranges[1]))
    vertex["packed_rotation"] = pack_rotations(a.quats[order])
    rgb = quantize_unorm(_normalized(colours, *ranges[2]), 255).astype(np.uint32)
    alpha = opacity_to_byte(a.opacities[order]).astype(np.uint32)
    r, g, b = (rgb[:, channel] for channel in range(3))
    vertex["packed_color"] = (r << np.uint32(24)) | (g << np.uint32(16)) | (b << np.uint32(8)) | alpha
    elements = [PlyElement.describe(chunk, "chunk"), PlyElement.describe(vertex, "vertex")]
    if a.sh_degree:
        codes = _sh_bytes(a.shN[order])
        sh = np.empty(n, dtype=[(f"f_rest_{i}", "u1") for i in range(codes.shape[1])])
        for i in range(codes.shape[1]):
            sh[f"f_rest_{i}"] = codes[:, i]
        elements.append(PlyElement.describe(sh, "sh"))
    header = [f"ExploreGS compressed 3DGS scene, SH degree {a.sh_degree}, Morton order", *comments]
    return PlyData(elements, byte_order="<", comments=header)


def write_compressed_ply(path: Path, params: Mapping[str, Tensor], comments: Sequence[str] = ()) -> int:
    """Write raw parameters (already in the frame to store, all finite) as a PlayCanvas
    compressed PLY; ``comments`` go into the header. Returns the bytes written."""
    path = Path(path)
    buffer = io.BytesIO()
    encode_compressed_ply(params, path, comments).write(buffer)
    return write_file_atomic(path, [buffer.getvalue()])


# ----------------------------------------------------------------------------- reading
def is_compressed_ply(path: Path) -> bool:
    """Whether ``path`` is a PLY whose header has a ``chunk`` element or ``packed_*`` properties
    (reads at most the first 64 KiB)."""
    with open(path, "rb") as f:
        head = f.read(HEADER_LIMIT)
    if not head.startswith(b"ply"):
        return False
    lines = head.split(b"end_header", 1)[0].decode("ascii", "replace").splitlines()
    words = [line.split() for line in lines]
    return any(w[:2] == ["element", "chunk"] or (w[:1] == ["property"] and w[-1].startswith("packed_"))
               for w in words if w)


def _fields(path: Path, element: PlyElement, names: Sequence[str], kinds: str) -> np.ndarray:
    """[rows, len(names)] float64 of the named properties; a missing or non-numeric one is an error."""
    data = element.data
    have = data.dtype.names or ()
    missing = [name for name in names if name not in have]
    if missing:
        raise PlyFormatError(path, f"'{element.name}' element lacks {', '.join(missing)}; not a compressed PLY")
    wrong = [name for name in names if data.dtype[name].kind not in kinds]
    if wrong:
        raise PlyFormatError(path, f"'{element.name}' properties {', '.join(wrong)} are not {kinds!r} numbers")
    return np.stack([np.asarray(data[name], dtype=np.float64) for name in names], axis=1) if len(names) else \
        np.zeros((len(data), 0))


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray, chunk: np.ndarray) -> np.ndarray:
    return lo[chunk] * (1.0 - t) + hi[chunk] * t


def read_compressed_ply(path: Path) -> tuple[dict[str, Tensor], int]:
    """Read a PlayCanvas compressed PLY -> (raw float32 parameters in file order, SH degree)."""
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(path, "file not found")
    try:
        ply = PlyData.read(str(path))
    except Exception as err:  # plyfile raises parse errors, ValueError, ... for damaged files
        raise PlyFormatError(path, f"not a readable PLY file ({type(err).__name__}: {err})") from err
    elements = {element.name: element for element in ply.elements}
    if "chunk" not in elements or "vertex" not in elements:
        raise PlyFormatError(path, f"needs 'chunk' and 'vertex' elements (has {', '.join(elements) or 'none'}); "
                                   f"not a compressed PLY")
    chunk_el, vertex_el = elements["chunk"], elements["vertex"]
    n = len(vertex_el.data)
    if n == 0:
        raise PlyFormatError(path, "holds no Gaussians (the vertex element is empty)")
    if len(chunk_el.data) != -(-n // CHUNK_SIZE):
        raise PlyFormatError(path, f"has {len(chunk_el.data)} chunks; {n} Gaussians need {-(-n // CHUNK_SIZE)} "
                                   f"(one per {CHUNK_SIZE})")
    packed = _fields(path, vertex_el, PACKED_FIELDS, "ui").astype(np.uint32)
    positions, scales = _fields(path, chunk_el, POSITION_FIELDS, "f"), _fields(path, chunk_el, SCALE_FIELDS, "f")
    has_colour_range = "min_r" in (chunk_el.data.dtype.names or ())
    chunk = np.arange(n) // CHUNK_SIZE

    t = _unpack_11_10_11(packed[:, 0])
    means = _lerp(positions[:, :3], positions[:, 3:], t, chunk)
    log_scales = _lerp(scales[:, :3], scales[:, 3:], _unpack_11_10_11(packed[:, 2]), chunk)
    colour_word = packed[:, 3]
    rgba = np.stack([(colour_word >> np.uint32(s)) & np.uint32(255) for s in (24, 16, 8, 0)], axis=1)
    rgb = rgba[:, :3] / 255.0
    if has_colour_range:
        colours = _fields(path, chunk_el, COLOR_FIELDS, "f")
        rgb = _lerp(colours[:, :3], colours[:, 3:], rgb, chunk)
    sh0 = (rgb - 0.5) / SH_C0

    degree, shN = 0, np.zeros((n, 0, 3))
    if "sh" in elements:
        names = elements["sh"].data.dtype.names or ()
        try:
            degree = sh_degree_for_rest(len(names))
        except ValueError as err:
            raise PlyFormatError(path, f"'sh' element: {err}") from err
        if len(elements["sh"].data) != n:
            raise PlyFormatError(path, f"'sh' element has {len(elements['sh'].data)} rows, 'vertex' has {n}")
        codes = _fields(path, elements["sh"], [f"f_rest_{i}" for i in range(len(names))], "u")
        shN = _sh_values(codes).reshape(n, 3, -1).transpose(0, 2, 1)
    params = params_from_arrays(means, log_scales, unpack_rotations(packed[:, 1]), byte_to_opacity(rgba[:, 3]),
                                sh0, shN)
    return params, degree
