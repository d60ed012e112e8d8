"""Niantic ``.spz`` files (github.com/nianticlabs/spz, ``src/cc/load-spz.cc``): quantised
attribute streams, compressed.

Containers. Version 4, what the reference writer writes today (``LATEST_SPZ_HEADER_VERSION``):
a 32-byte header ``magic u32 ("NGSP" = 0x5053474e), version u32, numPoints u32, shDegree u8,
fractionalBits u8, flags u8, numStreams u8, tocByteOffset u32, 12 reserved``, then a table of
``numStreams`` x (compressed size u64, uncompressed size u64), then one zstd frame per stream.
Versions 2 and 3: gzip of a 16-byte header ``magic, version, numPoints, shDegree,
fractionalBits, flags, reserved`` followed by the streams back to back. flags bit 0: the scene
was trained with the antialiased (2D-filter) rasterizer; bit 1: extensions (skipped here).

Streams, in this order (N Gaussians, D = (degree + 1)^2 - 1 SH coefficients per channel)::

    positions  N x 3 x 3 bytes  24-bit signed fixed point, x 2^fractionalBits, little-endian
    alphas     N bytes          round(sigmoid(opacity) 255)
    colours    N x 3 bytes      round(sh0 0.15 255 + 127.5)    (0.15: spz's SH-DC scale, not C0)
    scales     N x 3 bytes      round((log sigma + 10) 16)
    rotations  N x 4 bytes      v3+: smallest three of the unit quaternion in x y z w order
               N x 3 bytes      v2: x y z of the unit quaternion with w >= 0, round(q 127.5 + 127.5)
    sh         N x D x 3 bytes  coefficient-major, channel-minor: round(c 128) + 128, then rounded
                                to a bucket of 2^(8 - bits): 5 bits for band 1, 4 for bands 2-3

Smallest three (v3+): the index of the largest |component| (2 bits, bits 30-31), then for each
other component in x y z w order a sign bit (relative to the largest being positive) and
9 bits of round(511 |q_i| / sqrt(1/2)), the first one highest. The largest is rebuilt as
sqrt(1 - sum of the others' squares).

Values are stored as given (the reference's ``from = UNSPECIFIED``, as splat-transform writes
and reads them): no axis flips between our frame and spz's nominal RUB one. Positions use 12
fractional bits (the reference's) unless the scene's extent needs fewer to fit 24 bits.
"""

from __future__ import annotations

import gzip
import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
from torch import Tensor

from exploregs_plugin.io.packing import (
    SplatArrays,
    byte_to_opacity,
    opacity_to_byte,
    params_from_arrays,
    read_file_bytes,
    splat_arrays,
    unit_quaternions,
    write_file_atomic,
)
from exploregs_plugin.io.ply import MAX_SH_DEGREE, PlyFormatError

MAGIC = 0x5053474E
LATEST_VERSION = 4
READ_VERSIONS = (2, 3, 4)
FRACTIONAL_BITS = 12
COLOR_SCALE = 0.15
SH1_BITS, SH_REST_BITS = 5, 4
FLAG_ANTIALIASED, FLAG_EXTENSIONS = 0x1, 0x2
ZSTD_LEVEL = 12
SQRT1_2 = math.sqrt(0.5)
MAG_MAX = (1 << 9) - 1
LEGACY_HEADER = struct.Struct("<IIIBBBB")       # 16 bytes, gzip containers (v2, v3)
NGSP_HEADER = struct.Struct("<IIIBBBBI12x")     # 32 bytes, zstd container (v4)
TOC_ENTRY = struct.Struct("<QQ")
GZIP_MAGIC = b"\x1f\x8b"
POSITION_MAX = (1 << 23) - 1  # 24-bit two's complement
SPZ_MAX_SH_DEGREE = 4         # the reference reads up to degree 4; bands above 3 are left out here


@dataclass(frozen=True)
class SpzHeader:
    version: int
    num_points: int
    sh_degree: int
    fractional_bits: int
    antialiased: bool


@dataclass
class SpzStreams:
    """The quantised streams of one file (uint8 arrays, one row per Gaussian)."""

    header: SpzHeader
    positions: np.ndarray  # [N, 9]
    alphas: np.ndarray     # [N]
    colors: np.ndarray     # [N, 3]
    scales: np.ndarray     # [N, 3]
    rotations: np.ndarray  # [N, 4] (v3+) or [N, 3] (v2)
    sh: np.ndarray         # [N, D, 3]

    def ordered(self) -> list[np.ndarray]:
        return [self.positions, self.alphas, self.colors, self.scales, self.rotations, self.sh]


def sh_dim(degree: int) -> int:
    return (degree + 1) ** 2 - 1


def stream_sizes(header: SpzHeader) -> list[int]:
    """Bytes of each stream, in file order (the sh stream is 0 bytes at degree 0)."""
    n = header.num_points
    rotation = 3 if header.version == 2 else 4
    return [9 * n, n, 3 * n, 3 * n, rotation * n, 3 * sh_dim(header.sh_degree) * n]


# ----------------------------------------------------------------------------- quantisation
def fractional_bits_for(means: np.ndarray, path: str | Path) -> int:
    """FRACTIONAL_BITS, or fewer where the largest |coordinate| would overflow 24 bits:
    round(|x| 2^bits) <= 2^23 - 1. Error: a position is within 2^-(bits + 1) of its value."""
    peak = float(np.abs(means).max())
    for bits in range(FRACTIONAL_BITS, -1, -1):
        if round(peak * 2.0**bits) <= POSITION_MAX:
            return bits
    raise PlyFormatError(path, f"a coordinate of {peak:g} is beyond the +-{POSITION_MAX} that .spz's "
                               f"24-bit positions hold")


def pack_positions(means: np.ndarray, bits: int) -> np.ndarray:
    """[N, 3] -> [N, 9] uint8: round(x 2^bits) as 24-bit little-endian two's complement."""
    fixed = np.rint(means * 2.0**bits).astype(np.int64).astype("<i4")
    return fixed.view(np.uint8).reshape(-1, 3, 4)[:, :, :3].reshape(-1, 9).copy()


def unpack_positions(packed: np.ndarray, bits: int) -> np.ndarray:
    b = packed.reshape(-1, 3, 3).astype(np.int64)
    fixed = b[..., 0] | (b[..., 1] << 8) | (b[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)  # sign extension
    return fixed.astype(np.float64) * 2.0**-bits


def pack_smallest_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz (any norm) -> [N, 4] uint8, the little-endian u32 described above."""
    q = unit_quaternions(quats_wxyz)[:, [1, 2, 3, 0]]  # spz orders x y z w
    rows = np.arange(q.shape[0])
    largest = np.argmax(np.abs(q), axis=1)  # first of equals, as the reference's strict '>'
    negate = q[rows, largest] < 0           # -q is the same rotation: make the largest positive
    comp = largest.astype(np.uint32)
    for i in range(4):
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        # |q_i| <= sqrt(1/2) for every component but the largest; clip guards rounding above it
        mag = np.clip(np.floor(MAG_MAX * np.abs(q[:, i]) / SQRT1_2 + 0.5), 0, MAG_MAX).astype(np.uint32)
        comp = np.where(largest != i, (comp << np.uint32(10)) | (negbit << np.uint32(9)) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def unpack_smallest_three(packed: np.ndarray) -> np.ndarray:
    """[N, 4] uint8 -> [N, 4] wxyz unit quaternions."""
    comp = np.ascontiguousarray(packed).view("<u4").reshape(-1).astype(np.uint32)
    largest = comp >> np.uint32(30)
    q = np.zeros((comp.shape[0], 4))
    for i in range(3, -1, -1):  # the last component packed sits in the lowest bits
        other = largest != i
        value = SQRT1_2 * (comp & np.uint32(MAG_MAX)).astype(np.float64) / MAG_MAX
        q[:, i] = np.where(other, np.where((comp >> np.uint32(9)) & np.uint32(1), -value, value), 0.0)
        comp = np.where(other, comp >> np.uint32(10), comp)
    rest = (q * q).sum(axis=1)
    q[np.arange(q.shape[0]), largest] = np.sqrt(np.maximum(0.0, 1.0 - rest))
    return q[:, [3, 0, 1, 2]]


def pack_first_three(quats_wxyz: np.ndarray) -> np.ndarray:
    """v2: [N, 4] wxyz -> [N, 3] uint8 of x y z of the unit quaternion with w >= 0."""
    q = unit_quaternions(quats_wxyz)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    return np.clip(np.rint(q[:, 1:] * 127.5 + 127.5), 0, 255).astype(np.uint8)


def unpack_first_three(packed: np.ndarray) -> np.ndarray:
    xyz = packed.astype(np.float64) / 127.5 - 1.0
    w = np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(axis=1, keepdims=True)))
    return np.concatenate([w, xyz], axis=1)


def quantize_sh(coefficients: np.ndarray, sh_bits: tuple[int, int] = (SH1_BITS, SH_REST_BITS)) -> np.ndarray:
    """[N, D, 3] -> uint8: round(c 128) + 128, then to the nearest multiple of the band's bucket
    2^(8 - bits) (``sh_bits``: band 1's bits and bands 2-3's; the reference's 5 and 4 give buckets
    8 and 16), clamped to 0..255. Decoded (byte - 128) / 128: the file keeps 8 bits whatever the
    bucket, coarser buckets only compress better, so any reader reads any choice."""
    if not all(1 <= bits <= 8 for bits in sh_bits):
        raise ValueError(f"spz SH bits must be in 1..8, got {sh_bits}")
    q = np.rint(coefficients * 128.0) + 128.0
    bucket = np.full(coefficients.shape[1], float(1 << (8 - sh_bits[1])))
    bucket[:3] = 1 << (8 - sh_bits[0])
    bucket = bucket[None, :, None]
    return np.clip(np.floor((q + bucket // 2) / bucket) * bucket, 0, 255).astype(np.uint8)


def encode_spz(a: SplatArrays, path: str | Path, antialiased: bool, version: int,
               sh_bits: tuple[int, int] = (SH1_BITS, SH_REST_BITS)) -> SpzStreams:
    """Validated arrays -> the quantised streams of a file of ``version``."""
    bits = fractional_bits_for(a.means, path)
    header = SpzHeader(version, a.count, a.sh_degree, bits, antialiased)
    colors = np.clip(np.rint(a.sh0 * (COLOR_SCALE * 255.0) + 127.5), 0, 255).astype(np.uint8)
    scales = np.clip(np.rint((a.scales + 10.0) * 16.0), 0, 255).astype(np.uint8)
    rotations = pack_first_three(a.quats) if version == 2 else pack_smallest_three(a.quats)
    return SpzStreams(header, pack_positions(a.means, bits), opacity_to_byte(a.opacities), colors, scales,
                      rotations, quantize_sh(a.shN, sh_bits))


def decode_spz(s: SpzStreams) -> tuple[dict[str, Tensor], int]:
    """Streams -> (raw float32 parameters, SH degree; a degree-4 file gives its bands 1-3)."""
    h = s.header
    quats = unpack_first_three(s.rotations) if h.version == 2 else unpack_smallest_three(s.rotations)
    degree = min(h.sh_degree, MAX_SH_DEGREE)
    sh = (s.sh[:, :sh_dim(degree)].astype(np.float64) - 128.0) / 128.0
    params = params_from_arrays(unpack_positions(s.positions, h.fractional_bits),
                                s.scales.astype(np.float64) / 16.0 - 10.0, quats, byte_to_opacity(s.alphas),
                                (s.colors.astype(np.float64) / 255.0 - 0.5) / COLOR_SCALE, sh)
    return params, degree


# ----------------------------------------------------------------------------- containers
def _zstd(path: str | Path):
    try:
        import zstandard  # viser's dependency, so installed with the package
    except ImportError as err:
        raise PlyFormatError(path, ".spz version 4 is zstd-compressed and needs the zstandard package "
                                   "(pip install zstandard)") from err
    return zstandard


def container_bytes(s: SpzStreams, path: str | Path) -> bytes:
    h = s.header
    flags = FLAG_ANTIALIASED if h.antialiased else 0
    payload = [np.ascontiguousarray(stream).tobytes() for stream in s.ordered()]
    if h.version < 4:
        header = LEGACY_HEADER.pack(MAGIC, h.version, h.num_points, h.sh_degree, h.fractional_bits, flags, 0)
        # mtime 0: the same scene gives the same bytes
        return gzip.compress(header + b"".join(payload), compresslevel=6, mtime=0)
    compressor = _zstd(path).ZstdCompressor(level=ZSTD_LEVEL)
    frames = [(compressor.compress(part), len(part)) for part in payload if part]  # no empty stream
    header = NGSP_HEADER.pack(MAGIC, h.version, h.num_points, h.sh_degree, h.fractional_bits, flags,
                              len(frames), NGSP_HEADER.size)
    toc = b"".join(TOC_ENTRY.pack(len(frame), size) for frame, size in frames)
    return header + toc + b"".join(frame for frame, _ in frames)


def _check_header(path: str | Path, version: int, num_points: int, sh_degree: int, fractional_bits: int,
                  flags: int) -> SpzHeader:
    if version not in READ_VERSIONS:
        raise PlyFormatError(path, f".spz version {version} is not supported (reads versions "
                                   f"{', '.join(map(str, READ_VERSIONS))})")
    if num_points == 0:
        raise PlyFormatError(path, "holds no Gaussians (numPoints is 0)")
    if sh_degree > SPZ_MAX_SH_DEGREE:
        raise PlyFormatError(path, f"SH degree {sh_degree} is beyond .spz's {SPZ_MAX_SH_DEGREE}")
    if fractional_bits > 23:
        raise PlyFormatError(path, f"{fractional_bits} fractional bits leave no integer part in 24-bit positions")
    return SpzHeader(version, num_points, sh_degree, fractional_bits, bool(flags & FLAG_ANTIALIASED))


def _split(header: SpzHeader, parts: list[bytes]) -> SpzStreams:
    n, d = header.num_points, sh_dim(header.sh_degree)
    shapes = [(n, 9), (n,), (n, 3), (n, 3), (n, 3 if header.version == 2 else 4), (n, d, 3)]
    arrays = [np.frombuffer(part, dtype=np.uint8).reshape(shape) for part, shape in zip(parts, shapes)]
    return SpzStreams(header, *arrays)


def _legacy_streams(path: str | Path, data: bytes) -> SpzStreams:
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as err:
        raise PlyFormatError(path, f"gzip data is damaged or truncated ({err})") from err
    if len(raw) < LEGACY_HEADER.size:
        raise PlyFormatError(path, f"holds {len(raw)} bytes after gunzip, fewer than the "
                                   f"{LEGACY_HEADER.size}-byte header")
    magic, version, n, degree, bits, flags, _ = LEGACY_HEADER.unpack_from(raw)
    if magic != MAGIC:
        raise PlyFormatError(path, f"gzip content starts with 0x{magic:08x}, not the .spz magic 0x{MAGIC:08x} (NGSP)")
    header = _check_header(path, version, n, degree, bits, flags)
    if version >= 4:
        raise PlyFormatError(path, f"version {version} inside a gzip container; version 4 files are not gzipped")
    sizes = stream_sizes(header)
    end = LEGACY_HEADER.size + sum(sizes)
    if len(raw) < end or (len(raw) > end and not flags & FLAG_EXTENSIONS):
        raise PlyFormatError(path, f"payload is {len(raw) - LEGACY_HEADER.size} bytes; {n} Gaussians of SH "
                                   f"degree {degree} (version {version}) need {end - LEGACY_HEADER.size}")
    offsets = np.cumsum([LEGACY_HEADER.size, *sizes])
    return _split(header, [raw[offsets[i]:offsets[i + 1]] for i in range(len(sizes))])


def _ngsp_streams(path: str | Path, data: bytes) -> SpzStreams:
    if len(data) < NGSP_HEADER.size:
        raise PlyFormatError(path, f"is {len(data)} bytes, shorter than the {NGSP_HEADER.size}-byte .spz header")
    _, version, n, degree, bits, flags, count, toc_at = NGSP_HEADER.unpack_from(data)  # magic checked by the caller
    header = _check_header(path, version, n, degree, bits, flags)
    if version < 4:
        raise PlyFormatError(path, f"version {version} without gzip; versions 2 and 3 are gzip-compressed")
    sizes = [size for size in stream_sizes(header) if size]
    if count != len(sizes):
        raise PlyFormatError(path, f"has {count} streams; SH degree {degree} needs {len(sizes)}")
    start = toc_at + count * TOC_ENTRY.size
    if toc_at < NGSP_HEADER.size or start > len(data):
        raise PlyFormatError(path, f"table of streams at byte {toc_at} is outside the file ({len(data)} bytes)")
    entries = [TOC_ENTRY.unpack_from(data, toc_at + i * TOC_ENTRY.size) for i in range(count)]
    if start + sum(c for c, _ in entries) != len(data):
        raise PlyFormatError(path, f"streams take {sum(c for c, _ in entries)} bytes, the file has "
                                   f"{len(data) - start} after the table (truncated?)")
    zstandard = _zstd(path)
    decompressor, parts, at = zstandard.ZstdDecompressor(), [], start
    for (compressed, size), expected in zip(entries, sizes):
        if size != expected:
            raise PlyFormatError(path, f"a stream holds {size} bytes, {expected} expected for {n} Gaussians")
        try:
            frame = data[at:at + compressed]
            # a frame that claims another size is refused before anything that size is allocated
            claimed = zstandard.get_frame_parameters(frame).content_size
            if claimed not in (expected, zstandard.CONTENTSIZE_UNKNOWN):
                raise PlyFormatError(path, f"zstd stream at byte {at} claims {claimed} bytes, {expected} expected")
            part = decompressor.decompress(frame, max_output_size=expected)
        except zstandard.ZstdError as err:
            raise PlyFormatError(path, f"zstd stream at byte {at} is damaged ({err})") from err
        if len(part) != expected:
            raise PlyFormatError(path, f"zstd stream at byte {at} gives {len(part)} bytes, {expected} expected")
        parts.append(part)
        at += compressed
    if not header.sh_degree:
        parts.append(b"")
    return _split(header, parts)


def read_spz_streams(path: Path) -> SpzStreams:
    """The quantised streams of an .spz file (v2, v3 gzip; v4 zstd); bad files raise PlyFormatError."""
    path = Path(path)
    data = read_file_bytes(path, "an .spz file")
    if data[:2] == GZIP_MAGIC:
        return _legacy_streams(path, data)
    if len(data) >= 4 and struct.unpack_from("<I", data)[0] == MAGIC:
        return _ngsp_streams(path, data)
    raise PlyFormatError(path, f"starts with {data[:4].hex()}: neither gzip (1f8b, .spz v2-3) nor NGSP (.spz v4)")


# ----------------------------------------------------------------------------- files
def write_spz(path: Path, params: Mapping[str, Tensor], *, antialiased: bool = False,
              version: int = LATEST_VERSION, sh_bits: tuple[int, int] = (SH1_BITS, SH_REST_BITS)) -> int:
    """Write raw parameters (already in the frame to store, all finite) as an .spz file of
    ``version`` (4: zstd, the reference's current; 3: gzip, for readers that predate 4; 2: gzip
    with 3-byte rotations). ``antialiased``: set the header's flag. ``sh_bits``: bits kept of
    each SH coefficient of band 1 and of bands 2-3 (see :func:`quantize_sh`). Returns the bytes written."""
    path = Path(path)
    if version not in READ_VERSIONS:
        raise ValueError(f"spz version must be one of {READ_VERSIONS}, got {version}")
    streams = encode_spz(splat_arrays(params, path), path, antialiased, version, sh_bits)
    return write_file_atomic(path, [container_bytes(streams, path)])


def read_spz(path: Path) -> tuple[dict[str, Tensor], int]:
    """Read an .spz file (versions 2-4) -> (raw float32 parameters, SH degree)."""
    return decode_spz(read_spz_streams(path))


def spz_header(path: Path) -> SpzHeader:
    """The header of an .spz file (version, count, SH degree, fractional bits, antialiased flag)."""
    return read_spz_streams(path).header
