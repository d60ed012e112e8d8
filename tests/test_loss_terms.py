"""The training loss as a list of terms: each term's value, their sum, and what a config builds."""

from __future__ import annotations

import pytest
import torch

from exploregs_plugin.engine.loss_terms import DepthTerm, PhotometricTerm, ViewLossInput, view_loss
from exploregs_plugin.model.losses import VIEW_PSNR, depth_l1, photometric_loss
from exploregs_plugin.engine.pipeline import PipelineConfig


def _view(with_depth: bool = True) -> ViewLossInput:
    g = torch.Generator().manual_seed(0)
    image, target = torch.rand(12, 16, 3, generator=g, requires_grad=True), torch.rand(12, 16, 3, generator=g)
    depth = (1.0 + torch.rand(12, 16, 1, generator=g)).requires_grad_()
    extras = {"depth": 1.0 + torch.rand(12, 16, 1, generator=g)} if with_depth else {}
    return ViewLossInput(image, target, depth, extras, index=3)


def test_the_terms_sum_in_order_and_log_their_parts():
    view = _view()
    loss, parts = view_loss([PhotometricTerm(0.2), DepthTerm(0.5, "inverse")], view)
    photo, photo_parts = photometric_loss(view.image, view.target, 0.2)
    depth = depth_l1(view.depth, view.extras["depth"], "inverse")
    assert torch.equal(loss, photo + 0.5 * depth)  # the same operations, bit for bit
    # the view's PSNR too where the compiled loss computed it in its pass (on the CPU)
    assert set(parts) - {VIEW_PSNR} == {"l1", "dssim", "depth"} and torch.equal(parts["depth"], depth.detach())
    assert set(parts) == set(photo_parts) | {"depth"}
    assert torch.equal(parts["l1"], photo_parts["l1"])
    loss.backward()  # the terms stay in the graph: both the image and the depth get gradients
    assert view.image.grad.abs().sum() > 0 and view.depth.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in parts.values())


def test_a_depth_term_without_depth_maps_and_an_empty_loss_are_clear_errors():
    with pytest.raises(ValueError, match="the dataset has no depth maps"):
        view_loss([PhotometricTerm(), DepthTerm(1.0)], _view(with_depth=False))
    with pytest.raises(ValueError, match="at least one term"):
        view_loss([], _view())


def test_a_pipeline_config_builds_the_terms_it_asks_for():
    assert PipelineConfig().loss_terms() == [PhotometricTerm(0.2)]
    terms = PipelineConfig(ssim_lambda=0.3, depth_loss_weight=0.1, depth_loss_space="inverse").loss_terms()
    assert terms[0] == PhotometricTerm(0.3) and isinstance(terms[1], DepthTerm)
    assert (terms[1].weight, terms[1].space) == (0.1, "inverse")
