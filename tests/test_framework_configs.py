"""Config YAML round trip and the run schedule."""

from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from exploregs_plugin.io.config_files import load_config, save_config
from exploregs_plugin.schedule import ScheduleConfig


@dataclass
class _Inner:
    rate: float = 0.5
    names: tuple[str, ...] = ("a", "b")


@dataclass
class _Outer:
    path: Path = Path("x/y")
    inner: _Inner = field(default_factory=_Inner)
    steps: int | None = None
    tags: list[str] = field(default_factory=list)


def test_yaml_round_trip_keeps_types(tmp_path):
    cfg = _Outer(path=Path("/data/scene"), inner=_Inner(rate=1e-15, names=("x",)), steps=7, tags=["t"])
    save_config(cfg, tmp_path / "config.yml")
    back = load_config(tmp_path / "config.yml")
    assert back == cfg
    assert isinstance(back.path, Path) and isinstance(back.inner.names, tuple)


def test_a_method_config_is_written_and_read_as_pyyamls_safe_dump_and_safe_load_would(tmp_path):
    """config.yml goes through libyaml where PyYAML has it: the same text as the pure-Python
    safe_dump, read back to the same data as safe_load (floats of every size, None, paths,
    tuples, unicode), and a tag outside the safe subset is still refused."""
    import yaml

    from exploregs_plugin.io.config_files import config_to_dict, read_yaml, yaml_text
    from exploregs_plugin.method_configs import get_method

    config = get_method("exploregs-seedsplit").config
    data = config_to_dict(replace(config, data="données/scène 1", seed=2**40, run_dir=Path("/tmp/r"),
                                  pipeline=replace(config.pipeline, strategy=replace(
                                      config.pipeline.strategy, final_weight_share=1e-300))))
    text = yaml_text(data)
    assert text == yaml.safe_dump(data, sort_keys=False)
    assert read_yaml(text) == yaml.safe_load(text) == data
    save_config(replace(config, seed=3), tmp_path / "config.yml")
    assert load_config(tmp_path / "config.yml") == replace(config, seed=3)
    with pytest.raises(yaml.YAMLError):
        read_yaml("!!python/object/apply:os.system ['true']\n")


def test_yaml_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="config file not found"):
        load_config(tmp_path / "nope.yml")
    bad = tmp_path / "bad.yml"
    bad.write_text("_type: not_a_module_xyz:Thing\n")
    with pytest.raises(ValueError, match="not_a_module_xyz"):
        load_config(bad)
    bad.write_text(f"_type: {__name__}:_Inner\nrate: 1.0\nbogus: 3\n")
    with pytest.raises(ValueError, match="unknown fields.*bogus"):
        load_config(bad)


def test_schedule_keeps_the_3dgs_shape():
    s = ScheduleConfig().resolve(30_000)
    assert (s.refine_start, s.refine_stop, s.refine_every, s.reset_every, s.sh_degree_interval) == (
        500, 15_000, 100, 3_000, 1_000)
    short = ScheduleConfig().resolve(3_000)
    assert (short.refine_start, short.refine_stop) == (50, 1_500)
    # the interval keeps its 3DGS length (100 steps) instead of shrinking with the run
    assert short.refine_every == 100 and short.reset_every == 300 and short.sh_degree_interval == 100
    tiny = ScheduleConfig().resolve(120)
    assert tiny.refine_every == 100 and tiny.reset_every == 200 and tiny.sh_degree_interval == 25
    assert ScheduleConfig(min_refine_every=10).resolve(120).refine_every == 10
    with pytest.raises(ValueError, match="max_steps"):
        ScheduleConfig().resolve(0)


def test_a_config_saved_before_a_field_moved_loads_or_says_where_it_went(tmp_path):
    # runs saved before the branch ablation left the core model config carry detach_paths: ()
    # (the bench resumes them); a run that switched a path off is told where the switch is now
    from exploregs_plugin.method_configs import get_method

    saved = tmp_path / "config.yml"
    save_config(get_method("exploregs-default").config, saved)
    text = saved.read_text()
    old = text.replace("    init_scale: 1.0\n", "    init_scale: 1.0\n    detach_paths:\n      _type: tuple\n      value: []\n", 1)
    assert old != text
    saved.write_text(old)
    assert load_config(saved) == get_method("exploregs-default").config
    saved.write_text(old.replace("      value: []\n", "      value:\n      - cov\n", 1))
    with pytest.raises(ValueError, match=r"field 'detach_paths' \(\('cov',\)\) is gone: .*exploregs-branch-ablation"):
        load_config(saved)
    # a subclass's saved config is migrated the same way (the 4D model), and a class that has the
    # field again keeps it (the branch-ablation model, which round-trips its detached paths)
    save_config(get_method("exploregs-4d-default").config, saved)
    text = saved.read_text()
    old = text.replace("    init_scale: 1.0\n", "    init_scale: 1.0\n    detach_paths:\n      _type: tuple\n      value: []\n", 1)
    assert old != text and "DynamicGaussianModelConfig" in old
    saved.write_text(old)
    assert load_config(saved) == get_method("exploregs-4d-default").config
    from dataclasses import replace

    ablation = get_method("exploregs-branch-ablation").config
    ablation = replace(ablation, pipeline=replace(ablation.pipeline, model=replace(ablation.pipeline.model,
                                                                                    detach_paths=("cov",))))
    save_config(ablation, saved)
    assert load_config(saved).pipeline.model.detach_paths == ("cov",)


OLD_SEEDSPLIT = """\
_type: exploregs_plugin.strategies.seedsplit:SeedSplitStrategy
cap_max: null
refine_start_iter: null
refine_stop_iter: null
refine_every: null
reset_every: null
prune_opa: 0.005
grow_grad2d: 0.0012
grow_scale3d: 0.01
prune_scale3d: 0.1
reset_opacity: 0.01
split_scale_factor: 1.6
budget: cpu-small
n_split: null
split_every: null
n_seed: 10
seed_every: 700
seed_box_mode: cameras
seed_box_quantile: 0.01
seed_opacity_base: 0.2
seed_opacity_gain: 0.5
seed_prune_scale3d: 10.0
seed_min_scale: 1.0e-06
seed_prune_opa: 0.05
seed_grace: null
"""
"""A strategy section as runs saved it before the operators became nested configs (the bench's
seedsplit-official entry: flat fields, seeding's prefixed with seed_)."""

OLD_MCMC_RAY = """\
_type: exploregs_plugin.strategies.mcmc:MCMCStrategy
cap_max: 30000
refine_start_iter: null
refine_stop_iter: null
refine_every: null
reset_every: null
noise_lr: 1000.0
noise_gate_k: 100.0
noise_gate_t: 0.005
min_opacity: 0.005
growth_rate: 0.05
opacity_reg: 0.01
scale_reg: 0.01
noise_mode: ray
"""


def _with_strategy(method: str, strategy_yaml: str) -> dict:
    import yaml

    from exploregs_plugin.io.config_files import config_to_dict
    from exploregs_plugin.method_configs import get_method

    written = config_to_dict(get_method(method).config)
    written["pipeline"]["strategy"] = yaml.safe_load(strategy_yaml)
    return written


def test_configs_saved_with_flat_strategy_fields_load_into_the_operators(tmp_path):
    import yaml

    from exploregs_plugin.io.config_files import config_from_dict, upgraded
    from exploregs_plugin.strategies import MCMCStrategy, PositionNoise, RandomSeeding, RandomSplitting, SeedSplitStrategy

    strategy = config_from_dict(_with_strategy("exploregs-seedsplit", OLD_SEEDSPLIT)).pipeline.strategy
    assert strategy == SeedSplitStrategy(grow_grad2d=0.0012, budget="cpu-small", splitting=RandomSplitting(),
                                         seeding=RandomSeeding(n_seed=10, every=700, box_mode="cameras"),
                                         final_weight_share=0.0, final_cut_tolerance=0.0, settled_cut_iter=0,
                                         settled_cut_frac=2.0 / 3.0, settled_cut_tolerance=None)  # as it trained
    mcmc = config_from_dict(_with_strategy("exploregs-mcmc-ray", OLD_MCMC_RAY)).pipeline.strategy
    assert mcmc == MCMCStrategy(noise=PositionNoise(mode="ray", lr=1000.0))
    # the raw upgrade (what the bench compares a finished run's job file with) is the same move
    raw = upgraded(yaml.safe_load(OLD_SEEDSPLIT))
    assert raw["seeding"]["every"] == 700 and "seed_every" not in raw and raw["splitting"]["n_split"] is None
    # a field that is neither a field nor a moved one is still refused by name
    with pytest.raises(ValueError, match=r"unknown fields: \['seed_colour'\]"):
        config_from_dict(_with_strategy("exploregs-seedsplit", OLD_SEEDSPLIT + "seed_colour: red\n"))
    # a saved nested config round-trips as it is
    saved = tmp_path / "config.yml"
    save_config(config_from_dict(_with_strategy("exploregs-seedsplit", OLD_SEEDSPLIT)), saved)
    assert load_config(saved).pipeline.strategy == strategy


def test_the_bench_reuses_a_run_saved_with_flat_strategy_fields_only_for_the_same_settings(tmp_path):
    import dataclasses

    import yaml

    from exploregs_plugin.bench.files import JOB_NAME
    from exploregs_plugin.bench.runner import same_config
    from exploregs_plugin.io.config_files import config_from_dict

    (tmp_path / JOB_NAME).write_text(yaml.safe_dump(_with_strategy("exploregs-seedsplit", OLD_SEEDSPLIT), sort_keys=False))
    same = config_from_dict(_with_strategy("exploregs-seedsplit", OLD_SEEDSPLIT))
    assert same_config(tmp_path, same)
    strategy = same.pipeline.strategy
    other = dataclasses.replace(strategy, seeding=dataclasses.replace(strategy.seeding, prune_opa=0.1))
    assert not same_config(tmp_path, dataclasses.replace(same, pipeline=dataclasses.replace(same.pipeline, strategy=other)))


def test_a_config_saved_with_the_core_branch_logging_loads_or_names_its_method(tmp_path):
    from exploregs_plugin.method_configs import get_method

    saved = tmp_path / "config.yml"
    save_config(get_method("exploregs-default").config, saved)
    text = saved.read_text()
    old = text.replace("tensorboard: true\n", "tensorboard: true\ngrad_branches_every: 0\ngrad_branches_views: 2\n", 1)
    assert old != text
    saved.write_text(old)
    assert load_config(saved) == get_method("exploregs-default").config
    saved.write_text(old.replace("grad_branches_every: 0", "grad_branches_every: 50"))
    with pytest.raises(ValueError, match=r"field 'grad_branches_every' \(50\) is gone: .*exploregs-grad-branches"):
        load_config(saved)
    method = get_method("exploregs-grad-branches").config
    save_config(method, saved)
    assert load_config(saved) == method


def test_a_config_saved_with_the_core_depth_degradation_loads_or_names_its_method(tmp_path):
    # the degraded depth maps left the core pipeline for the method exploregs-mono-depth; runs
    # saved before carry pipeline.depth_supervision with its class at its old path
    from exploregs_plugin.method_configs import get_method

    saved = tmp_path / "config.yml"
    save_config(get_method("exploregs-default").config, saved)
    text = saved.read_text()
    old_field = ("  depth_supervision:\n    _type: exploregs_plugin.data.depth_supervision:DepthSupervisionConfig\n"
                 "    noise_std: 0.0\n    bias_amplitude: 0.0\n    bias_wavelength: 0.5\n    seed: 3\n")
    old = text.replace("  batch_size: null\n", old_field + "  batch_size: null\n", 1)
    assert old != text
    saved.write_text(old)
    assert load_config(saved) == get_method("exploregs-default").config  # off (any seed): dropped
    saved.write_text(old.replace("    noise_std: 0.0\n", "    noise_std: 0.05\n", 1))
    with pytest.raises(ValueError, match=r"field 'depth_supervision' .* is gone: .*exploregs-mono-depth"):
        load_config(saved)
    # the method's own config keeps the field, and reads the old class path too
    mono = get_method("exploregs-mono-depth").config
    save_config(mono, saved)
    assert load_config(saved) == mono and mono.pipeline.depth_supervision.active
    moved = saved.read_text().replace("exploregs_plugin.analysis.depth_degradation:DepthSupervisionConfig",
                                      "exploregs_plugin.data.depth_supervision:DepthSupervisionConfig")
    saved.write_text(moved)
    assert load_config(saved) == mono


def test_a_wrapped_error_line_that_starts_with_a_dash_keeps_it():
    from exploregs_plugin.io.config_files import tyro_error_text

    # tyro's box, narrow enough that the bad value "-1" starts a wrapped line
    captured = ("╭─ Value error ──────────────────────────╮\n"
                "│ Error parsing --schedule: coarse_levels │\n"
                "│ must be >= 0, got                       │\n"
                "│ -1                                      │\n"
                "│ ─────────────────────────────────────── │\n"
                "│ For full helptext, see - --help         │\n"
                "╰─────────────────────────────────────────╯\n")
    assert tyro_error_text(captured).endswith("Error parsing --schedule: coarse_levels must be >= 0, got -1")


def test_a_config_error_is_named_by_its_flag_not_by_a_class_or_a_group_without_flags(capsys):
    from exploregs_plugin.io.config_files import tyro_error_text
    from exploregs_plugin.scripts.train import parse_config

    def boxed(message: str) -> str:
        return f"╭─ Value error ─╮\n│ Error parsing {message} │\n│ For full helptext, see - --help │\n╰───╯\n"

    # the command's own config class has no flag; a group whose message names its flag adds nothing
    assert tyro_error_text(boxed("TrainerConfig: --checkpoint-every must be >= 1, got 0")) == \
        "--checkpoint-every must be >= 1, got 0"
    assert tyro_error_text(boxed("options: --num-frames: must be >= 3, got -4")) == "--num-frames: must be >= 3, got -4"
    assert tyro_error_text(boxed("pipeline.strategy: cap_max must be >= 0")) == "--strategy: cap_max must be >= 0"
    # a periodic checkpoint every 0 steps was a ZeroDivisionError in the first step
    with pytest.raises(SystemExit) as exit_:
        parse_config(["exploregs-default", "--data", "builtin:tiny", "--checkpoint-every", "0"])
    assert exit_.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "eg-train: error: --checkpoint-every must be >= 1, got 0"]


def test_a_config_naming_a_renamed_module_loads_and_compares_equal(tmp_path):
    # strategies/ray.py, perturbation.py and operator.py were renamed (ray_perturbation,
    # position_noise, operator_contract): the config.yml of earlier runs names the old modules,
    # and a bench resuming those runs must see the same config (upgraded() rewrites the type)
    from exploregs_plugin.io.config_files import MOVED_MODULES, config_to_dict, upgraded
    from exploregs_plugin.method_configs import get_method

    config = get_method("exploregs-ray").config
    saved = tmp_path / "config.yml"
    save_config(config, saved)
    text = saved.read_text()
    assert "strategies.ray_perturbation:RayPerturbationStrategy" in text
    assert "strategies.position_noise:PositionNoise" in text
    old = text.replace("strategies.ray_perturbation:", "strategies.ray:").replace(
        "strategies.position_noise:", "strategies.perturbation:")
    saved.write_text(old)
    assert load_config(saved) == config
    import yaml

    assert upgraded(yaml.safe_load(old)) == config_to_dict(config)
    assert MOVED_MODULES["exploregs_plugin.strategies.ray"] == "exploregs_plugin.strategies.ray_perturbation"


def test_a_run_config_saved_by_d015f35_loads_and_trains(tmp_path):
    """config.yml of a run saved by d015f35 (before the engine, evaluation and runtime modules moved
    into their folders) names exploregs_plugin.trainer, .pipeline, .distributed: it loads into the
    classes where they live now, trains, saves their new paths and loads again."""
    from dataclasses import replace

    from exploregs_plugin.engine.pipeline import PipelineConfig
    from exploregs_plugin.engine.trainer import TrainerConfig
    from exploregs_plugin.runtime.distributed import MachineConfig
    from exploregs_plugin.runs import load_run

    saved = Path(__file__).parent / "data" / "run_d015f35" / "config.yml"
    assert "_type: exploregs_plugin.trainer:TrainerConfig" in saved.read_text()
    config = load_config(saved)
    assert type(config) is TrainerConfig and type(config.pipeline) is PipelineConfig
    assert type(config.machine) is MachineConfig and config.method_name == "exploregs-seedsplit"
    run_dir = tmp_path / "run"
    config = replace(config, data="builtin:tiny", max_steps=3, run_dir=run_dir, output_dir=tmp_path, eval_count=1,
                     tensorboard=False, save_eval_images=False, quiet=True)
    metrics = config.setup().train()
    written = (run_dir / "config.yml").read_text()
    assert "_type: exploregs_plugin.engine.trainer:TrainerConfig" in written
    assert "exploregs_plugin.trainer:" not in written and "exploregs_plugin.runtime.distributed:MachineConfig" in written
    run = load_run(run_dir, "cpu")
    assert run.pipeline.model.num_gaussians == metrics["num_gaussians"] > 0
