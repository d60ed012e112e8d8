"""Error-mass densification (a negative result, outside the package): the per-view error mass,
the choice of rows, and a densification step that grows Default's count but picks by error mass.

Run: PYTHONPATH=experiments/nearside/errormass_negative python -m pytest experiments/nearside/errormass_negative
"""

from __future__ import annotations

import math

import pytest
import torch

from exploregs_plugin.strategies import StrategyError
from exploregs_plugin.strategies.observation import ViewError, ViewObservation
from exploregs_plugin.strategies.synthetic import make_gaussians, make_optimizers
from nearside_errormass_negative.strategy import ERROR_MASS, ErrorMassStrategy, choose_growth, error_mass

W, H = 8, 6


def test_error_mass_is_error_at_the_centre_times_the_light_delivered():
    error = torch.zeros(H, W)
    error[2, 3] = 0.5
    error[0, 0] = 0.25
    means2d = torch.tensor([[3.7, 2.2], [0.1, 0.9], [-1.0, 2.0], [3.5, 2.5], [float("nan"), 1.0]])
    weight = torch.tensor([4.0, 2.0, 9.0, 3.0, 1.0])
    visible = torch.tensor([True, True, True, False, True])
    mass = error_mass(error, means2d, weight, visible)
    # outside the image, not visible and a NaN centre give 0
    assert torch.allclose(mass, torch.tensor([2.0, 0.5, 0.0, 0.0, 0.0]))


def test_choose_growth_splits_the_count_between_error_mass_and_the_statistic():
    statistic = torch.tensor([5.0, 4.0, 3.0, 2.0, 1.0])
    mass = torch.tensor([0.0, 0.1, 0.0, 0.9, 0.5])
    assert torch.where(choose_growth(statistic, mass, 3, 2 / 3))[0].tolist() == [0, 3, 4]
    assert torch.where(choose_growth(statistic, mass, 3, 1.0))[0].tolist() == [1, 3, 4]
    assert torch.where(choose_growth(statistic, mass, 3, 0.0))[0].tolist() == [0, 1, 2]
    # fewer rows with mass than the share asks for: the statistic fills the rest
    assert torch.where(choose_growth(statistic, torch.tensor([0.0, 0.0, 0.0, 0.0, 0.2]), 2, 1.0))[0].tolist() == [0, 4]
    assert not choose_growth(statistic, mass, 0, 1.0).any()


def _view(grads: torch.Tensor, positions: torch.Tensor, error: torch.Tensor) -> ViewObservation:
    n = grads.shape[0]
    means2d = positions.clone().requires_grad_(True)
    means2d.grad = grads.clone()
    radii = torch.full((n, 2), 3, dtype=torch.int32)
    visibility = torch.stack([torch.ones(n), torch.ones(n)], -1)  # each delivers one pixel of light
    err = ViewError(0, torch.eye(4), torch.eye(3), torch.zeros(H, W, 3), error)
    return ViewObservation(W, H, radii, torch.zeros(3), means2d=means2d, visibility=visibility, error=err)


@pytest.mark.parametrize("share, grown", [(1.0, 2), (0.0, 0)])
def test_a_densification_grows_defaults_count_and_picks_by_error_mass(share, grown):
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(4, g)
    with torch.no_grad():
        params["scales"].fill_(math.log(1e-3))  # all small: growth is a clone
    optimizers = make_optimizers(params)
    s = ErrorMassStrategy(refine_start_iter=0, refine_stop_iter=100, refine_every=2, reset_every=1000,
                          error_share=share)
    state = s.initialize_state(scene_scale=1.0)
    # Gaussian 0 alone passes grow_grad2d; the error sits under Gaussian 2
    grads = torch.tensor([[1e-3, 0.0], [0.0, 0.0], [1e-6, 0.0], [0.0, 0.0]])
    positions = torch.tensor([[1.5, 1.5], [6.5, 1.5], [3.5, 4.5], [6.5, 4.5]])
    error = torch.zeros(H, W)
    error[4, 3] = 0.8
    s.step_post_backward(params, optimizers, state, 1, [_view(grads, positions, error)])
    assert torch.allclose(state["stats"][ERROR_MASS], torch.tensor([0.0, 0.0, 0.8, 0.0]))
    before = params["means"].detach().clone()
    counts = s.step_post_backward(params, optimizers, state, 2, [_view(grads, positions, error)])
    assert counts["cloned"] == 1 and params["means"].shape[0] == 5  # Default's count: one
    assert torch.equal(params["means"].detach()[4], before[grown])
    assert not state["stats"][ERROR_MASS].any()  # a new window starts empty


def test_missing_error_map_is_a_clear_error():
    g = torch.Generator().manual_seed(0)
    params = make_gaussians(2, g)
    s = ErrorMassStrategy(refine_start_iter=0, refine_stop_iter=100, refine_every=2, reset_every=1000)
    view = _view(torch.zeros(2, 2), torch.zeros(2, 2), torch.zeros(H, W))
    view.error = None
    with pytest.raises(StrategyError, match="error map"):
        s.step_post_backward(params, make_optimizers(params), s.initialize_state(), 1, [view])
    with pytest.raises(StrategyError, match="error_share"):
        ErrorMassStrategy(error_share=1.5)
