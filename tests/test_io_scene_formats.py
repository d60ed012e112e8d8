"""Web splat formats (.splat, .spz, PlayCanvas compressed PLY): round trips within each format's
quantisation bounds, the dispatcher's format choice, bad files, and eg-export / eg-render on them.

Every bound below is derived from the format's quantisation (equation in the comment); values
are compared after the clamping the format does, quaternions up to sign.
"""

import gzip
import math
import struct

import numpy as np
import pytest
import torch
from PIL import Image
from plyfile import PlyData, PlyElement

from exploregs_plugin.io import compressed_ply as CP
from exploregs_plugin.io import spz as SPZ
from exploregs_plugin.io.ply import PlyFormatError, read_ply
from exploregs_plugin.io.scene_files import format_for, read_scene, write_scene
from exploregs_plugin.rasterizer.sh import SH_C0
from exploregs_plugin.runs import load_run
from exploregs_plugin.runs.scene import dataset_normalization
from exploregs_plugin.scripts import export as export_script
from exploregs_plugin.scripts import render as render_script
from exploregs_plugin.engine.trainer import TrainerConfig

F32_EPS = float(np.finfo(np.float32).eps)  # 2^-23: a float32 result is within |x| 2^-24 of its float64 value


# ----------------------------------------------------------------------------- bounds
def quat_angle_bound(dq: float) -> float:
    """Rotation angle bound for unit quaternions at 4-vector distance <= dq: two unit vectors at
    angle phi are 2 sin(phi / 2) apart and the rotation angle is 2 phi, so angle <= 4 asin(dq / 2)."""
    return 4.0 * math.asin(min(1.0, dq / 2.0))


def smallest_three_bound(delta: float) -> float:
    """Angle bound of a smallest-three code whose three small components are each within delta.

    |ds| <= sqrt(3) delta. The largest component l >= 1/2 (the largest of four squares summing
    to 1 is >= 1/4), so |s| <= sqrt(3)/2, and the rebuilt l' = sqrt(1 - |s'|^2) differs by
    ||s'|^2 - |s|^2| / (l + l') <= 2 |ds| (2 |s| + |ds|) <= 2 |ds| (sqrt(3) + |ds|).
    """
    ds = math.sqrt(3.0) * delta
    dl = 2.0 * ds * (math.sqrt(3.0) + ds)
    return quat_angle_bound(math.hypot(ds, dl))


# .splat: each component round(q 128 + 128) / 128 - 1 is within 0.5/128 of q, or 1/128 for the
# one component > 255/256 that clamps at 255; |e| <= sqrt((1/128)^2 + 3 (0.5/128)^2) = sqrt(7)/256,
# and the normalised decode is at angle phi <= asin(|e|) from q: rotation angle <= 2 asin(sqrt(7)/256)
SPLAT_ANGLE = 2.0 * math.asin(math.sqrt(7.0) / 256.0)
# spz v3/v4: 9-bit magnitudes of |q_i| / sqrt(1/2): each small component within sqrt(1/2) 0.5/511
SPZ_ANGLE = smallest_three_bound(math.sqrt(0.5) * 0.5 / 511)
# compressed PLY: 10-bit unorm of q sqrt(1/2) + 0.5, decoded (u - 0.5) / sqrt(1/2): within 0.5/1023 / sqrt(1/2)
CPLY_ANGLE = smallest_three_bound(0.5 / 1023 / math.sqrt(0.5))


def spz_v2_angle() -> float:
    """spz v2 stores x y z as round(q 127.5 + 127.5) (|dx| <= sqrt(3) 0.5/127.5) and rebuilds
    w = sqrt(1 - |x|^2): |dw| <= sqrt(||x'|^2 - |x|^2|) <= sqrt(|dx| (2 + |dx|))."""
    dx = math.sqrt(3.0) * 0.5 / 127.5
    return quat_angle_bound(math.hypot(dx, math.sqrt(dx * (2.0 + dx))))


ALPHA = 0.5 / 255 + 1e-6  # |sigmoid(o') - sigmoid(o)|: round(p 255) / 255, ends decoded mid-interval; + float32


# ----------------------------------------------------------------------------- scenes
def random_params(n: int, degree: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * 4.0,
        "scales": torch.randn(n, 3, generator=g) * 1.5 - 3.0,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, generator=g) * 4.0,
        "sh0": torch.randn(n, 1, 3, generator=g) * 1.5,
        "shN": torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g) * 0.4,
    }


def hard_params(degree: int) -> dict[str, torch.Tensor]:
    """Rows at the edges of every format: log-scales whose exp is 0 or inf in float32 (+-100)
    and beyond every format's range (+-30), opacity logits +-20, quaternions unnormalised
    (x 1e3, x 1e-3), zero, with w < 0 and with equal components, colours and SH far outside
    the stored ranges. Positions on a grid (distinct, so rows can be matched)."""
    p = random_params(300, degree, seed=7)
    grid = torch.stack(torch.meshgrid(*[torch.arange(7.0)] * 3, indexing="ij"), -1).reshape(-1, 3)[:300]
    p["means"] = grid * 0.75 - 2.0
    p["scales"][:8] = torch.tensor([[-100.0] * 3, [100.0] * 3, [-30.0] * 3, [30.0] * 3, [-100.0, 0.0, 100.0],
                                    [-87.0, 88.0, 0.0], [-10.0, 5.9, -20.0], [20.0, -20.0, 0.0]])
    p["opacities"][:6] = torch.tensor([20.0, -20.0, 0.0, 60.0, -60.0, 5.5])
    p["quats"][:8] = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1e3, 2e3, -3e3, 1e3], [1e-3, 0.0, 0.0, -1e-3],
                                   [-1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.5], [-0.5, 0.5, -0.5, 0.5],
                                   [0.0, 1.0, 0.0, 0.0], [1e-30, 0.0, 0.0, 0.0]])
    p["sh0"][:4] = torch.tensor([[[40.0, -40.0, 0.0]], [[3.4, -3.4, 1.7]], [[-1.7725, 1.7725, 0.0]],
                                 [[100.0, 100.0, 100.0]]])
    if degree:
        p["shN"][:3] = torch.tensor([5.0, -5.0, 0.99])[:, None, None]
    return p


def nan_rows(params: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], int]:
    """A copy with non-finite values in three rows (two parameters and an inf)."""
    bad = {k: v.clone() for k, v in params.items()}
    bad["means"][10, 1] = float("nan")
    bad["quats"][11, 2] = float("nan")
    bad["opacities"][12] = float("inf")
    return bad, 3


def unit(q: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    out = np.where(norm > 1e-12, q, np.array([[1.0, 0.0, 0.0, 0.0]]))
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def rotation_angles(q: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Rotation angle between quaternions (any norm; zero = identity), up to sign: 4 asin(d / 2)."""
    a, b = unit(q.astype(np.float64)), unit(q2.astype(np.float64))
    d = np.minimum(np.linalg.norm(a - b, axis=1), np.linalg.norm(a + b, axis=1))
    return 4.0 * np.arcsin(np.minimum(1.0, d / 2.0))


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def match_rows(expected_means: np.ndarray, got_means: np.ndarray, tolerance: np.ndarray | float) -> np.ndarray:
    """Index of the expected row each decoded row is (decoded rows may be reordered): the
    nearest position, which must be within ``tolerance`` and one-to-one."""
    d = np.linalg.norm(got_means[:, None, :].astype(np.float64) - expected_means[None].astype(np.float64), axis=2)
    index = d.argmin(axis=1)
    assert len(set(index.tolist())) == len(index) == len(expected_means), "rows do not match one to one"
    assert (d[np.arange(len(index)), index] <= tolerance).all()
    return index


def np_params(params) -> dict[str, np.ndarray]:
    return {k: v.detach().double().numpy() for k, v in params.items()}


def check_common(exp: dict, got: dict, angle: float) -> None:
    """Opacity and rotation, bounded the same way by every packed format."""
    assert (np.abs(sigmoid(got["opacities"]) - sigmoid(exp["opacities"])) <= ALPHA).all()
    assert (rotation_angles(got["quats"], exp["quats"]) <= angle).all()


# ----------------------------------------------------------------------------- per format
def check_splat(exp: dict, got: dict) -> None:
    assert got["shN"].shape[1] == 0
    # positions: float32 as given
    assert np.array_equal(got["means"], exp["means"])
    # scales: exp of the log clipped to [-87, 88] rounded to float32 (relative 2^-24, so the log
    # within 2^-24) and the decoded log rounded to float32 (half an ulp: |log| 2^-24)
    clipped = np.clip(exp["scales"], -87.0, 88.0)
    assert (np.abs(got["scales"] - clipped) <= F32_EPS * (1.0 + np.abs(clipped))).all()
    # colour: round(clamp(0.5 + C0 sh0, 0, 1) 255) / 255, within 0.5/255 of the clamped colour
    colour = np.clip(0.5 + SH_C0 * exp["sh0"], 0.0, 1.0)
    assert (np.abs(0.5 + SH_C0 * got["sh0"] - colour) <= 0.5 / 255 + 1e-6).all()
    check_common(exp, got, SPLAT_ANGLE)


def check_spz(exp: dict, got: dict, header: SPZ.SpzHeader) -> None:
    # positions: round(x 2^bits) 2^-bits, exact in float32 (|integer| < 2^24): within 2^-(bits + 1)
    assert (np.abs(got["means"] - exp["means"]) <= 2.0 ** -(header.fractional_bits + 1)).all()
    # log-scales: round((l + 10) 16) / 16 - 10 for l in [-10, 5.9375] (bytes 0..255): within 1/32
    assert (np.abs(got["scales"] - np.clip(exp["scales"], -10.0, 255 / 16 - 10.0)) <= 1 / 32).all()
    # colour: round(sh0 0.15 255 + 127.5), sh0 clamped to +-0.5/0.15: within 0.5 / (0.15 255), + float32
    limit = 0.5 / SPZ.COLOR_SCALE
    assert (np.abs(got["sh0"] - np.clip(exp["sh0"], -limit, limit)) <= 0.5 / (0.15 * 255) + 1e-6).all()
    # SH: round(c 128) to a bucket b (8 for band 1, 16 above) in [0, 255]: for c in [-1, 127/128]
    # within (0.5 + b / 2) / 128
    if exp["shN"].shape[1]:
        bucket = np.full(exp["shN"].shape[1], 16.0)
        bucket[:3] = 8.0
        bound = ((0.5 + bucket / 2) / 128)[None, :, None]
        assert (np.abs(got["shN"] - np.clip(exp["shN"], -1.0, 127 / 128)) <= bound + 1e-7).all()
    check_common(exp, got, spz_v2_angle() if header.version == 2 else SPZ_ANGLE)


def chunk_table(path) -> dict[str, np.ndarray]:
    chunk = PlyData.read(str(path))["chunk"].data
    return {name: np.repeat(np.asarray(chunk[name], np.float64), CP.CHUNK_SIZE) for name in chunk.dtype.names}


def check_compressed(exp: dict, got: dict, path) -> None:
    """Rows of ``got`` in file order; ``exp`` already matched to them."""
    n = got["means"].shape[0]
    table = {k: v[:n] for k, v in chunk_table(path).items()}

    def within(value, expected, lo, hi, bits):
        # round(t (2^b - 1)) of t = (v - lo) / (hi - lo): within (hi - lo) 0.5 / (2^b - 1), + float32
        bound = (hi - lo) * 0.5 / ((1 << bits) - 1) + F32_EPS * (1.0 + np.abs(expected))
        assert (np.abs(value - expected) <= bound).all()

    for axis, name, bits in ((0, "x", 11), (1, "y", 10), (2, "z", 11)):
        within(got["means"][:, axis], exp["means"][:, axis], table[f"min_{name}"], table[f"max_{name}"], bits)
        # log-scales clamped to [-20, 20] by the chunk range
        within(got["scales"][:, axis], np.clip(exp["scales"][:, axis], -20.0, 20.0),
               table[f"min_scale_{name}"], table[f"max_scale_{name}"], bits)
    for c, name in enumerate("rgb"):  # colour 0.5 + C0 sh0 in 8 bits of the chunk's range
        within(0.5 + SH_C0 * got["sh0"][:, 0, c], 0.5 + SH_C0 * exp["sh0"][:, 0, c], table[f"min_{name}"],
               table[f"max_{name}"], 8)
    # SH: floor((c / 8 + 0.5) 256) decoded mid-byte (ends at -4 and 4): within 1/32 of c clamped to [-4, 4]
    assert (np.abs(got["shN"] - np.clip(exp["shN"], -4.0, 4.0)) <= 1 / 32 + 1e-6).all()
    check_common(exp, got, CPLY_ANGLE)


def read_back(path, params) -> tuple[dict, dict, int]:
    """Write ``params`` with write_scene, read with read_scene: (expected rows matched to the
    decoded ones, decoded, decoded SH degree). Every format stores positions to well under the
    grid's 0.75 spacing (compressed PLY: a chunk's range / 2046; spz: 2^-13)."""
    written = write_scene(path, params)
    scene = read_scene(path)
    assert scene.num_gaussians == written.written == params["means"].shape[0] and scene.dropped == 0
    assert written.size_bytes == path.stat().st_size
    exp, got = np_params(params), np_params(scene.params)
    index = match_rows(exp["means"], got["means"], 0.05)
    return {k: v[index] for k, v in exp.items()}, got, scene.sh_degree


def scene_for(kind: str, degree: int) -> dict[str, torch.Tensor]:
    return random_params(600, degree, seed=degree) if kind == "random" else hard_params(degree)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("kind", ["random", "hard"])
def test_splat_round_trips_within_its_quantisation_in_importance_order(tmp_path, degree, kind):
    exp, got, read_degree = read_back(tmp_path / "s.splat", scene_for(kind, degree))
    assert read_degree == 0 and (tmp_path / "s.splat").stat().st_size == 32 * len(exp["means"])
    check_splat(exp, got)
    # file order: volume x opacity, exp(s0 + s1 + s2) sigmoid(o), descending; as a log (sigmoid(-60)
    # underflows a tanh-based sigmoid): s0 + s1 + s2 - log(1 + exp(-o))
    importance = exp["scales"].sum(axis=1) - np.logaddexp(0.0, -exp["opacities"])
    assert np.all(np.diff(importance) <= 1e-9)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("kind", ["random", "hard"])
@pytest.mark.parametrize("version", [4, 3, 2])
def test_spz_round_trips_within_its_quantisation(tmp_path, degree, kind, version):
    params = scene_for(kind, degree)
    path = tmp_path / "s.spz"
    size = SPZ.write_spz(path, params, version=version)
    header = SPZ.spz_header(path)
    assert size == path.stat().st_size
    assert header == SPZ.SpzHeader(version, params["means"].shape[0], degree, SPZ.FRACTIONAL_BITS, False)
    raw = path.read_bytes()
    # v4: the NGSP header in the clear; v2, v3: gzip of the 16-byte header
    assert raw[:4] == b"NGSP" if version == 4 else gzip.decompress(raw)[:8] == struct.pack("<II", SPZ.MAGIC, version)
    got, got_degree = read_scene(path), SPZ.read_spz(path)[1]
    assert got_degree == got.sh_degree == degree
    check_spz(np_params(params), np_params(got.params), header)  # spz keeps the order


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("kind", ["random", "hard"])
def test_compressed_ply_round_trips_within_its_quantisation(tmp_path, degree, kind):
    path = tmp_path / "s.compressed.ply"
    exp, got, read_degree = read_back(path, scene_for(kind, degree))
    assert read_degree == degree
    check_compressed(exp, got, path)
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["chunk", "vertex", "sh"][:3 if degree else 2]
    assert [p.name for p in ply["vertex"].properties] == list(CP.PACKED_FIELDS)
    assert {p.val_dtype for p in ply["vertex"].properties} == {"u4"}
    assert len(ply["chunk"].data) == -(-len(exp["means"]) // 256)


def test_compressed_ply_is_in_morton_order(tmp_path):
    """Rows go along the Z-order curve of the scene's box at 21 bits per axis: cell c_a =
    floor((x_a - min_a) / extent_a (2^21 - 1)), code = sum over bits b of bit b of c_a at 3 b + a."""
    params = random_params(2000, 0, seed=3)
    path = tmp_path / "s.compressed.ply"
    write_scene(path, params)
    means = params["means"].double().numpy()
    cells = np.floor((means - means.min(axis=0)) / (means.max(axis=0) - means.min(axis=0)) * (2 ** 21 - 1))
    cells = cells.astype(np.uint64)
    code = np.zeros(len(means), dtype=np.uint64)
    for bit in range(21):
        for axis in range(3):
            code |= ((cells[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    file_rows = match_rows(means, read_scene(path).params["means"].double().numpy(), 0.05)
    assert np.array_equal(file_rows, np.argsort(code, kind="stable"))
    # so each chunk of 256 is compact: its box is a fraction of the scene's (about 1 for any order)
    chunk = chunk_table(path)
    volume = np.prod([chunk[f"max_{a}"] - chunk[f"min_{a}"] for a in "xyz"], axis=0)[::256]
    assert volume[:-1].mean() < 0.5 * np.prod(means.max(axis=0) - means.min(axis=0))


def test_smallest_three_codes_round_trip_exactly_at_the_edges():
    """Quaternions with a component at 0, +-1 or equal magnitudes: decode is the same rotation."""
    edge = np.array([[1, 0, 0, 0], [0, 0, 0, -1], [0.5, -0.5, 0.5, -0.5], [1, 1, 0, 0], [0, 0, 0, 0],
                     [-1, -1, -1, 1e-9]], dtype=np.float64)
    for pack, unpack, bound in ((SPZ.pack_smallest_three, SPZ.unpack_smallest_three, SPZ_ANGLE),
                                (CP.pack_rotations, CP.unpack_rotations, CPLY_ANGLE)):
        decoded = unpack(pack(edge))
        assert np.allclose(np.linalg.norm(decoded, axis=1), 1.0)
        assert (rotation_angles(decoded, edge) <= bound).all()


def test_nonfinite_rows_are_dropped_and_counted_in_every_format(tmp_path):
    params, bad = nan_rows(random_params(50, 1, seed=4))
    for name in ("s.ply", "s.splat", "s.spz", "s.compressed.ply"):
        result = write_scene(tmp_path / name, params)
        assert (result.written, result.dropped) == (50 - bad, bad)
        scene = read_scene(tmp_path / name)
        assert scene.num_gaussians == 50 - bad and torch.isfinite(scene.params["means"]).all()


def test_frames_are_mapped_as_for_a_ply(tmp_path):
    """write_scene maps to the original frame, read_scene back into the normalised one."""
    t, s = np.array([1.5, -2.0, 0.25]), 0.125
    params = random_params(300, 2, seed=5)
    for name in ("s.ply", "s.spz", "s.splat"):
        write_scene(tmp_path / name, params, (t, s))
        raw = read_scene(tmp_path / name)  # original frame: x / s - t, log sigma - log s
        back = read_scene(tmp_path / name, (t, s))
        index = match_rows(params["means"].double().numpy(), back.params["means"].double().numpy(), 0.01)
        means, scales = back.params["means"].double().numpy(), back.params["scales"].double().numpy()
        original = params["means"].double().numpy()[index] / s - t
        # spz: positions within 2^-13 in the original frame, 2^-13 s in the normalised one; the
        # others: float32 rounding of x / s - t and back
        tol = 2.0 ** -13 * s + 1e-6 if name.endswith(".spz") else 1e-5
        assert np.abs(means - params["means"].double().numpy()[index]).max() <= tol
        assert np.abs(raw.params["means"].double().numpy() - original).max() <= tol / s
        if name != "s.spz":  # spz log-scales in 1/16 steps; the others carry them to float32
            assert np.abs(scales - params["scales"].double().numpy()[index]).max() <= 1e-5


def test_format_for_reads_the_suffix_and_checks_an_explicit_format(tmp_path):
    assert [format_for(f"a{suffix}") for suffix in (".ply", ".PLY", ".compressed.ply", ".splat", ".spz")] == \
        ["ply", "ply", "compressed-ply", "splat", "spz"]
    assert format_for("a.ply", "compressed-ply") == "compressed-ply"  # a compressed PLY may end in .ply
    assert format_for("scene.bin", "spz") == "spz" and format_for("scene.bin", default="ply") == "ply"
    for path, fmt, message in (("a.splat", "spz", "format spz does not match the suffix, which names splat"),
                               ("a.compressed.ply", "ply", "format ply does not match the suffix, which names "
                                                           "compressed-ply"),
                               ("a.spz", "ply", "format ply does not match")):
        with pytest.raises(PlyFormatError, match=message) as err:
            format_for(path, fmt)
        assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)
    with pytest.raises(PlyFormatError, match="scene.bin: cannot tell the scene format from the name"):
        format_for("scene.bin")
    with pytest.raises(ValueError, match="unknown scene format 'web'"):
        format_for("a.ply", "web")


def test_a_compressed_ply_named_ply_reads_and_antialiased_is_recorded(tmp_path):
    params = random_params(40, 3, seed=6)
    path = tmp_path / "scene.ply"
    result = write_scene(path, params, fmt="compressed-ply", antialiased=True, comments=["hello"])
    assert result.format == "compressed-ply"
    scene = read_scene(path)  # by content: the header has chunk / packed_* properties
    assert scene.num_gaussians == 40 and scene.sh_degree == 3
    assert PlyData.read(str(path)).comments[1:] == ["hello", "SplatRenderMode: mip"]
    with pytest.raises(PlyFormatError, match="compressed"):
        read_ply(path)  # the PLY-only reader still refuses it; read_scene routes it
    write_scene(tmp_path / "aa.spz", params, antialiased=True)
    write_scene(tmp_path / "plain.spz", params)
    assert SPZ.spz_header(tmp_path / "aa.spz").antialiased and not SPZ.spz_header(tmp_path / "plain.spz").antialiased
    with pytest.raises(PlyFormatError, match="ASCII"):
        write_scene(tmp_path / "a.spz", params, text=True)


def test_bad_files_give_one_clear_error_naming_the_file(tmp_path):
    params = random_params(300, 1, seed=8)
    good = {name: tmp_path / name for name in ("g.splat", "g.spz", "g.compressed.ply")}
    for path in good.values():
        write_scene(path, params)
    SPZ.write_spz(tmp_path / "g3.spz", params, version=3)
    splat, spz, spz3, cply = (good["g.splat"].read_bytes(), good["g.spz"].read_bytes(),
                              (tmp_path / "g3.spz").read_bytes(), good["g.compressed.ply"].read_bytes())
    legacy = gzip.decompress(spz3)
    cases = {
        "short.splat": (splat[:-5], "is not a multiple of 32"),
        "empty.splat": (b"", "is empty"),
        "magic.spz": (b"XXXX" + spz[4:], "neither gzip"),
        "cut.spz": (spz[:-100], "truncated"),
        "cut3.spz": (spz3[:len(spz3) // 2], "gzip data is damaged or truncated"),
        "magic3.spz": (gzip.compress(b"ABCD" + legacy[4:]), "not the .spz magic"),
        "version.spz": (gzip.compress(legacy[:4] + struct.pack("<I", 9) + legacy[8:]), "version 9 is not supported"),
        "short3.spz": (gzip.compress(legacy[:-7]), "need"),
        "count.spz": (spz[:8] + struct.pack("<I", 301) + spz[12:], "a stream holds"),
        "zero.spz": (spz[:8] + struct.pack("<I", 0) + spz[12:], "holds no Gaussians"),
        "v1.spz": (gzip.compress(legacy[:4] + struct.pack("<I", 1) + legacy[8:]), "version 1 is not supported"),
        "junk.spz": (spz[:40] + b"\0" * 200, "streams take"),
        "cut.compressed.ply": (cply[:len(cply) // 2], "not a readable PLY file"),
        "chunks.ply": (cply.replace(b"element chunk 2", b"element chunk 1", 1), "has 1 chunks; 300 Gaussians need 2"),
        "text.splat": (b"hello world, not a splat at all!", None),  # 32 bytes: a .splat cannot be told from noise
        "nothing.bin": (b"\x00" * 64, "is not a scene file"),
    }
    for name, (data, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        if message is None:
            assert read_scene(path, keep_nonfinite=True).num_gaussians == 1
            continue
        with pytest.raises(PlyFormatError) as err:
            read_scene(path)
        text = str(err.value)
        assert text.startswith(f"{path}: ") and message in text and "\n" not in text, (name, text)
    with pytest.raises(PlyFormatError, match="missing.spz: file not found"):
        read_scene(tmp_path / "missing.spz")
    (tmp_path / "fields.ply").write_bytes(cply.replace(b"packed_scale", b"packed_scalX", 1))
    with pytest.raises(PlyFormatError, match="lacks packed_scale"):
        read_scene(tmp_path / "fields.ply")
    with pytest.raises(PlyFormatError, match="coordinate of 1e\\+07 is beyond"):
        SPZ.write_spz(tmp_path / "far.spz", {**params, "means": params["means"] + 1e7})
    nan, _ = nan_rows(params)
    with pytest.raises(PlyFormatError, match="'means' has non-finite values"):
        SPZ.write_spz(tmp_path / "nan.spz", nan)
    assert not (tmp_path / "nan.spz").exists() and not list(tmp_path.glob(".*.tmp-*"))


def test_spz_of_sh_degree_4_reads_its_bands_1_to_3(tmp_path):
    """The reference writes up to degree 4 (24 coefficients, coefficient-major): the first 15
    are bands 1-3, read as a degree-3 scene."""
    params = random_params(64, 3, seed=10)
    SPZ.write_spz(tmp_path / "d3.spz", params, version=3)
    streams = SPZ.read_spz_streams(tmp_path / "d3.spz")
    band4 = np.full((64, 9, 3), 200, np.uint8)  # (200 - 128) / 128: nonzero, so a misread shows
    streams.sh = np.concatenate([streams.sh, band4], axis=1)
    streams.header = SPZ.SpzHeader(3, 64, 4, streams.header.fractional_bits, False)
    (tmp_path / "d4.spz").write_bytes(SPZ.container_bytes(streams, tmp_path / "d4.spz"))
    four, three = read_scene(tmp_path / "d4.spz"), read_scene(tmp_path / "d3.spz")
    assert four.sh_degree == 3
    for key in three.params:
        assert torch.equal(four.params[key], three.params[key]), key


def test_compressed_ply_without_chunk_colours_reads(tmp_path):
    """Files from before per-chunk colour ranges: 12 chunk properties, colour an absolute unorm8."""
    params = random_params(300, 0, seed=11)
    path = tmp_path / "s.compressed.ply"
    write_scene(path, params)
    ply = PlyData.read(str(path))
    colour = np.clip(0.5 + SH_C0 * read_scene(path).params["sh0"][:, 0].double().numpy(), 0.0, 1.0)
    rgb = np.rint(colour * 255).astype(np.uint32)
    vertex = ply["vertex"].data.copy()
    vertex["packed_color"] = (rgb[:, 0] << 24) | (rgb[:, 1] << 16) | (rgb[:, 2] << 8) | (vertex["packed_color"] & 255)
    chunk = ply["chunk"].data
    names = [n for n in chunk.dtype.names if n not in CP.COLOR_FIELDS]
    old_chunk = np.empty(len(chunk), dtype=[(n, "<f4") for n in names])
    for n in names:
        old_chunk[n] = chunk[n]
    old = tmp_path / "old.ply"
    PlyData([PlyElement.describe(old_chunk, "chunk"), PlyElement.describe(vertex, "vertex")]).write(str(old))
    got = read_scene(old)
    # colour round(c 255) / 255 of the colour decoded from the new file: within 0.5/255
    assert np.abs(0.5 + SH_C0 * got.params["sh0"][:, 0].double().numpy() - colour).max() <= 0.5 / 255 + 1e-6
    assert torch.equal(got.params["means"], read_scene(path).params["means"])


def test_spz_keeps_fractional_bits_for_a_large_scene(tmp_path):
    """A scene wider than 24 bits at 12 fractional bits gets fewer, and the bound follows them."""
    params = random_params(100, 0, seed=9)
    params["means"] = params["means"] * 3000.0  # |x| up to ~4e4 > 2^11 = 2048
    SPZ.write_spz(tmp_path / "big.spz", params)
    header = SPZ.spz_header(tmp_path / "big.spz")
    peak = params["means"].abs().max().item()
    assert header.fractional_bits == max(b for b in range(13) if round(peak * 2 ** b) < 2 ** 23)
    check_spz(np_params(params), np_params(read_scene(tmp_path / "big.spz").params), header)


# ----------------------------------------------------------------------------- commands
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny run trained with the antialiased filter (so exports carry the flag)."""
    from dataclasses import replace

    from exploregs_plugin.rasterizer import RasterSettings

    run_dir = tmp_path_factory.mktemp("run")
    config = TrainerConfig(data="builtin:tiny", max_steps=20, run_dir=run_dir, quiet=True, tensorboard=False,
                           eval_count=1, save_eval_images=False)
    model = replace(config.pipeline.model, raster=RasterSettings(antialiased=True))
    replace(config, pipeline=replace(config.pipeline, model=model)).setup().train()
    return load_run(run_dir)


def test_eg_export_writes_each_format_and_eg_render_reads_it_back(run, tmp_path, capsys):
    from exploregs_plugin.io.frames import to_uint8
    from exploregs_plugin.model.gaussians import render_params

    model, dm = run.pipeline.model, run.pipeline.datamanager
    norm = dataset_normalization(dm)
    n = model.num_gaussians
    for fmt, suffix in (("ply", ".ply"), ("splat", ".splat"), ("spz", ".spz"), ("compressed-ply", ".compressed.ply")):
        result = export_script.main(export_script.ExportArgs(run.run_dir, format=fmt))  # default name
        assert result.path == run.run_dir / "exports" / f"scene-step-{run.step:07d}{suffix}"
        assert (result.format, result.written, result.size_bytes) == (fmt, n, result.path.stat().st_size)
        printed = capsys.readouterr().out
        assert f"wrote {n} Gaussians as {fmt} (SH degree {result.sh_degree}, original frame, " \
               f"{result.size_bytes} bytes" in printed
        assert ("holds no SH bands above 0" in printed) == (fmt == "splat")
        scene = read_scene(result.path, norm)
        assert scene.sh_degree == (0 if fmt == "splat" else model.config.sh_degree)
        frames = render_script.main(render_script.RenderArgs(result.path, out=tmp_path / fmt, video=False,
                                                             cameras_from=str(run.run_dir)))
        assert len(frames.frames) == len(dm.test_cameras) >= 1
        for path, camera in zip(frames.frames, dm.test_cameras):
            # eg-render draws exactly what read_scene gives, with the run's raster settings
            with torch.no_grad():
                image = render_params(scene.params, camera, scene.sh_degree, dm.background,
                                      settings=model.config.raster)[0]
            assert np.array_equal(np.array(Image.open(path)), to_uint8(image.numpy()))
    assert SPZ.spz_header(run.run_dir / "exports" / f"scene-step-{run.step:07d}.spz").antialiased
    ply_comments = PlyData.read(str(run.run_dir / "exports" / f"scene-step-{run.step:07d}.ply")).comments
    assert "SplatRenderMode: mip" in ply_comments and any("frame original" in c for c in ply_comments)
    # --out's suffix picks the format; a contradicting --format is one clear error
    assert export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "x.spz")).format == "spz"
    with pytest.raises(PlyFormatError, match="format splat does not match the suffix"):
        export_script.main(export_script.ExportArgs(run.run_dir, out=tmp_path / "x.spz", format="splat"))
    with pytest.raises(ValueError, match="a .splat file holds no cameras; pass --cameras-from"):
        render_script.main(render_script.RenderArgs(tmp_path / "x.splat"))


def test_the_formats_constants_are_the_renderers():
    # io states the colour and rotation conventions itself (it knows formats only); they must be
    # the very numbers the renderer uses, or every file would shift colours or turn Gaussians
    from exploregs_plugin.io import packing
    from exploregs_plugin.rasterizer.projection import QUAT_NORM2_MIN
    from exploregs_plugin.rasterizer.sh import SH_C0

    assert packing.SH_C0 == SH_C0
    assert packing.QUAT_NORM2_MIN == QUAT_NORM2_MIN


def test_spz_sh_bits_set_the_sh_step_and_any_reader_reads_them(tmp_path):
    from exploregs_plugin.io.spz import read_spz, write_spz

    g = torch.Generator().manual_seed(3)
    n = 500
    params = {"means": torch.rand(n, 3, generator=g) - 0.5, "scales": torch.full((n, 3), -3.0),
              "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1), "opacities": torch.zeros(n),
              "sh0": torch.zeros(n, 1, 3), "shN": 0.05 * torch.randn(n, 15, 3, generator=g)}
    errors = {}
    for bits in ((5, 4), (8, 8)):
        path = tmp_path / f"sh{bits[0]}{bits[1]}.spz"
        write_spz(path, params, sh_bits=bits)
        shn = read_spz(path)[0]["shN"]
        errors[bits] = (shn - params["shN"]).abs()
    # byte = round(c 128) + 128 to the nearest multiple of 2^(8 - bits): |error| <= (0.5 + bucket / 2) / 128
    assert float(errors[(8, 8)].max()) <= 0.5 / 128 + 1e-6
    assert float(errors[(5, 4)][:, :3].max()) <= (0.5 + 4) / 128 + 1e-6
    assert float(errors[(5, 4)][:, 3:].max()) <= (0.5 + 8) / 128 + 1e-6
    assert float(errors[(8, 8)].mean()) < 0.25 * float(errors[(5, 4)].mean())
    with pytest.raises(ValueError, match="SH bits must be in 1..8"):
        write_spz(tmp_path / "bad.spz", params, sh_bits=(9, 4))
