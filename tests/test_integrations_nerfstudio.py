"""The ``exploregs-splatfacto`` nerfstudio method (exploregs_plugin.integrations.nerfstudio) on a CPU.

Runs only where nerfstudio is installed: nerfstudio 1.1.5 pins packages that clash with ours
(viser 0.2.7, gsplat 1.4.0), so it lives in its own environment (docs/integrations.md says how to
make it). Elsewhere the file is skipped with that reason; what runs everywhere is the one-line
ImportError without nerfstudio.

Model construction replaces one thing: splatfacto's constructor builds its LPIPS metric, whose
AlexNet weights torchvision downloads on first use; these machines reach no such host, and the
metric is only evaluated, never trained through, so a stand-in module takes its place.
"""

from __future__ import annotations

import importlib
import sys
import types

import pytest
import torch


def test_import_without_nerfstudio_is_one_clear_line(monkeypatch):
    pytest.importorskip("gsplat", reason="gsplat is not installed (pip install gsplat==1.5.3)")
    for name in [m for m in sys.modules if m == "nerfstudio" or m.startswith("nerfstudio.")] + ["nerfstudio"]:
        monkeypatch.setitem(sys.modules, name, None)  # as if not installed, also where it is
    monkeypatch.delitem(sys.modules, "exploregs_plugin.integrations.nerfstudio", raising=False)
    with pytest.raises(ImportError, match=r"pip install nerfstudio==1\.1\.5") as err:
        importlib.import_module("exploregs_plugin.integrations.nerfstudio")
    assert "\n" not in str(err.value)


NO_NERFSTUDIO = ("nerfstudio is not installed: it pins viser 0.2.7 and gsplat 1.4.0; run this file in its own "
                 "environment (docs/integrations.md, 'In nerfstudio')")


@pytest.fixture
def ns():
    """exploregs_plugin.integrations.nerfstudio; the test is skipped where nerfstudio is missing."""
    pytest.importorskip("nerfstudio", reason=NO_NERFSTUDIO)
    importlib.import_module("nerfstudio.configs.method_configs")  # nerfstudio's discovery runs here
    return importlib.import_module("exploregs_plugin.integrations.nerfstudio")


pytestmark = pytest.mark.usefixtures("one_thread")


class _NoLpips(torch.nn.Module):
    """Stands in for torchmetrics' LPIPS in splatfacto's constructor (its weights are a download)."""

    def __init__(self, *args, **kwargs):
        super().__init__()


def test_the_method_is_registered_under_nerfstudio_entry_point(ns):
    from nerfstudio.configs.method_configs import all_methods
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    assert ns.METHOD_NAME in methods and ns.METHOD_NAME in all_methods
    assert descriptions[ns.METHOD_NAME] == ns.DESCRIPTION
    config = all_methods[ns.METHOD_NAME]
    assert config.method_name == "exploregs-splatfacto"
    assert isinstance(config.pipeline.model, ns.ExploreSplatfactoModelConfig)
    assert config.pipeline.model._target is ns.ExploreSplatfactoModel
    splatfacto = all_methods["splatfacto"]
    assert type(splatfacto.pipeline.model).__name__ == "SplatfactoModelConfig"  # nerfstudio's own is untouched
    for name in ("max_num_iterations", "steps_per_eval_image", "mixed_precision"):
        assert getattr(config, name) == getattr(splatfacto, name), name
    assert config.optimizers == splatfacto.optimizers
    assert config.pipeline.model.cull_alpha_thresh == splatfacto.pipeline.model.cull_alpha_thresh


def test_config_round_trips_through_yaml_and_the_command_line(ns, tmp_path):
    import tyro
    import yaml
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    config = tyro.cli(AnnotatedBaseConfigUnion, args=[
        ns.METHOD_NAME, "--pipeline.model.n-seed", "5", "--pipeline.model.exploration-seed", "3",
        "--pipeline.model.cull-alpha-thresh", "0.2", "--output-dir", str(tmp_path),
    ])
    model = config.pipeline.model
    assert isinstance(model, ns.ExploreSplatfactoModelConfig)
    assert (model.n_seed, model.exploration_seed, model.cull_alpha_thresh, model.n_split) == (5, 3, 0.2, 20)
    path = tmp_path / "config.yml"
    path.write_text(yaml.dump(config), "utf8")  # as nerfstudio's trainer saves it
    loaded = yaml.load(path.read_text("utf8"), Loader=yaml.Loader)  # as ns-eval / ns-viewer load it
    assert loaded == config
    assert loaded.pipeline.model._target is ns.ExploreSplatfactoModel


def _model(ns, monkeypatch, **fields):
    import torchmetrics.image.lpip
    from nerfstudio.data.scene_box import SceneBox

    monkeypatch.setattr(torchmetrics.image.lpip, "LearnedPerceptualImagePatchSimilarity", _NoLpips)
    config = ns.exploregs_splatfacto_config().pipeline.model
    for key, value in fields.items():
        setattr(config, key, value)
    torch.manual_seed(0)
    box = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    return config.setup(scene_box=box, num_train_data=4, metadata={})


def test_the_model_builds_on_a_cpu_with_our_strategy_and_splatfacto_settings(ns, monkeypatch):
    from gsplat.strategy import DefaultStrategy

    from exploregs_plugin.integrations import into_gsplat as integ

    model = _model(ns, monkeypatch, num_random=500, n_seed=7, n_split=3, exploration_seed=5, cull_alpha_thresh=0.2)
    strategy = model.strategy
    assert isinstance(strategy, integ.GsplatSeedSplitStrategy) and isinstance(strategy, DefaultStrategy)
    # the model options configure eg-train's operators
    assert (strategy.seeding.n_seed, strategy.splitting.n_split, strategy.splitting.every) == (7, 3, 1)
    assert strategy.seed == 5
    assert strategy.seeding.prune_scale3d == 10.0
    assert strategy.prune_opa == 0.2  # splatfacto's own settings came along
    assert strategy.pause_refine_after_reset == 4 + model.config.refine_every
    assert strategy.refine_every == model.config.refine_every
    assert set(model.strategy_state) >= {"grad2d", "count", "scene_scale", "generator"}
    assert model.gauss_params["opacities"].shape == (500, 1) and model.gauss_params["features_dc"].shape == (500, 3)


def test_a_refine_step_of_the_model_adds_splits_and_seeds_in_splatfacto_layout(ns, monkeypatch):
    # splatfacto's callbacks with gsplat 1.4's info (radii [C, N]), the way its get_outputs makes it
    from exploregs_plugin.integrations import into_gsplat as integ

    model = _model(ns, monkeypatch, num_random=300, n_seed=7, n_split=3, warmup_length=0, refine_every=2,
                   reset_alpha_every=100, stop_split_at=1000)
    params = model.gauss_params
    optimizers = {k: torch.optim.Adam([p], lr=1e-3, eps=1e-15) for k, p in params.items()}
    model.strategy.check_sanity(params, optimizers)
    model.strategy.pause_refine_after_reset = 0  # refine at step 2 already (splatfacto waits num_train_data)
    sizes = []
    for step in (1, 2):
        model.step_cb(types.SimpleNamespace(optimizers=optimizers), step)
        n = params["means"].shape[0]
        means2d = (params["means"][None, :, :2] * 20 + 32).clone()
        means2d.retain_grad()
        radii = torch.full((1, n), 3, dtype=torch.int32) if not integ.RADII_PAIRS else torch.full((1, n, 2), 3, dtype=torch.int32)
        model.info = {"means2d": means2d, "radii": radii, "width": 64, "height": 64, "n_cameras": 1,
                      "gaussian_ids": None}
        model.strategy.step_pre_backward(params, optimizers, model.strategy_state, step, model.info)
        (means2d.square().sum() * 1e-3 + sum(p.square().sum() for p in params.values()) * 1e-6).backward()
        means2d.absgrad = means2d.grad.abs()  # splatfacto's use_absgrad: gsplat's rasterizer sets it
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        model.step_post_backward(step)
        sizes.append(params["means"].shape[0])
        for key, p in params.items():
            assert optimizers[key].param_groups[0]["params"][0] is p
            assert optimizers[key].state[p]["exp_avg"].shape == p.shape
    assert sizes[0] == 300 + 3  # step 1: Random Splitting only (gsplat refines on even steps here)
    assert sizes[1] >= sizes[0] + 3 + 7  # step 2: gsplat's growth, 3 more splits and 7 seeds (every refine_every)
    assert params["opacities"].shape[1:] == (1,) and params["features_dc"].shape[1:] == (3,)
    assert not params["features_rest"][-7:].any()  # seeds: higher SH start at zero
