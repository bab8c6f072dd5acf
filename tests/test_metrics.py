"""Error metrics: hand-computed values, masks, PU21 encoding."""

from __future__ import annotations

import numpy as np
import pytest

from mbcapture.metrics import (
    PU21_PARAMETERS,
    psnr,
    pu21_encode,
    pu21_psnr,
    relative_mse,
)


def test_relative_mse_by_hand():
    y = np.array([1.0, 2.0, 0.0])
    x = np.array([1.5, 2.0, 0.1])
    # ((0.5^2)/(1 + 0.01) + 0 + 0.1^2 / (0 + 0.01)) / 3
    expected = (0.25 / 1.01 + 0.0 + 0.01 / 0.01) / 3
    assert relative_mse(x, y) == pytest.approx(expected)
    assert relative_mse(x, y, eps=1.0) == pytest.approx((0.25 / 2 + 0 + 0.01 / 1) / 3)
    mask = np.array([True, True, False])
    assert relative_mse(x, y, mask=mask) == pytest.approx(0.25 / 1.01 / 2)


def test_psnr_by_hand_and_mask():
    y = np.array([[0.0, 1.0], [0.5, 0.25]])
    x = y + np.array([[0.1, -0.1], [0.0, 0.0]])
    # MSE = (0.01 + 0.01) / 4 = 0.005, peak 1 -> 10 log10(200) = 23.0103 dB
    assert psnr(x, y) == pytest.approx(10 * np.log10(200.0))
    assert psnr(x, y, peak=2.0) == pytest.approx(10 * np.log10(800.0))
    assert psnr(x, y, mask=np.array([[False, False], [True, True]])) == float("inf")
    with pytest.raises(ValueError):
        psnr(x, y, mask=np.zeros((2, 2), dtype=bool))


def test_pu21_monotonic_and_reference_values():
    y = np.geomspace(0.005, 10_000.0, 2000)
    for variant in PU21_PARAMETERS:
        v = pu21_encode(y, variant)
        assert np.all(np.diff(v) > 0), variant
        assert np.all(v >= 0)
    # By hand from V = p7 (((p1 + p2 Y^p4) / (1 + p3 Y^p4))^p5 - p6), banding_glare:
    # Y = 1: (0.353487901 + 0.3734658629) / (1 + 8.277049286e-05) = 0.7268936;
    #   0.7268936^0.09150303166 = exp(0.0915030 * (-0.3189752)) = exp(-0.0291869) = 0.9712346;
    #   V = 596.3148142 * (0.9712346 - 0.9099517204) = 36.544.
    assert float(pu21_encode(np.array(1.0))) == pytest.approx(36.544, abs=2e-3)
    # Y = 100: 100^0.9062562627 = exp(0.9062563 * 4.6051702) = 64.94004;
    #   (0.353488 + 0.3734659 * 64.94004) / (1 + 8.277049e-5 * 64.94004) = 24.60637 / 1.0053751 = 24.47482;
    #   ^0.0915030 = exp(0.0915030 * 3.1976448) = 1.3398989;
    #   V = 596.3148 * (1.3398989 - 0.9099517) = 256.384 (the paper maps 100 cd/m^2 to about 256).
    assert float(pu21_encode(np.array(100.0))) == pytest.approx(256.384, abs=2e-3)
    # Clamped outside [0.005, 10000] cd/m^2.
    assert pu21_encode(np.array(1e-6)) == pu21_encode(np.array(0.005))
    assert pu21_encode(np.array(1e6)) == pu21_encode(np.array(1e4))
    with pytest.raises(ValueError, match="banding_glare"):
        pu21_encode(np.array(1.0), variant="nope")


def test_pu21_psnr():
    rng = np.random.default_rng(0)
    y = np.geomspace(0.01, 1000.0, 1000)
    assert pu21_psnr(y, y) == float("inf")
    small = pu21_psnr(y * (1 + 0.01 * rng.standard_normal(y.size)), y)
    large = pu21_psnr(y * (1 + 0.1 * rng.standard_normal(y.size)), y)
    assert np.isfinite(small) and small > large
