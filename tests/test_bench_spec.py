"""eg-bench specs without training: entries, scenes, overrides through tyro, presets, spec files,
CLI composition, config matching and the paired statistics of the tables."""

from __future__ import annotations

from dataclasses import replace
import json
import math
from pathlib import Path

import pytest

from exploregs_plugin.bench.presets import preset
from exploregs_plugin.bench.spec import BenchEntry, BenchScene, BenchSpec, BenchSpecError
from exploregs_plugin.bench.specfile import compose
from exploregs_plugin.bench.presets import LOWTHRESH_GROW_GRAD2D, entry_from_arg, full, named_entries, real
from exploregs_plugin.bench.runner import RunRecord
from exploregs_plugin.bench.spec import build_config, comparable, config_fingerprint, configs_match, scene_from_arg
from exploregs_plugin.bench.tables import mean_std, run_row, summarize
from exploregs_plugin.strategies import DefaultStrategy, SeedingStrategy


def _config(spec: BenchSpec, entry: str, scene: int = 0, seed: int = 0):
    return build_config(spec, spec.scenes[scene], spec.entry(entry), seed, Path("/tmp/unused-run"))


def test_controls_are_default_with_seedings_prune_and_a_lower_threshold():
    spec = preset("standard")
    relaxed = _config(spec, "default-relaxed-prune").pipeline.strategy
    plain = _config(spec, "default").pipeline.strategy
    assert type(relaxed) is DefaultStrategy and type(plain) is DefaultStrategy
    assert relaxed.prune_scale3d == SeedingStrategy().seeding.prune_scale3d == 10.0
    assert plain.prune_scale3d == DefaultStrategy().prune_scale3d
    low = build_config(spec, spec.scenes[0], named_entries()["default-lowthresh"], 0, Path("/tmp/x")).pipeline.strategy
    assert low.grow_grad2d == LOWTHRESH_GROW_GRAD2D < plain.grow_grad2d
    assert [e.name for e in spec.entries] == ["default", "default-relaxed-prune", "seed", "split", "seedsplit",
                                              "ray", "mcmc"]
    assert spec.seeds == (0, 1, 2) and len(spec.runs()) == 7 * 3 * len(spec.scenes)


def test_full_explore_preset_adds_mcmc_explore_to_fulls_recipe_and_reuses_its_entries(tmp_path):
    from exploregs_plugin.strategies import MCMCExploreStrategy

    for name in ("beer", "fox"):
        (tmp_path / name).mkdir()
    from exploregs_plugin.bench.presets import full_explore

    base = full(tmp_path)

    spec = full_explore(tmp_path)
    assert (spec.steps, spec.seeds, spec.eval_count, spec.scenes) == (base.steps, base.seeds, base.eval_count, base.scenes)
    runs = [(entry.name, seed) for _, entry, seed in spec.runs()]
    assert {e for e, s in runs if s > 0} == {"default", "mcmc", "mcmc-explore"}
    assert len(runs) == 2 * (3 * 3 + 4)
    shared = {e.name: e for e in base.entries}
    for name in ("default", "default-relaxed-prune"):  # the same runs as full's: reused
        assert spec.entry(name) == shared[name]
    assert spec.entry("seedsplit") == replace(shared["seedsplit"], seeds=(0,))  # its seed 0 is full's
    assert spec.entry("mcmc").overrides == shared["mcmc"].overrides
    capped = spec.entry("mcmc-explore").resolved(lambda entry, field: 1234)  # Default's count, once known
    explore = build_config(spec, spec.scenes[0], capped, 0, Path("/tmp/unused-run")).pipeline.strategy
    assert type(explore) is MCMCExploreStrategy and explore.cap_max == 1234
    assert spec.entry("mcmc-explore").depends_on() == {"default"}
    assert _config(spec, "mcmc-explore-auto").pipeline.strategy.cap_max == "auto"
    assert _config(spec, "guided-occlusion").pipeline.strategy.budget == "cpu-small"
    assert named_entries()["mcmc-auto"].overrides == ("--strategy.cap-max", "auto")


def test_build_config_applies_bench_fields_then_scene_options_then_entry_overrides():
    spec = BenchSpec(entries=(BenchEntry("s50", "exploregs-seed", ("--strategy.seeding.n-seed", "50", "--data-factor", "3")),),
                     scenes=(BenchScene("t", "builtin:tiny", ("--data-factor", "2", "--eval-count", "7")),),
                     seeds=(4,), steps=123, eval_count=3)
    c = _config(spec, "s50", seed=4)
    assert c.pipeline.strategy.seeding.n_seed == 50 and type(c.pipeline.strategy) is SeedingStrategy
    assert c.pipeline.datamanager.data == "builtin:tiny" and c.pipeline.datamanager.data_factor == 3  # entry wins
    assert (c.max_steps, c.seed, c.eval_count, c.quiet, c.tensorboard) == (123, 4, 7, True, False)
    assert c.run_dir == Path("/tmp/unused-run")


def test_invalid_overrides_name_the_entry_and_argument():
    spec = BenchSpec(entries=(BenchEntry("oops", "exploregs-seed", ("--strategy.seeding.n-seed", "many")),),
                     scenes=(BenchScene("t", "builtin:tiny"),))
    with pytest.raises(BenchSpecError, match=r"entry 'oops' overrides.*--strategy.seeding.n-seed"):
        _config(spec, "oops")
    with pytest.raises(BenchSpecError, match="unknown method"):
        entry_from_arg("x=exploregs-nothing")
    with pytest.raises(BenchSpecError, match="unknown entry"):
        entry_from_arg("nothing")
    with pytest.raises(BenchSpecError, match="unique"):
        BenchSpec(entries=(named_entries()["seed"],) * 2, scenes=(BenchScene("t", "builtin:tiny"),))
    with pytest.raises(BenchSpecError, match="folder"):
        scene_from_arg("a/b=builtin:tiny")


def test_a_run_matches_its_config_whatever_its_folder_and_across_added_fields():
    from exploregs_plugin.io.config_files import config_to_dict

    spec = preset("quick")

    def written(entry: str, seed: int = 0, run_dir: str = "/tmp/unused-run") -> dict:
        return comparable(config_to_dict(build_config(spec, spec.scenes[0], spec.entry(entry), seed, Path(run_dir))))

    a = written("default")
    assert configs_match(a, written("default", run_dir="/elsewhere"))
    assert not configs_match(a, written("default", seed=1))
    assert not configs_match(a, written("seed"))  # another strategy type
    older = json.loads(json.dumps(a))
    del older["pipeline"]["strategy"]["grow_scale3d"]  # a field the code did not have then
    assert configs_match(older, a)
    older["pipeline"]["strategy"]["grow_grad2d"] = 1e-3  # a value that differs
    assert not configs_match(older, a)
    assert config_fingerprint(build_config(spec, spec.scenes[0], spec.entry("default"), 0, Path("/x"))) == \
        config_fingerprint(build_config(spec, spec.scenes[0], spec.entry("default"), 0, Path("/y")))


def test_a_scene_reached_by_a_relative_or_an_absolute_path_is_the_same_run(tmp_path, monkeypatch):
    """A spec file names ../shared/scenes/beer, an earlier command /work/shared/scenes/beer: the
    runs are one scene's, so the finished ones are reused (the config holds the resolved path)."""
    scene_dir = tmp_path / "scenes" / "beer"
    scene_dir.mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "scenes")
    spec = preset("quick")
    relative, absolute = BenchScene("beer", "../scenes/beer"), BenchScene("beer", str(scene_dir))
    config = build_config(spec, relative, spec.entry("default"), 0, Path("/x"))
    assert Path(config.pipeline.datamanager.data) == scene_dir.resolve()
    assert config_fingerprint(config) == config_fingerprint(build_config(spec, absolute, spec.entry("default"), 0, Path("/x")))
    assert build_config(spec, BenchScene("t", "builtin:tiny"), spec.entry("default"), 0, Path("/x")).pipeline.datamanager.data == "builtin:tiny"


def test_compose_cli_and_spec_file(tmp_path):
    spec = compose(methods=("default", "seed50=seed", "exploregs-mcmc"), scenes=("builtin:farside", "mine=/data/x",
                                                                                 "/data/fox/transforms.json"),
                   seeds=(0, 1), steps=2000, overrides=("seed50:--strategy.seeding.n-seed 50",),
                   scene_options=("mine:--data-factor 4",))
    assert [e.name for e in spec.entries] == ["default", "seed50", "exploregs-mcmc"]
    assert spec.entry("seed50").method == "exploregs-seed"
    assert spec.entry("seed50").overrides == ("--strategy.seeding.n-seed", "50")
    assert [(s.name, s.data, s.options) for s in spec.scenes] == [
        ("farside", "builtin:farside", ()), ("mine", "/data/x", ("--data-factor", "4")),
        ("fox", "/data/fox/transforms.json", ())]
    assert (spec.seeds, spec.steps, spec.name) == ((0, 1), 2000, "custom")
    with pytest.raises(BenchSpecError, match="not in the bench"):
        compose(methods=("default",), scenes=("builtin:tiny",), overrides=("seed:--strategy.seeding.n-seed 5",))
    with pytest.raises(BenchSpecError, match="say what to run"):
        compose(methods=("default",))

    yml = tmp_path / "b.yml"
    yml.write_text("preset: quick\nsteps: 50\nseeds: [3]\nmethods:\n  - default\n"
                   "  - {name: s5, method: seed, overrides: --strategy.seeding.n-seed 5}\n"
                   "scenes:\n  - builtin:tiny\n  - {name: far, data: builtin:farside, data_factor: 2}\n")
    spec = compose(spec_file=yml, steps=60)
    assert [e.name for e in spec.entries] == ["default", "s5"]
    assert spec.entry("s5").overrides == ("--strategy.seeding.n-seed", "5")
    assert spec.scenes[1].options == ("--data-factor", "2") and (spec.steps, spec.seeds) == (60, (3,))
    assert spec.eval_count == preset("quick").eval_count and spec.name == "quick+custom"
    js = tmp_path / "b.json"
    js.write_text(json.dumps({"methods": ["split"], "scenes": ["builtin:tiny"], "bogus": 1}))
    with pytest.raises(BenchSpecError, match="unknown keys.*bogus"):
        compose(spec_file=js)


def test_real_preset_skips_absent_scenes(tmp_path):
    with pytest.raises(BenchSpecError, match="no captured scenes"):
        real(tmp_path)
    (tmp_path / "fox").mkdir()
    spec = real(tmp_path)
    assert [s.name for s in spec.scenes] == ["fox"] and spec.scenes[0].options == ("--data-factor", "12")
    assert any("beer" in note for note in spec.notes)


def test_full_preset_runs_the_compared_methods_three_times_and_the_rest_once(tmp_path):
    with pytest.raises(BenchSpecError, match="no captured scenes"):
        full(tmp_path)
    for name in ("beer", "fox"):
        (tmp_path / name).mkdir()
    spec = full(tmp_path)
    assert spec.steps == 30_000 and spec.seeds == (0, 1, 2)
    runs = [(scene.name, entry.name, seed) for scene, entry, seed in spec.runs()]
    assert len(runs) == 2 * (2 * 3 + 7)
    assert {e for _, e, s in runs if s > 0} == {"default", "seedsplit"}
    # seed outermost: every method of every scene at seed 0 comes before any second seed
    first_repeat = next(i for i, (_, _, s) in enumerate(runs) if s > 0)
    assert all(s == 0 for _, _, s in runs[:first_repeat]) and first_repeat == 2 * 9
    # the overrides parse against each method, as eg-train would parse them
    official = _config(spec, "seedsplit-official").pipeline.strategy
    assert (official.seeding.n_seed, official.seeding.every, official.budget) == (10, 700, "cpu-small")
    assert official.seeding.box_mode == "cameras" and official.split_scale_factor == 1.6
    assert _config(spec, "seedsplit").pipeline.strategy.budget == "cpu-small"
    # the threshold for 120-pixel-high images (3DGS's at 720), half of it for the count control
    assert _config(spec, "default").pipeline.strategy.grow_grad2d == pytest.approx(0.0012)
    assert spec.entry("default-lowthresh").overrides[:2] == ("--strategy.grow-grad2d", "0.0006")
    assert _config(spec, "default", scene=1).pipeline.datamanager.data_factor == 9
    # a --seeds choice keeps each entry within it; the tables count each entry's own seeds
    assert spec.seeds_of(spec.entry("mcmc")) == (0,) and spec.seeds_of(spec.entry("default")) == (0, 1, 2)
    records = [_record("default", s, 20.0 + s) for s in (0, 1, 2)] + [_record("mcmc", 0, 21.0)]
    small = BenchSpec(entries=(spec.entry("default"), BenchEntry("mcmc", "exploregs-mcmc", seeds=(0,))),
                      scenes=(BenchScene("s", "builtin:tiny"),), seeds=(0, 1, 2))
    summary = {s["entry"]: s for s in summarize(small, [run_row(small, r) for r in records])}
    assert summary["mcmc"]["n_seeds"] == 1 and summary["mcmc"]["n_done"] == 1
    assert summary["mcmc"]["paired"]["psnr"]["mean"] == pytest.approx(1.0)
    with pytest.raises(BenchSpecError, match="seeds must be unique"):
        BenchSpec(entries=(BenchEntry("d", "exploregs-default", seeds=(0, 0)),), scenes=small.scenes)


def test_methods_named_in_the_preset_keep_the_presets_arguments(tmp_path, monkeypatch):
    """`eg-bench full --methods default seedsplit mcmc` runs the full bench's entries (its
    threshold, budget and cap), not the generic entries of those names; other names are as before."""
    import exploregs_plugin.bench.presets as presets

    for name in ("beer", "fox"):
        (tmp_path / name).mkdir()
    monkeypatch.setattr(presets, "shared_scenes_root", lambda: tmp_path)
    spec = compose("full", methods=("default", "seedsplit", "mcmc", "seed50=seed", "exploregs-ray"), seeds=(0, 1))
    whole = full(tmp_path)
    for name in ("default", "seedsplit", "mcmc"):
        assert spec.entry(name) == whole.entry(name) != named_entries()[name]
    assert _config(spec, "default").pipeline.strategy.grow_grad2d == pytest.approx(0.0012)
    assert spec.entry("mcmc").depends_on() == {"default"}
    assert spec.entry("seed50").overrides == named_entries()["seed"].overrides
    assert [e.name for e in spec.entries] == ["default", "seedsplit", "mcmc", "seed50", "exploregs-ray"]


def _record(entry: str, seed: int, psnr: float | None, far: float = 20.0) -> RunRecord:
    if psnr is None:
        return RunRecord("s", entry, seed, Path("/x"), status="failed", error="boom")
    metrics = {"psnr": psnr, "ssim": 0.5, "lpips": None, "region_psnr": {"far": far, "occluded": 1.0, "other": 2.0},
               "num_gaussians": 100 + seed, "train_seconds": 1.0, "seconds_per_step": 0.1,
               "render_seconds_per_image": 0.01}
    return RunRecord("s", entry, seed, Path("/x"), status="done", metrics=metrics)


def test_paired_differences_use_the_same_seed_and_skip_failures():
    named = named_entries()
    spec = BenchSpec(entries=(named["default"], named["seed"]), scenes=(BenchScene("s", "builtin:tiny"),),
                     seeds=(0, 1, 2))
    records = [_record("default", 0, 20.0), _record("default", 1, 22.0), _record("default", 2, 24.0),
               _record("seed", 0, 21.0, far=23.0), _record("seed", 1, None), _record("seed", 2, 24.5)]
    summary = {s["entry"]: s for s in summarize(spec, [run_row(spec, r) for r in records])}
    d = summary["seed"]["paired"]["psnr"]
    assert d["n"] == 2 and d["mean"] == pytest.approx(0.75) and d["std"] == pytest.approx(math.sqrt(0.125))
    assert summary["seed"]["paired"]["region_far"]["mean"] == pytest.approx(1.5)  # (23-20 + 20-20) / 2
    assert summary["seed"]["n_done"] == 2 and summary["seed"]["n_failed"] == 1
    base = summary["default"]["metrics"]["psnr"]
    assert base["mean"] == pytest.approx(22.0) and base["std"] == pytest.approx(2.0)
    assert summary["default"]["metrics"]["lpips"] == {"mean": None, "std": None, "n": 0}
    assert summary["default"]["paired"] == {}
    assert mean_std([5.0]) == {"mean": 5.0, "std": None, "n": 1}


def test_cli_dry_run_prints_the_plan_and_bad_input_is_one_line(capsys):
    from exploregs_plugin.scripts.bench import main
    from exploregs_plugin.scripts import run_cli

    assert main(["standard", "--dry-run", "--steps", "400", "--override", "seed:--strategy.seeding.n-seed 5"]) is None
    err = capsys.readouterr().err
    assert "7 methods x 3 scenes x 3 seeds = 63 runs of 400 steps" in err
    assert "seed [--strategy.seeding.n-seed 5]" in err and "estimate: ~" in err
    with pytest.raises(SystemExit) as exit_:
        run_cli("eg-bench", main, ["--methods", "default", "--scenes", "builtin:tiny", "--override", "nocolon"])
    assert exit_.value.code == 2
    assert "eg-bench: error: --override 'nocolon': expected 'ENTRY:ARGS'" in capsys.readouterr().err


def test_override_and_scene_option_flags_repeat(capsys):
    from exploregs_plugin.scripts.bench import main

    assert main(["quick", "--dry-run", "--methods", "default", "seed", "--override", "seed:--strategy.seeding.n-seed 5",
                 "--override", "default:--strategy.grow-grad2d 0.0003", "--scene-option", "tiny:--data-factor 2",
                 "--scene-option", "tiny:--datamanager.test-every 4"]) is None
    err = capsys.readouterr().err
    assert "seed [--strategy.seeding.n-seed 5]" in err and "default [--strategy.grow-grad2d 0.0003]" in err
    assert "--data-factor 2 --datamanager.test-every 4" in err


def test_frame_curves_average_runs_by_frame_time():
    from exploregs_plugin.bench.plots import frame_curves

    runs = [
        {"per_image": [{"time": 0.0, "psnr": 20.0, "region_psnr": {"occluded": 18.0}},
                       {"time": 0.5, "psnr": 22.0, "region_psnr": {"occluded": float("nan")}}]},
        {"per_image": [{"time": 0.5, "psnr": 24.0, "region_psnr": {"occluded": 21.0}},
                       {"time": 0.0, "psnr": 22.0, "region_psnr": {"occluded": 20.0}}]},
        {"per_image": [{"psnr": 30.0}]},  # a static run's views have no time
    ]
    assert frame_curves(runs) == ([0.0, 0.5], [21.0, 23.0])
    assert frame_curves(runs, "occluded") == ([0.0, 0.5], [19.0, 21.0])  # NaN frames left out
    assert frame_curves([{"per_image": [{"psnr": 1.0}]}]) == ([], [])


def test_the_dynamic_preset_has_a_measured_estimate():
    from exploregs_plugin.bench.estimate import RUN_OVERHEAD_SECONDS, SECONDS_PER_STEP, estimate_seconds
    from exploregs_plugin.bench.presets import dynamic

    spec = dynamic()
    seconds, how = estimate_seconds(spec)
    rates = SECONDS_PER_STEP["dynamic"]
    # the control runs 4d-default's method, so it costs 4d-default's rate
    per_seed = sum(rates[e.method] for e in spec.entries) * spec.steps + len(spec.entries) * RUN_OVERHEAD_SECONDS
    assert seconds == pytest.approx(per_seed * len(spec.seeds)) and "assumed" not in how


def test_cap_sweep_scales_defaults_count_and_reuses_full_explores_runs(tmp_path):
    from exploregs_plugin.bench.presets import cap_sweep, full_explore

    for name in ("beer", "fox"):
        (tmp_path / name).mkdir()
    spec, explore = cap_sweep(tmp_path), full_explore(tmp_path)
    assert spec.seeds == (0,) and spec.steps == explore.steps and spec.scenes == explore.scenes
    for name in ("default", "mcmc-explore", "mcmc-explore-auto"):  # full-explore's runs, reused
        assert spec.entry(name) == explore.entry(name)
    caps = {}
    for entry in spec.entries:
        if entry.depends_on():
            resolved = entry.resolved(lambda ref, field: 22381)  # Default's final count
            caps[entry.name] = build_config(spec, spec.scenes[0], resolved, 0, Path("/tmp/unused")).pipeline.strategy.cap_max
    # 22381 x 0.125 = 2797.6, x 0.25 = 5595.25, x 0.5 = 11190.5 (rounded half to even), x 1, x 2
    assert caps == {"mcmc-explore-x0.125": 2798, "mcmc-explore-x0.25": 5595, "mcmc-explore-x0.5": 11190, "mcmc-explore": 22381,
                    "mcmc-explore-x2": 44762}
