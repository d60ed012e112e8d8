"""Operators per training step: the count's definition, and a pin per method that fails when a
change makes a step dispatch more than 10% more operators (bench/components/op_count.py)."""

from types import SimpleNamespace

import pytest

from exploregs_plugin.bench.components.op_count import count_operators, top_level_operators
from exploregs_plugin.rasterizer.cpp_backend import cpp_problem

PINNED_PER_STEP = {
    "exploregs-default": 88.1,
    "exploregs-seedsplit": 146.1,
    "exploregs-mcmc": 179.1,
}
"""Top-level operators per step, steps 20-29 of a 300-step schedule, cpp backend (``python -m
exploregs_plugin.bench.components.op_count``; the benchmark's builtin:default and the test's
builtin:tiny, which the suite makes anyway, give the same counts). Change a figure on purpose: up
when a change must add operators (say why in its message), down when one removes them."""
GROWTH_ALLOWED = 1.10
STALE_BELOW = 0.75  # a pin this far above the count no longer guards anything: lower it


def _event(name, parent=None):
    return SimpleNamespace(name=name, cpu_parent=parent)


def test_only_operators_no_operator_encloses_count():
    step = _event("ProfilerStep#1")
    mul = _event("aten::mul", step)
    inner = _event("aten::empty", mul)  # inside mul: not top level
    node = _event("autograd::engine::evaluate_function: MulBackward0")
    backward_mul = _event("aten::mul", node)  # a backward function's operator counts
    scope = _event("Optimizer.step#Adam.step")
    adam = _event("aten::_fused_adam_", scope)
    nested = _event("aten::copy_", _event("user scope", adam))  # an operator above, through a scope
    counts = top_level_operators([step, mul, inner, node, backward_mul, scope, adam, nested])
    assert counts == {"aten::mul": 2, "aten::_fused_adam_": 1}


@pytest.mark.skipif(cpp_problem() is not None, reason=f"the pins are for the cpp backend: {cpp_problem()}")
@pytest.mark.parametrize("method", sorted(PINNED_PER_STEP))
def test_operators_per_step_stay_within_the_pin(method):
    count = count_operators(method, data="builtin:tiny")
    pinned = PINNED_PER_STEP[method]
    assert count.per_step <= pinned * GROWTH_ALLOWED, (
        f"{method}: {count.per_step:.1f} operators per step, more than 10% over the pinned {pinned}: "
        f"find the new operators (python -m exploregs_plugin.bench.components.op_count --top 40), or raise "
        f"the pin on purpose")
    assert count.per_step >= pinned * STALE_BELOW, (
        f"{method}: {count.per_step:.1f} operators per step, far under the pinned {pinned}: lower the pin")
    assert count.steps == 10 and "aten::_fused_adam_" in count.by_name  # the window holds whole steps
