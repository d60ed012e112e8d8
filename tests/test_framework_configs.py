"""Config YAML round trip and the run schedule."""

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from exploregs_plugin.configs import load_config, save_config
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
