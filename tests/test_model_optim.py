"""The run's Adam: torch's fused kernel where the device has it, called by our own class with
torch's bits and state dicts, and the same Adam as torch's for-loop one up to float32 rounding
(exploregs_plugin/model/optim.py, exploregs_plugin/model/fused_adam.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from torch import nn

from exploregs_plugin.model.fused_adam import FusedAdam, fused_adam_step
from exploregs_plugin.model.optim import ADAM_EPS, OptimizerConfig, OptimizerSet, ParamGroup, adam


def _gradients(step: int, shape: tuple[int, ...]) -> torch.Tensor:
    """Gradients over twelve orders of magnitude, with rows that never get one (Gaussians that no
    view sees: their moments stay zero, and m / (sqrt(v) + eps) must stay 0, not 0/0)."""
    g = torch.Generator().manual_seed(1000 + step)
    grad = torch.randn(shape, generator=g) * torch.logspace(-9, 3, shape[0])[:, None]
    grad[::7] = 0.0
    return grad


def test_fused_adam_follows_the_for_loop_adam_over_100_steps():
    torch.manual_seed(0)
    start = torch.randn(64, 3)
    fused_p, loop_p = nn.Parameter(start.clone()), nn.Parameter(start.clone())
    fused = adam([{"params": [fused_p], "lr": 1e-2}], (0.9, 0.999))
    loop = torch.optim.Adam([loop_p], lr=1e-2, eps=ADAM_EPS, betas=(0.9, 0.999), foreach=False)
    assert fused.defaults["fused"] and not loop.defaults["fused"]
    for step in range(100):
        lr = 1e-2 * 0.97 ** step  # the means' decaying rate, set each step as the trainer does
        for opt, p in ((fused, fused_p), (loop, loop_p)):
            opt.param_groups[0]["lr"] = lr
            p.grad = _gradients(step, tuple(start.shape))
            opt.step()
    moved = (loop_p - start).abs()
    assert torch.equal(fused_p.detach()[::7], start[::7]) and torch.equal(loop_p.detach()[::7], start[::7])
    assert (moved[1:7] > 1e-4).all()  # every row with a gradient moved, the 1e-9 ones too (eps 1e-15)
    # float32 rounding of 100 steps of a few ops each, on moves of order 1
    assert torch.allclose(fused_p.detach(), loop_p.detach(), rtol=0.0, atol=2e-6), (fused_p - loop_p).abs().max()
    for key in ("exp_avg", "exp_avg_sq"):
        a, b = fused.state[fused_p][key], loop.state[loop_p][key]
        assert torch.allclose(a, b, rtol=1e-5, atol=0.0), (key, ((a - b).abs() / b.abs().clamp_min(1e-30)).max())


def test_the_runs_optimizers_are_fused_on_the_cpu_and_keep_their_rates():
    params = nn.ParameterDict({name: nn.Parameter(torch.zeros(5, k)) for name, k in
                               (("means", 3), ("scales", 3), ("quats", 4), ("opacities", 1), ("sh0", 3), ("shN", 45))})
    config = OptimizerConfig()
    optimizers = config.setup(params, scene_extent=2.0, batch_size=4)
    assert all(opt.defaults["fused"] for opt in optimizers.values())
    assert optimizers["means"].param_groups[0]["lr"] == config.means_lr * 2.0 * 2.0  # extent x sqrt(B)
    assert optimizers["means"].defaults["betas"] == (0.9 ** 4, 0.999 ** 4)
    field = ParamGroup("planes", [nn.Parameter(torch.zeros(3))], lambda step: 1e-3 / (1 + step))
    optimizer_set = OptimizerSet(optimizers, lambda step: 0.5 ** step, [field])
    assert optimizer_set.shared.defaults["fused"]
    for p in list(params.values()) + field.params:
        p.grad = torch.ones_like(p)
    assert optimizer_set.step(3) == 0.125 and optimizer_set.lrs()["planes"] == 1e-3 / 4
    # Adam's first step moves every element by lr (m / sqrt(v) = 1): the fused step did step
    assert torch.allclose(params["means"].detach(), torch.full((5, 3), -0.125))


def _torch_fused(groups):
    return torch.optim.Adam(groups, eps=ADAM_EPS, betas=(0.9, 0.99), fused=True)


def _ours(groups):
    return FusedAdam(groups, eps=ADAM_EPS, betas=(0.9, 0.99))


def _groups(start: dict[str, torch.Tensor]) -> tuple[dict[str, nn.Parameter], list[dict]]:
    params = {name: nn.Parameter(value.clone()) for name, value in start.items()}
    return params, [{"params": [params["a"], params["b"]], "lr": 1e-2, "name": "ab"},
                    {"params": [params["c"]], "lr": 3e-3, "name": "c"}]


def _assert_same_bits(ours: FusedAdam, theirs: torch.optim.Adam, mine: dict, other: dict) -> None:
    for name in mine:
        assert torch.equal(mine[name].detach(), other[name].detach()), name
    a, b = ours.state_dict(), theirs.state_dict()
    assert a["param_groups"] == b["param_groups"]
    assert a["state"].keys() == b["state"].keys()
    for index, state in a["state"].items():
        assert state.keys() == b["state"][index].keys()
        for key, value in state.items():
            other_value = b["state"][index][key]
            assert value.dtype == other_value.dtype and value.device == other_value.device, key
            assert torch.equal(value, other_value), (index, key)


def test_fused_adam_is_torchs_fused_adam_bit_for_bit():
    """Two groups, a parameter that has no gradient for its first steps (its state and counter
    start late, as in torch), gradients over twelve orders of magnitude, a rate set each step:
    the parameters, moments, counters and state dicts are torch's bits, stepped one optimizer at a
    time or together with a second one (fused_adam_step's one counter update)."""
    torch.manual_seed(0)
    start = {"a": torch.randn(64, 3), "b": torch.randn(64, 1), "c": torch.randn(64, 4)}
    mine, ours_groups = _groups(start)
    other, their_groups = _groups(start)
    ours, theirs = _ours(ours_groups), _torch_fused(their_groups)
    solo_p = nn.Parameter(torch.randn(64, 2))
    solo_ref = nn.Parameter(solo_p.detach().clone())
    solo, solo_theirs = _ours([solo_p]), _torch_fused([solo_ref])
    for step in range(30):
        for params in (mine, other):
            for name, p in params.items():
                p.grad = None if name == "c" and step < 5 else _gradients(step, tuple(p.shape))
        solo_p.grad, solo_ref.grad = _gradients(step + 50, (64, 2)), _gradients(step + 50, (64, 2))
        for opt in (ours, theirs):
            opt.param_groups[0]["lr"] = 1e-2 * 0.97 ** step
        if step % 2:
            fused_adam_step([ours, solo])
        else:
            ours.step()
            solo.step()
        theirs.step()
        solo_theirs.step()
        if step == 3:
            assert mine["c"] not in ours.state and other["c"] not in theirs.state
        _assert_same_bits(ours, theirs, mine, other)
        assert torch.equal(solo_p.detach(), solo_ref.detach())
    assert float(ours.state[mine["a"]]["step"]) == 30 and float(ours.state[mine["c"]]["step"]) == 25


def test_state_dicts_load_between_torchs_adam_and_fused_adam(tmp_path):
    """A checkpoint written by torch's Adam resumes in FusedAdam, and the other way round, through
    torch.save and torch.load: the same bits after five more steps as the run that never stopped."""
    torch.manual_seed(1)
    start = {"a": torch.randn(32, 3), "b": torch.randn(32, 1), "c": torch.randn(32, 4)}
    runs = {}
    for first, second in ((_torch_fused, _ours), (_ours, _torch_fused)):
        params, groups = _groups(start)
        opt = first(groups)
        reference_params, reference_groups = _groups(start)
        reference = _torch_fused(reference_groups)
        for step in range(10):
            if step == 5:  # stop: save, and resume in the other class with fresh tensors
                torch.save({"params": {k: p.detach() for k, p in params.items()}, "opt": opt.state_dict()},
                           tmp_path / "ckpt.pt")
                saved = torch.load(tmp_path / "ckpt.pt")
                params, groups = _groups(saved["params"])
                groups[0]["lr"] = groups[1]["lr"] = 0.5  # the saved rates are restored
                opt = second(groups)
                opt.load_state_dict(saved["opt"])
                assert [g["lr"] for g in opt.param_groups] == [1e-2, 3e-3]
            for ps in (params, reference_params):
                for name, p in ps.items():
                    p.grad = _gradients(step, tuple(p.shape))
            opt.step()
            reference.step()
        runs[second.__name__] = params
        for name in params:
            assert torch.equal(params[name].detach(), reference_params[name].detach()), (second.__name__, name)
    with pytest.raises(ValueError, match="do not match"):
        _ours([nn.Parameter(torch.zeros(2))]).load_state_dict(_torch_fused(_groups(start)[1]).state_dict())


def test_fused_adam_refuses_what_it_does_not_run():
    with pytest.raises(ValueError, match="plain Adam"):
        FusedAdam([{"params": [nn.Parameter(torch.zeros(2))], "weight_decay": 0.1}])
    with pytest.raises(ValueError, match="floating point"):
        FusedAdam([nn.Parameter(torch.zeros(2, dtype=torch.complex64))])
    p = nn.Parameter(torch.zeros(2))
    with pytest.raises(ValueError, match="more than one group"):
        FusedAdam([{"params": [p]}, {"params": [p]}])


def test_a_training_step_never_imports_torch_dynamo():
    """torch's Adam imports torch._dynamo on its first step (about 1.5 s of CPU in every process
    that trains); the run's optimizers never do: set up, stepped, saved and loaded in a fresh
    process."""
    code = """if True:
        import sys
        import exploregs_plugin
        import torch
        from torch import nn
        from exploregs_plugin.model.optim import OptimizerConfig, OptimizerSet, ParamGroup
        params = nn.ParameterDict({n: nn.Parameter(torch.zeros(5, 3)) for n in ("means", "scales", "sh0")})
        field = ParamGroup("planes", [nn.Parameter(torch.zeros(3))], lambda step: 1e-3)
        optim = OptimizerSet(OptimizerConfig().setup(params, 1.0), lambda step: 1e-3, [field])
        for p in [*params.values(), *field.params]:
            p.grad = torch.ones_like(p)
        optim.step(0)
        optim.load_state_dict(optim.state_dict())
        assert float(params["means"][0, 0]) < 0
        print("torch._dynamo" in sys.modules)
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"


def test_zero_grad_drops_or_zeroes_the_gradients_as_torchs_optimizers_do():
    p = nn.Parameter(torch.ones(3))
    opt = _ours([p])
    p.grad = torch.full((3,), 2.0)
    kept = p.grad
    opt.zero_grad(set_to_none=False)
    assert p.grad is kept and torch.equal(p.grad, torch.zeros(3))
    opt.zero_grad()
    assert p.grad is None
