"""Our .splat, .spz, compressed PLY and PLY files read by a real third-party tool, PlayCanvas's
splat-transform (the converter behind SuperSplat), and its own .spz / compressed PLY read by us.

splat-transform converts each of our files to a plain PLY (log-scales, logit opacities, rot_0..3
= w x y z, as ours); we read that with ``read_ply`` and compare with what we wrote, row by
row matched by position (it may reorder), within each format's quantisation bound. Its
conventions that differ from ours: a .splat rotation byte b decodes as 2 b / 255 - 1 (ours and
antimatter15's: (b - 128) / 128); opacity bytes 0 and 255 decode to logit(1e-6), logit(1 - 1e-6)
for .splat / .spz and to -inf / +inf for a compressed PLY (ours: to the byte's interval centre).

The tool: ``node_modules/.bin/splat-transform`` under ``$XDG_CACHE_HOME/exploregs/splat-transform``
(default ``~/.cache/...``; .ci/run installs it there), else one on PATH; where neither exists and
npm does, the test installs the pinned version there. Skipped, with the reason, without node/npm.
"""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData

from exploregs_plugin.io import spz as SPZ
from exploregs_plugin.io.ply import export_ply, read_ply
from exploregs_plugin.io.scene_files import read_scene, write_scene
from exploregs_plugin.rasterizer.sh import SH_C0

PINNED = "3.7.0"
"""@playcanvas/splat-transform version these tests were checked with (npm view ... version)."""


def install_dir() -> Path:
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache) / "exploregs" / "splat-transform"


@pytest.fixture(scope="module")
def tool() -> str:
    """Path of the splat-transform command (installed with npm if need be), or skip."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed: splat-transform is a Node.js tool")
    local = install_dir() / "node_modules" / ".bin" / "splat-transform"
    if not local.exists() and shutil.which("splat-transform") is None:
        npm = shutil.which("npm")
        if npm is None:
            pytest.skip(f"splat-transform is not in {install_dir()} nor on PATH, and npm is absent to install it")
        done = subprocess.run([npm, "install", "--prefix", str(install_dir()), "--no-audit", "--no-fund",
                               "--loglevel=error", f"@playcanvas/splat-transform@{PINNED}"],
                              check=False, capture_output=True, text=True, timeout=600)
        if done.returncode != 0 or not local.exists():
            tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
            pytest.skip(f"npm could not install @playcanvas/splat-transform@{PINNED}: {tail}")
    return str(local) if local.exists() else str(shutil.which("splat-transform"))


def convert(tool: str, source: Path, target: Path) -> Path:
    done = subprocess.run([tool, "-q", "-w", str(source), str(target)], check=False, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and target.is_file(), f"splat-transform {source.name} -> {target.name}: {done.stderr}"
    return target


def test_the_pinned_version_runs(tool):
    done = subprocess.run([tool, "--version"], check=False, capture_output=True, text=True, timeout=60)
    said = done.stdout + done.stderr  # 3.7.0 prints its version on stderr
    assert done.returncode == 0 and "splat-transform v" in said
    if f"v{PINNED}" not in said:
        pytest.skip(f"found {said.strip()}, these tests were checked with {PINNED}")


# ----------------------------------------------------------------------------- scenes and bounds
def scene(degree: int = 3, n: int = 700, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random Gaussians on a jittered grid (distinct positions, so rows match by position) with
    edge rows: log-scales +-30 and +-100, opacity logits +-20, unnormalised quaternions."""
    g = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(*[torch.arange(9.0)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    params = {"means": grid * 0.6 - 2.4 + 0.1 * torch.rand(n, 3, generator=g),
              "scales": torch.randn(n, 3, generator=g) - 3.0,
              "quats": torch.randn(n, 4, generator=g) * torch.rand(n, 1, generator=g) * 10,
              "opacities": torch.randn(n, generator=g) * 4.0,
              "sh0": torch.randn(n, 1, 3, generator=g),
              "shN": torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g) * 0.4}
    params["scales"][:4] = torch.tensor([[-30.0] * 3, [30.0] * 3, [-100.0, 0.0, 100.0], [-12.0, 7.0, 0.0]])
    params["opacities"][:3] = torch.tensor([20.0, -20.0, 0.0])
    params["quats"][:2] = torch.tensor([[1e3, -2e3, 0.0, 1.0], [-1e-3, 0.0, 1e-3, 0.0]])
    return params


def numpy_params(params) -> dict[str, np.ndarray]:
    return {k: v.detach().double().numpy() for k, v in params.items()}


def matched(written: dict, decoded: dict, tolerance: float) -> dict:
    """``written`` reordered as ``decoded`` (nearest position, one to one, within ``tolerance``)."""
    d = np.linalg.norm(decoded["means"][:, None, :] - written["means"][None], axis=2)
    index = d.argmin(axis=1)
    assert sorted(index.tolist()) == list(range(len(written["means"])))
    assert d[np.arange(len(index)), index].max() <= tolerance
    return {k: v[index] for k, v in written.items()}


def rotation_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rotations (quaternions of any norm), up to sign: 4 asin(|a - +-b| / 2)."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    d = np.minimum(np.linalg.norm(a - b, axis=1), np.linalg.norm(a + b, axis=1))
    return 4.0 * np.arcsin(np.minimum(1.0, d / 2.0))


def opacity(logit: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * logit))  # exact at +-inf


def assert_within(what: str, error: np.ndarray, bound) -> None:
    if error.size == 0:  # SH of a degree-0 scene
        return
    worst = float(np.max(error - bound))
    assert worst <= 0.0, f"{what}: error exceeds its bound by {worst:.3g}"


def smallest_three_angle(step: float) -> float:
    """Three components within ``step`` (|ds| <= sqrt(3) step), the largest (>= 1/2) rebuilt from
    them (|dl| <= 2 |ds| (sqrt(3) + |ds|)): rotation angle <= 4 asin(|(ds, dl)| / 2)."""
    ds = math.sqrt(3.0) * step
    return 4.0 * math.asin(math.hypot(ds, 2.0 * ds * (math.sqrt(3.0) + ds)) / 2.0)


# |sigmoid(o') - sigmoid(o)| <= 0.5/255: alpha is round(sigmoid(o) 255), the end bytes decode
# inside their half-step (theirs at 1e-6 from 0 and 1, ours at its centre); + float32 of the logit
ALPHA = 0.5 / 255 + 1e-6
F32 = 2.0 ** -23


def check_packed_common(w: dict, d: dict, angle: float) -> None:
    assert_within("opacity", np.abs(opacity(d["opacities"]) - opacity(w["opacities"])), ALPHA)
    assert_within("rotation", rotation_angles(d["quats"], w["quats"]), angle)


def check_splat(w: dict, d: dict, their_rotation: bool) -> None:
    assert np.array_equal(d["means"], w["means"])  # float32 positions
    # linear scale exp(clip(l, -87, 88)) in float32 (2^-24 relative), its log rounded to float32
    clipped = np.clip(w["scales"], -87.0, 88.0)
    assert_within("log-scale", np.abs(d["scales"] - clipped), F32 * (1.0 + np.abs(clipped)))
    # colour round(clamp(0.5 + C0 sh0, 0, 1) 255) / 255: within 0.5/255
    colour = np.clip(0.5 + SH_C0 * w["sh0"], 0.0, 1.0)
    assert_within("colour", np.abs(0.5 + SH_C0 * d["sh0"] - colour), 0.5 / 255 + 1e-6)
    # rotation bytes round(q 128 + 128) (clamped at 255): within 0.5/128 per component, 1/128 for a
    # component > 255/256; splat-transform decodes 2 b / 255 - 1 = (b - 128) / 128 + b / 32640, up to
    # 1/128 more. |e| <= sqrt((1/128 + x)^2 + 3 (0.5/128 + x)^2), x = 1/128 for theirs, 0 for ours;
    # the normalised decode is at angle <= 2 asin(|e|)
    x = 1 / 128 if their_rotation else 0.0
    e = math.sqrt((1 / 128 + x) ** 2 + 3 * (0.5 / 128 + x) ** 2)
    check_packed_common(w, d, 2.0 * math.asin(e))


def check_spz(w: dict, d: dict, header: SPZ.SpzHeader) -> None:
    # positions round(x 2^bits) 2^-bits: within 2^-(bits + 1)
    assert_within("position", np.abs(d["means"] - w["means"]), 2.0 ** -(header.fractional_bits + 1))
    # log-scales round((l + 10) 16) / 16 - 10, l clamped to [-10, 5.9375]: within 1/32
    assert_within("log-scale", np.abs(d["scales"] - np.clip(w["scales"], -10.0, 5.9375)), 1 / 32 + 1e-6)
    # colour round(sh0 0.15 255 + 127.5), sh0 clamped to +-0.5/0.15: within 0.5 / (0.15 255)
    limit = 0.5 / 0.15
    assert_within("colour", np.abs(d["sh0"] - np.clip(w["sh0"], -limit, limit)), 0.5 / (0.15 * 255) + 1e-6)
    # SH round(c 128) to buckets of 8 (band 1) or 16 (bands 2-3), c in [-1, 127/128]: (0.5 + b/2) / 128
    bucket = np.where(np.arange(w["shN"].shape[1]) < 3, 8.0, 16.0)[None, :, None]
    assert_within("SH", np.abs(d["shN"] - np.clip(w["shN"], -1.0, 127 / 128)), (0.5 + bucket / 2) / 128 + 1e-6)
    # rotation: v3+ smallest three, 9-bit magnitudes of |q| / sqrt(1/2): within sqrt(1/2) 0.5/511
    check_packed_common(w, d, smallest_three_angle(math.sqrt(0.5) * 0.5 / 511))


def check_compressed(w: dict, d: dict, path: Path) -> None:
    """``d`` in the compressed file's order (chunk = row // 256), ``w`` matched to it."""
    chunk = PlyData.read(str(path))["chunk"].data
    rows = np.arange(len(d["means"])) // 256

    def lerp_bound(lo_name: str, hi_name: str, bits: int, value: np.ndarray) -> np.ndarray:
        # t = (v - lo) / (hi - lo) stored as round(t (2^b - 1)): within (hi - lo) 0.5 / (2^b - 1);
        # splat-transform writes t = 0 for a range under 1e-5 (error <= the range); + float32
        width = (np.asarray(chunk[hi_name], np.float64) - np.asarray(chunk[lo_name], np.float64))[rows]
        return np.where(width < 1e-5, width, width * 0.5 / ((1 << bits) - 1)) + F32 * (1.0 + np.abs(value))

    for axis, name, bits in ((0, "x", 11), (1, "y", 10), (2, "z", 11)):
        assert_within(f"position {name}", np.abs(d["means"][:, axis] - w["means"][:, axis]),
                      lerp_bound(f"min_{name}", f"max_{name}", bits, w["means"][:, axis]))
        log_scale = np.clip(w["scales"][:, axis], -20.0, 20.0)  # chunk ranges are clamped to +-20
        assert_within(f"log-scale {name}", np.abs(d["scales"][:, axis] - log_scale),
                      lerp_bound(f"min_scale_{name}", f"max_scale_{name}", bits, log_scale))
    for c, name in enumerate("rgb"):
        colour = 0.5 + SH_C0 * w["sh0"][:, 0, c]
        assert_within(f"colour {name}", np.abs(0.5 + SH_C0 * d["sh0"][:, 0, c] - colour),
                      lerp_bound(f"min_{name}", f"max_{name}", 8, colour))
    # SH floor((c / 8 + 0.5) 256), decoded mid-byte, ends at +-4: within 1/32 of c clamped to [-4, 4]
    assert_within("SH", np.abs(d["shN"] - np.clip(w["shN"], -4.0, 4.0)), 1 / 32 + 1e-6)
    # rotation: 10-bit unorm of q sqrt(1/2) + 0.5: each small component within 0.5/1023 / sqrt(1/2)
    check_packed_common(w, d, smallest_three_angle(0.5 / 1023 / math.sqrt(0.5)))


# ----------------------------------------------------------------------------- ours -> theirs
@pytest.mark.parametrize("name", ["s.ply", "s.splat", "s-v4.spz", "s-v3.spz", "s-v2.spz", "s.compressed.ply"])
def test_splat_transform_reads_our_files(tool, tmp_path, name):
    params = scene()
    source = tmp_path / name
    if name.endswith(".spz"):
        SPZ.write_spz(source, params, version=int(name[-5]), antialiased=True)
    else:
        write_scene(source, params, antialiased=True)
    plain = read_ply(convert(tool, source, tmp_path / "plain.ply"), keep_nonfinite=True)
    decoded = numpy_params(plain.params)
    written = matched(numpy_params(params), decoded, 0.05)
    if name == "s.ply":  # lossless: the very float32 values
        assert plain.sh_degree == 3
        for key, value in written.items():
            assert np.array_equal(decoded[key], value), key
    elif name == "s.splat":
        assert plain.sh_degree == 0
        check_splat(written, decoded, their_rotation=True)
    elif name.endswith(".spz"):
        header = SPZ.spz_header(source)
        assert plain.sh_degree == 3 and header.version == int(name[-5])
        if header.version == 2:  # x y z of the w >= 0 quaternion, w rebuilt: see test_io_scene_formats
            dx = math.sqrt(3.0) * 0.5 / 127.5
            assert_within("v2 rotation", rotation_angles(decoded["quats"], written["quats"]),
                          4.0 * math.asin(math.hypot(dx, math.sqrt(dx * (2.0 + dx))) / 2.0))
            decoded["quats"] = written["quats"]
        check_spz(written, decoded, header)
    else:
        assert plain.sh_degree == 3
        check_compressed(written, decoded, source)
    # the antialiased tag (spz flag, PLY comment) is seen: splat-transform keeps it as this comment
    if not name.endswith(".splat"):
        assert "SplatRenderMode: mip" in PlyData.read(str(tmp_path / "plain.ply")).comments


# ----------------------------------------------------------------------------- theirs -> ours
@pytest.mark.parametrize("degree", [0, 3])
@pytest.mark.parametrize("suffix", [".spz", ".compressed.ply"])
def test_we_read_splat_transforms_files(tool, tmp_path, degree, suffix):
    """splat-transform writes .spz (its current version) and compressed PLY from our PLY; our
    readers give back what the PLY held, within the format's bounds. (It writes no .splat.)"""
    params = scene(degree, seed=degree + 1)
    export_ply(tmp_path / "ours.ply", params)
    theirs = convert(tool, tmp_path / "ours.ply", tmp_path / f"theirs{suffix}")
    got = read_scene(theirs)
    assert got.sh_degree == degree and got.dropped == 0 and got.num_gaussians == len(params["means"])
    decoded = numpy_params(got.params)
    written = matched(numpy_params(params), decoded, 0.05)
    if suffix == ".spz":
        header = SPZ.spz_header(theirs)
        assert header.version == SPZ.LATEST_VERSION and not header.antialiased
        check_spz(written, decoded, header)
    else:
        check_compressed(written, decoded, theirs)
