"""Standard 3DGS PLY: field-by-field layout, round trips, frame mapping, non-finite rows, bad files."""

import math

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from exploregs_plugin.data.parsed import Normalization, compute_normalization
from exploregs_plugin.io import ply as P


def _params(n: int, degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return {
        "means": torch.randn(n, 3, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3.0,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, k - 1, 3, generator=g),
    }


def _write_vertices(path, fields: dict[str, np.ndarray], *, text=False, extra_elements=()):
    n = len(next(iter(fields.values())))
    data = np.empty(n, dtype=[(name, values.dtype.str) for name, values in fields.items()])
    for name, values in fields.items():
        data[name] = values
    PlyData([PlyElement.describe(data, "vertex"), *extra_elements], text=text).write(str(path))


def _reference_fields(n: int, degree: int) -> dict[str, np.ndarray]:
    """Every value distinct and decodable: field f of row r holds 1000 r + code(f).

    Built the way another tool would write it: no normals, an extra property, scalar fields
    in a non-standard order, and the f_rest fields numbered channel-major by hand.
    """
    rows = np.arange(n, dtype=np.float64)[:, None] * 1000.0
    n_coeff = (degree + 1) ** 2 - 1
    fields: dict[str, np.ndarray] = {}
    for i, name in enumerate(["rot_0", "rot_1", "rot_2", "rot_3", "x", "y", "z", "opacity",
                              "scale_0", "scale_1", "scale_2", "f_dc_0", "f_dc_1", "f_dc_2"]):
        fields[name] = (rows[:, 0] + 900.0 + i).astype(np.float32)
    fields["filter_3D"] = np.full(n, -7.0, np.float32)  # unrelated extra property: ignored
    for channel in range(3):
        for coeff in range(n_coeff):
            # f_rest_{c * (K-1) + k} holds channel c, coefficient k (+1: the DC one is separate)
            fields[f"f_rest_{channel * n_coeff + coeff}"] = (rows[:, 0] + 100.0 * channel + coeff).astype(np.float32)
    return fields


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("text", [False, True])
def test_reference_ply_is_read_field_by_field(tmp_path, degree, text):
    n = 4
    path = tmp_path / "ref.ply"
    _write_vertices(path, _reference_fields(n, degree), text=text)
    scene = P.read_ply(path)
    assert scene.sh_degree == degree and scene.dropped == 0 and scene.num_gaussians == n
    p = scene.params
    n_coeff = (degree + 1) ** 2 - 1
    assert p["shN"].shape == (n, n_coeff, 3) and p["sh0"].shape == (n, 1, 3) and p["opacities"].shape == (n,)
    for r in range(n):
        base = 1000.0 * r
        assert p["quats"][r].tolist() == [base + 900, base + 901, base + 902, base + 903]
        assert p["means"][r].tolist() == [base + 904, base + 905, base + 906]
        assert p["opacities"][r].item() == base + 907
        assert p["scales"][r].tolist() == [base + 908, base + 909, base + 910]
        assert p["sh0"][r, 0].tolist() == [base + 911, base + 912, base + 913]
        for coeff in range(n_coeff):
            for channel in range(3):
                assert p["shN"][r, coeff, channel].item() == base + 100.0 * channel + coeff


def test_export_writes_standard_layout_channel_major(tmp_path):
    params = _params(5, 3)
    result = P.export_ply(tmp_path / "s.ply", params)
    assert (result.written, result.dropped, result.sh_degree) == (5, 0, 3)
    vertex = PlyData.read(str(result.path))["vertex"]
    names = [prop.name for prop in vertex.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(45)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in names)
    for n in range(5):
        for k in range(15):
            for c in range(3):
                assert vertex[f"f_rest_{c * 15 + k}"][n] == params["shN"][n, k, c].item()
        assert [vertex[f"f_dc_{c}"][n] for c in range(3)] == params["sh0"][n, 0].tolist()
        assert [vertex[f"rot_{i}"][n] for i in range(4)] == params["quats"][n].tolist()
        assert vertex["opacity"][n] == params["opacities"][n].item()
        assert [vertex["nx"][n], vertex["ny"][n], vertex["nz"][n]] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_exact(tmp_path, degree):
    params = _params(37, degree, seed=degree)
    P.export_ply(tmp_path / "s.ply", params)
    scene = P.read_ply(tmp_path / "s.ply")
    assert scene.sh_degree == degree
    for name in P.PARAM_NAMES:
        assert scene.params[name].dtype == torch.float32
        assert torch.equal(scene.params[name], params[name]), name


def test_known_point_maps_back_to_the_original_frame_exactly(tmp_path):
    # Camera centres at (10, 20, 30) +- 4 along x: translation -(10, 20, 30) and scale 1/4, both
    # exact in binary, so the mapping of a dyadic point is exact in float32.
    centers = np.array([[6.0, 20.0, 30.0], [14.0, 20.0, 30.0]])
    norm = compute_normalization(centers)
    assert norm.scale == 0.25 and norm.translation.tolist() == [-10.0, -20.0, -30.0]
    known_orig = np.array([[11.5, 19.0, 30.25], [10.0, 20.0, 30.0]])
    params = _params(2, 1)
    params["means"] = torch.from_numpy(norm.apply_points(known_orig)).float()
    sigma_norm = torch.tensor([[0.125, 0.5, 2.0], [1.0, 1.0, 1.0]])
    params["scales"] = torch.log(sigma_norm)
    P.export_ply(tmp_path / "s.ply", params, norm)
    vertex = PlyData.read(str(tmp_path / "s.ply"))["vertex"]
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1)
    assert xyz.tolist() == known_orig.tolist()
    # sizes in file units are 1/scale = 4 times larger: log sigma_orig = log sigma_norm - log(scale)
    log_sigma = np.stack([vertex[f"scale_{i}"] for i in range(3)], axis=1)
    np.testing.assert_allclose(np.exp(log_sigma), sigma_norm.numpy() * 4.0, rtol=1e-6)
    # importing into the same frame gives the training-frame values back
    back = P.read_ply(tmp_path / "s.ply", norm)
    assert torch.equal(back.params["means"], params["means"])
    torch.testing.assert_close(back.params["scales"], params["scales"], rtol=0, atol=1e-6)


def test_round_trip_through_a_general_normalisation(tmp_path):
    norm = Normalization(np.array([-3.1, 0.7, 12.9]), 0.137)
    params = _params(50, 2)
    P.export_ply(tmp_path / "s.ply", params, norm)
    raw = P.read_ply(tmp_path / "s.ply")  # original frame
    expected = norm.invert_points(params["means"].double().numpy())
    np.testing.assert_allclose(raw.params["means"].numpy(), expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(raw.params["scales"].numpy(), params["scales"].numpy() - math.log(0.137), atol=1e-5)
    back = P.read_ply(tmp_path / "s.ply", (norm.translation, norm.scale))  # a plain pair works too
    torch.testing.assert_close(back.params["means"], params["means"], rtol=0, atol=2e-6)
    torch.testing.assert_close(back.params["scales"], params["scales"], rtol=0, atol=2e-6)
    for name in ("quats", "opacities", "sh0", "shN"):  # frame-independent: bit-exact
        assert torch.equal(back.params[name], params[name]), name


def test_nonfinite_gaussians_are_dropped_and_counted(tmp_path):
    params = _params(8, 1)
    params["means"][1, 2] = float("nan")
    params["shN"][3, 1, 0] = float("inf")
    params["opacities"][5] = -float("inf")
    keep = [0, 2, 4, 6, 7]
    result = P.export_ply(tmp_path / "s.ply", params)
    assert (result.written, result.dropped) == (5, 3)
    scene = P.read_ply(tmp_path / "s.ply")
    for name in P.PARAM_NAMES:
        assert torch.equal(scene.params[name], params[name][keep]), name
    # a mean that overflows float32 once mapped to the original frame (x / 1e-3) is dropped too
    params = _params(3, 0)
    params["means"][2, 0] = 3e38
    result = P.export_ply(tmp_path / "t.ply", params, Normalization(np.zeros(3), 1e-3))
    assert (result.written, result.dropped) == (2, 1)


def test_import_drops_nonfinite_rows_unless_asked(tmp_path):
    fields = _reference_fields(3, 0)
    fields["opacity"][1] = np.nan
    _write_vertices(tmp_path / "nan.ply", fields)
    scene = P.read_ply(tmp_path / "nan.ply")
    assert scene.dropped == 1 and scene.num_gaussians == 2
    assert scene.params["means"][:, 0].tolist() == [904.0, 2904.0]
    kept = P.read_ply(tmp_path / "nan.ply", keep_nonfinite=True)
    assert kept.dropped == 0 and math.isnan(kept.params["opacities"][1].item())


def test_bad_ply_files_get_clear_errors(tmp_path):
    with pytest.raises(P.PlyFormatError, match="missing.ply: file not found"):
        P.read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("this is not a ply\n")
    with pytest.raises(P.PlyFormatError, match="junk.ply: not a readable PLY"):
        P.read_ply(tmp_path / "junk.ply")

    fields = _reference_fields(2, 1)
    del fields["rot_3"], fields["scale_2"]
    _write_vertices(tmp_path / "norot.ply", fields)
    with pytest.raises(P.PlyFormatError, match=r"norot.ply: vertex element lacks scale_2, rot_3"):
        P.read_ply(tmp_path / "norot.ply")

    fields = _reference_fields(2, 1)
    fields["f_rest_9"] = fields["f_rest_0"]
    _write_vertices(tmp_path / "ten.ply", fields)
    with pytest.raises(P.PlyFormatError, match="10 f_rest fields match no SH degree"):
        P.read_ply(tmp_path / "ten.ply")

    fields = _reference_fields(2, 1)
    fields["f_rest_9"] = fields.pop("f_rest_4")
    _write_vertices(tmp_path / "gap.ply", fields)
    with pytest.raises(P.PlyFormatError, match=r"not numbered 0..8 \(missing f_rest_4\)"):
        P.read_ply(tmp_path / "gap.ply")

    _write_vertices(tmp_path / "empty.ply", {k: v[:0] for k, v in _reference_fields(1, 0).items()})
    with pytest.raises(P.PlyFormatError, match="holds no Gaussians"):
        P.read_ply(tmp_path / "empty.ply")

    faces = np.zeros(1, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"][0] = np.array([0, 1, 2], np.int32)
    PlyData([PlyElement.describe(faces, "face")]).write(str(tmp_path / "mesh.ply"))
    with pytest.raises(P.PlyFormatError, match="has no 'vertex' element"):
        P.read_ply(tmp_path / "mesh.ply")

    chunk = np.zeros(1, dtype=[("min_x", "<f4")])
    packed = np.zeros(2, dtype=[("packed_position", "<u4"), ("packed_rotation", "<u4")])
    PlyData([PlyElement.describe(chunk, "chunk"), PlyElement.describe(packed, "vertex")]).write(
        str(tmp_path / "packed.ply"))
    with pytest.raises(P.PlyFormatError, match="compressed"):
        P.read_ply(tmp_path / "packed.ply")


def test_bad_scenes_to_export_get_clear_errors(tmp_path):
    params = _params(3, 1)
    params["opacities"] = params["opacities"][:, None]
    with pytest.raises(P.PlyFormatError, match=r"'opacities' has shape \(3, 1\), expected \(3,\)"):
        P.export_ply(tmp_path / "a.ply", params)
    params = _params(3, 1)
    params["shN"] = params["shN"][:, :2]
    with pytest.raises(P.PlyFormatError, match="shN has 2 coefficients per channel"):
        P.export_ply(tmp_path / "b.ply", params)
    params = _params(2, 0)
    params["means"][:] = float("nan")
    with pytest.raises(P.PlyFormatError, match=r"no Gaussians to write \(2 had non-finite values\)"):
        P.export_ply(tmp_path / "c.ply", params)
    assert not (tmp_path / "c.ply").exists() and list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="scale must be finite and > 0"):
        P.export_ply(tmp_path / "d.ply", _params(2, 0), (np.zeros(3), 0.0))


def test_frame_mapping_is_an_inverse_pair():
    norm = Normalization(np.array([1.5, -2.0, 0.25]), 3.0)
    params = _params(10, 2)
    there = P.to_original_frame(params, norm)
    back = P.to_normalized_frame(there, norm)
    for name in P.PARAM_NAMES:
        torch.testing.assert_close(back[name], params[name], rtol=0, atol=1e-5)
    # a Gaussian's extent scales with the frame: sigma_orig = sigma_norm / scale
    torch.testing.assert_close(torch.exp(there["scales"]), torch.exp(params["scales"]) / 3.0, rtol=1e-6, atol=0)
