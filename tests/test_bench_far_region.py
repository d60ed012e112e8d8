"""Far-region PSNR for captured scenes (bench/far_region.py): the masks are the farthest quarter of
each test view's covered pixels by a reference run's rendered depth, the PSNR is pooled over them
as evaluation.py pools its regions, both are cached against the reference and the quantile, and
the bench tables fill region_far of a scene without region masks from them."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import pytest
import torch

from exploregs_plugin.bench import far_region
from exploregs_plugin.bench.far_region import (
    RESULT_NAME,
    FarRegionError,
    cached_far_region_psnr,
    cached_masks,
    far_mask,
    far_masks,
    far_region_psnr,
)
from exploregs_plugin.bench.presets import named_entries
from exploregs_plugin.bench.runner import RunRecord
from exploregs_plugin.bench.spec import BenchScene, BenchSpec
from exploregs_plugin.bench.tables import write_tables
from exploregs_plugin.model.losses import MSE_FLOOR, psnr
from exploregs_plugin.runs.load import load_run


def _train(run_dir: Path, seed: int) -> Path:
    from exploregs_plugin.scripts.train import parse_config

    parse_config(["exploregs-default", "--data", "builtin:tiny", "--max-steps", "20", "--seed", str(seed), "--quiet",
                  "--no-tensorboard", "--eval-count", "1", "--num-threads", "1", "--run-dir", str(run_dir)]).setup().train()
    return run_dir


@pytest.fixture(scope="module")
def runs(tmp_path_factory, tiny_scene_dir):
    """Two finished 20-step runs of builtin:tiny: the reference (seed 0) and another (seed 1)."""
    root = tmp_path_factory.mktemp("far")
    return _train(root / "reference", 0), _train(root / "other", 1)


def _copy(run: Path, where: Path) -> Path:
    shutil.copytree(run, where)
    return where


def _views(run_dir: Path):
    """(target, image, alpha, depth) of each test view, rendered here directly."""
    run = load_run(run_dir, "cpu")
    model, dm = run.pipeline.model, run.pipeline.datamanager
    out = []
    for i in range(len(dm.test_cameras)):
        camera, target, _ = dm.test_item(i)
        with torch.no_grad():
            image, alpha, depth, _ = model.render(camera, model.config.sh_degree, dm.background)
        out.append((target, image.clamp(0, 1), alpha[..., 0], depth[..., 0]))
    return out


def test_far_mask_rule_on_a_made_up_view():
    depth = torch.arange(1, 17, dtype=torch.float32).reshape(4, 4)
    alpha = torch.ones(4, 4)
    alpha[0, :] = 0.2          # not covered: the nearest row
    depth[1, 0] = 0.0          # not covered: no depth
    mask = far_mask(alpha, depth)
    covered = (alpha >= 0.5) & (depth > 0)
    assert int(covered.sum()) == 11 and not mask[~covered].any()
    assert torch.equal(mask, covered & (depth >= torch.quantile(depth[covered], 0.75)))
    assert int(mask.sum()) == 3  # depths 14, 15, 16: at or above the 0.75 quantile 13.5 of 6..16
    assert not far_mask(torch.zeros(4, 4), depth).any()  # nothing covered: nothing far
    with pytest.raises(ValueError, match="quantile must be a number in"):
        far_mask(alpha, depth, 1.5)


def test_masks_are_the_farthest_quarter_of_covered_pixels(runs):
    reference, _ = runs
    masks = far_masks(reference, device="cpu")
    views = _views(reference)
    assert len(masks) == len(views) >= 1
    for mask, (_, _, alpha, depth) in zip(masks, views):
        covered = (alpha >= 0.5) & (depth > 0)
        expected = covered & (depth >= torch.quantile(depth[covered], 0.75))
        assert mask.dtype == torch.bool and mask.shape == depth.shape
        assert torch.equal(mask, expected)
        assert int(mask.sum()) / int(covered.sum()) == pytest.approx(0.25, abs=0.02)
    half = far_masks(reference, quantile=0.5, device="cpu")
    assert all(int(h.sum()) > int(m.sum()) for h, m in zip(half, masks))


def test_psnr_of_the_reference_on_its_own_masks(runs):
    reference, _ = runs
    masks = far_masks(reference, device="cpu")
    result = far_region_psnr(reference, masks, device="cpu")
    total, count = 0.0, 0
    for mask, (target, image, _, _) in zip(masks, _views(reference)):
        total += float(((image.double() - target.double()) ** 2).mean(dim=-1)[mask].sum())
        count += int(mask.sum())
    assert result.psnr == pytest.approx(-10.0 * math.log10(max(total / count, MSE_FLOOR)), abs=1e-9)
    assert result.pixels == [int(m.sum()) for m in masks]
    assert result.per_view == pytest.approx([psnr(image, target, m) for m, (target, image, _, _)
                                             in zip(masks, _views(reference))], abs=1e-9)


def test_cache_reused_when_unchanged_and_recomputed_on_a_new_quantile_or_reference(runs, tmp_path, monkeypatch):
    reference, other = runs
    scored = _copy(other, tmp_path / "scored")
    first = cached_far_region_psnr(scored, reference, device="cpu")
    saved = json.loads((scored / RESULT_NAME).read_text())
    assert saved["reference"]["run_dir"] == str(reference.resolve())
    assert saved["reference"]["checkpoint"] == "step-0000020.pt" and saved["reference"]["step"] == 20
    assert saved["quantile"] == 0.75 and saved["psnr"] == pytest.approx(first["psnr"])
    assert first["psnr"] == pytest.approx(far_region_psnr(scored, far_masks(reference, device="cpu"), "cpu").psnr)

    real_load = far_region.load_run
    loads: list[Path] = []

    def counting_load(path, device="auto"):
        loads.append(Path(path))
        return real_load(path, device)

    monkeypatch.setattr(far_region, "load_run", counting_load)
    assert cached_far_region_psnr(scored, reference, device="cpu") == first and loads == []  # reused

    half = cached_far_region_psnr(scored, reference, 0.5, device="cpu")  # new quantile: recomputed
    assert len(loads) == 2 and half["quantile"] == 0.5 and sum(half["pixels"]) > sum(first["pixels"])
    again = cached_far_region_psnr(scored, other, 0.5, device="cpu")  # new reference: recomputed
    assert len(loads) == 4 and again["reference"]["run_dir"] == str(other.resolve())
    assert again["psnr"] != pytest.approx(half["psnr"], abs=1e-6)

    masks_file = tmp_path / "out" / "far_masks" / "tiny.pt"
    masks = cached_masks(reference, 0.75, masks_file, "cpu")
    loads.clear()
    assert all(torch.equal(a, b) for a, b in zip(cached_masks(reference, 0.75, masks_file, "cpu"), masks))
    assert loads == []  # reused from the file
    cached_masks(reference, 0.5, masks_file, "cpu")
    assert len(loads) == 1  # another quantile: made again


def test_a_run_without_final_checkpoint_is_one_clear_error(runs, tmp_path):
    unfinished = _copy(runs[0], tmp_path / "unfinished")
    for ckpt in (unfinished / "checkpoints").glob("*.pt"):
        ckpt.unlink()
    for call in (lambda: far_masks(unfinished, device="cpu"),
                 lambda: far_region_psnr(unfinished, [], device="cpu"),
                 lambda: cached_far_region_psnr(runs[1], unfinished, device="cpu")):
        with pytest.raises(FarRegionError) as err:
            call()
        text = str(err.value)
        assert str(unfinished) in text and "no final checkpoint" in text and "\n" not in text


def test_tables_fill_far_of_a_scene_without_region_masks(runs, tmp_path):
    named = named_entries()
    spec = BenchSpec(entries=(named["default"], named["seed"]),
                     scenes=(BenchScene("cap", "builtin:tiny"), BenchScene("tiny", "builtin:tiny")),
                     seeds=(0,), steps=20, eval_count=1, name="test")
    records = []
    for scene, strip in (("cap", True), ("tiny", False)):
        for entry, source in (("default", runs[0]), ("seed", runs[1])):
            run_dir = _copy(source, tmp_path / scene / entry)
            metrics = json.loads((run_dir / "metrics.json").read_text())
            if strip:  # a captured scene: no region masks, so no region numbers
                metrics = {k: v for k, v in metrics.items() if not k.startswith("region_")}
            records.append(RunRecord(scene, entry, 0, run_dir, status="done", metrics=metrics))
    out = tmp_path / "out"
    payload = write_tables(out, spec, records)
    runs_by = {(r["scene"], r["entry"]): r for r in payload["runs"]}
    for entry in ("default", "seed"):
        cap = runs_by[("cap", entry)]
        saved = json.loads((tmp_path / "cap" / entry / RESULT_NAME).read_text())
        assert cap["region_far"] == pytest.approx(saved["psnr"]) and cap["far_reference"] == "default/seed0"
        assert saved["reference"]["run_dir"] == str((tmp_path / "cap" / "default").resolve())
        own = runs_by[("tiny", entry)]  # a scene with its own masks keeps its generator's far region
        assert "far_reference" not in own and not (tmp_path / "tiny" / entry / RESULT_NAME).exists()
    assert (out / "far_masks" / "cap.pt").is_file()
    rows = {(r["scene"], r["entry"]): r for r in csv.DictReader(open(out / "results.csv"))}
    assert float(rows[("cap", "seed")]["region_far"]) == pytest.approx(runs_by[("cap", "seed")]["region_far"])
    md = (out / "results.md").read_text()
    assert "cap Δfar" in md and "cap far" in md
    assert "For captured scenes \"far\" is the farthest quarter of each test view's" in md
    assert "`cap`: `default/seed0`" in md
