"""Losses: values by hand, gradients finite for HDR extremes, registry."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from training import losses, metrics
from training.errors import ConfigError


def test_smape_matches_eq9_and_the_metric():
    g = torch.Generator().manual_seed(0)
    d = torch.rand(2, 3, 8, 8, generator=g, dtype=torch.float64) * 5
    r = torch.rand(2, 3, 8, 8, generator=g, dtype=torch.float64) * 5
    by_hand = (torch.abs(d - r) / (d.abs() + r.abs() + 0.01)).mean()
    assert losses.smape(d, r).item() == pytest.approx(by_hand.item())
    # the numpy metric on HWC agrees with the torch loss on BCHW
    assert metrics.smape(d[0].permute(1, 2, 0).numpy(), r[0].permute(1, 2, 0).numpy()) == \
        pytest.approx(losses.smape(d[:1], r[:1]).item())


def test_l2_l1_on_tonemapped():
    d = torch.tensor([[[[0.0]], [[1.0]], [[np.e - 1.0]]]])
    r = torch.zeros_like(d)
    tm1 = 1.055 * np.log(2.0) ** (1 / 2.4) - 0.055
    assert losses.l2_tonemap(d, r).item() == pytest.approx((0 + tm1 ** 2 + 1.0) / 3, rel=1e-5)
    assert losses.build_loss("l1")(d, r).item() == pytest.approx((0 + tm1 + 1.0) / 3, rel=1e-5)


def test_the_unused_temporal_l1_loss_is_gone():
    """Only Hasselgren et al.'s l1-temporal remains (temporal-l1 was unused and easily confused with it)."""
    assert "temporal-l1" not in losses.LOSSES and "l1-temporal" in losses.LOSSES


@pytest.mark.parametrize("name", ["smape", "l2-tonemap", "l1"])
def test_losses_finite_gradients_for_hdr_extremes(name):
    d = torch.tensor([0.0, 1e-8, 1.0, 1e6, 1e8, -1e-3]).view(1, 1, 2, 3).repeat(1, 3, 1, 1).requires_grad_(True)
    r = torch.tensor([0.0, 0.0, 1e8, 1.0, 1e8, 0.0]).view(1, 1, 2, 3).repeat(1, 3, 1, 1)
    loss = losses.build_loss(name)(d, r)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(d.grad).all()


def test_unknown_loss():
    with pytest.raises(ConfigError, match="loss"):
        losses.build_loss("nope")
