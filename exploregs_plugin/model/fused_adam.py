"""Adam as torch's fused kernel, called directly: the same update, state and checkpoints as
``torch.optim.Adam(fused=True)``, without the machinery around it.

Why not torch's class: its ``step`` (and ``add_param_group``, which its constructor calls) imports
``torch._dynamo`` on first use, to mark itself as not compilable. That import is about 1.5 s of
CPU in every process that trains, a third of a short run's start-up; this class never compiles
anything, so it has nothing to mark. Each step is, per parameter group, what torch's fused path
dispatches: the step counters raised by one (``torch._foreach_add_``), then ``torch._fused_adam_``
on the group's parameters. :func:`fused_adam_step` steps several optimizers with one counter
update for all of them (the same values: the counters are independent scalars).

The state (``state[p]``: ``step`` as a float32 scalar on the parameter's device, ``exp_avg``,
``exp_avg_sq``), the param groups and :meth:`FusedAdam.state_dict` are torch's, so the
strategies' row operations (``strategies/row_ops.py``), gsplat's and checkpoints written by
``torch.optim.Adam`` work unchanged, in both directions (tests/test_model_optim.py).
"""

from __future__ import annotations

import copy
from collections import defaultdict
from collections.abc import Iterable, Sequence
from typing import Any

import torch
from torch import Tensor

FUSED_DEVICES = ("cpu", "cuda")
"""Devices with torch's fused Adam kernel."""

_GROUP_DEFAULTS = {"weight_decay": 0.0, "amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
                   "differentiable": False, "fused": True, "decoupled_weight_decay": False}
"""The fields torch's Adam keeps in every group (so a state dict reads the same in both classes);
this class runs with exactly these values."""


class FusedAdam:
    """Adam with torch's fused kernel, for float parameters on the CPU or a CUDA device."""

    def __init__(self, params: Iterable[dict[str, Any]] | Iterable[Tensor], lr: float = 1e-3,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8) -> None:
        self.defaults: dict[str, Any] = {"lr": lr, "betas": tuple(betas), "eps": eps, **_GROUP_DEFAULTS}
        self.state: defaultdict[Tensor, dict[str, Any]] = defaultdict(dict)
        self.param_groups: list[dict[str, Any]] = []
        groups = list(params)
        if groups and not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        for group in groups:
            self.add_param_group(group)

    def add_param_group(self, group: dict[str, Any]) -> None:
        params = group["params"]
        params = [params] if isinstance(params, Tensor) else list(params)
        seen = {id(p) for g in self.param_groups for p in g["params"]}
        for p in params:
            if not isinstance(p, Tensor) or not p.is_leaf:
                raise ValueError("FusedAdam: parameters must be leaf tensors")
            if not p.is_floating_point() or p.device.type not in FUSED_DEVICES:
                raise ValueError(f"FusedAdam: parameters must be floating point on one of {FUSED_DEVICES}, got "
                                 f"{p.dtype} on {p.device}")
            if id(p) in seen:
                raise ValueError("FusedAdam: a parameter appears in more than one group")
            seen.add(id(p))
        fields = {**self.defaults, **{k: v for k, v in group.items() if k != "params"}}
        if {k: fields[k] for k in _GROUP_DEFAULTS} != _GROUP_DEFAULTS:
            raise ValueError(f"FusedAdam runs plain Adam only ({_GROUP_DEFAULTS})")
        self.param_groups.append({"params": params, **fields})

    def step(self) -> None:
        fused_adam_step([self])

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                    continue
                if p.grad.grad_fn is not None:
                    p.grad.detach_()
                else:
                    p.grad.requires_grad_(False)
                p.grad.zero_()

    # ------------------------------------------------------------------ torch's state-dict format
    def state_dict(self) -> dict[str, Any]:
        """``{"state": {index: {...}}, "param_groups": [...]}`` with parameters as their index in
        group order, as torch's ``Optimizer.state_dict`` (tensors by reference, not copied)."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            for p in group["params"]:
                index.setdefault(id(p), len(index))
            groups.append({**{k: v for k, v in group.items() if k != "params"},
                           "params": [index[id(p)] for p in group["params"]]})
        state = {index[id(p)]: value for p, value in self.state.items() if id(p) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (or torch's Adam's): the groups' fields from the saved ones, the
        moments in each parameter's dtype and device, the step counters as float32 scalars there."""
        saved_groups = copy.deepcopy(state_dict["param_groups"])
        if len(saved_groups) != len(self.param_groups) or any(
                len(s["params"]) != len(g["params"]) for s, g in zip(saved_groups, self.param_groups)):
            raise ValueError("FusedAdam.load_state_dict: the saved groups do not match this optimizer's parameters")
        by_index = {i: p for s, g in zip(saved_groups, self.param_groups) for i, p in zip(s["params"], g["params"])}
        state: defaultdict[Tensor, dict[str, Any]] = defaultdict(dict)
        for i, value in state_dict["state"].items():
            p = by_index[i]
            state[p] = {k: _as_state(p, k, v) for k, v in value.items()}
        self.state = state
        self.param_groups = [{**_GROUP_DEFAULTS, **{k: v for k, v in s.items() if k != "params"},
                              "params": g["params"]} for s, g in zip(saved_groups, self.param_groups)]


def _as_state(param: Tensor, key: str, value: Any) -> Any:
    if not isinstance(value, Tensor):
        return torch.tensor(float(value), dtype=torch.float32, device=param.device) if key == "step" else value
    if key == "step":  # the fused kernel reads its counter as float32 on the parameter's device
        return value.to(dtype=torch.float32, device=param.device)
    return value.to(dtype=param.dtype, device=param.device)


def fused_adam_step(optimizers: Sequence[FusedAdam]) -> None:
    """One Adam step of every parameter with a gradient in ``optimizers``: the step counters of all
    of them raised in one call per device, then one fused update per group and (device, dtype)."""
    calls: list[tuple[dict[str, Any], list[Tensor], list[Tensor], list[Tensor], list[Tensor], list[Tensor]]] = []
    steps_by_device: dict[torch.device, list[Tensor]] = {}
    with torch.no_grad():
        for optimizer in optimizers:
            for group in optimizer.param_groups:
                lists: dict[tuple[torch.device, torch.dtype], tuple[list[Tensor], ...]] = {}
                for p in group["params"]:
                    if p.grad is None:
                        continue
                    if p.grad.is_sparse:
                        raise RuntimeError("FusedAdam does not take sparse gradients")
                    state = optimizer.state[p]
                    if not state:  # torch's lazy initialisation, in its dtypes
                        state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                        state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                        state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    entry = lists.setdefault((p.device, p.dtype), ([], [], [], [], []))
                    for items, value in zip(entry, (p, p.grad, state["exp_avg"], state["exp_avg_sq"], state["step"])):
                        items.append(value)
                    steps_by_device.setdefault(p.device, []).append(state["step"])
                calls.extend((group, *entry) for entry in lists.values())
        for steps in steps_by_device.values():
            torch._foreach_add_(steps, 1)
        for group, params, grads, exp_avgs, exp_avg_sqs, steps in calls:
            beta1, beta2 = group["betas"]
            torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], steps, amsgrad=False, lr=group["lr"],
                               beta1=beta1, beta2=beta2, weight_decay=0.0, eps=group["eps"], maximize=False)
