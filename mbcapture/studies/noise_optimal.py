"""The noise-optimal exposure sequence of a conventional sensor, as Hasinoff, Durand and Freeman posed it
("Noise-optimal capture for high dynamic range photography", CVPR 2010): the exposures t_1..t_n, taken one
after another within a time budget T, that maximise the worst signal-to-noise ratio over a scene's range of
photo-electron rates [lambda_lo, lambda_hi].

Their noise model: each shot counts Poisson photo-electrons lambda t_i and adds read noise of variance sigma^2
(read noise and quantization; no dark current); a shot whose expected charge reaches the full well W is
unusable. The shots are merged at maximum likelihood (inverse variance), so at rate lambda

    SNR(lambda)^2 = lambda^2 sum over usable shots of t_i^2 / (lambda t_i + sigma^2).

The worst case over the range is at its low end or just above a shot's saturation rate W / t_i (where that
shot drops out), so it is evaluated exactly on those points (:func:`worst_snr`). The optimum (:func:`optimum`) is found by
differential evolution over the log exposures (scipy; seeded), every budget spent (more light never lowers an
unsaturated shot's SNR). Written here, independently of the capture's own SNR code
(:mod:`mbcapture.studies.dynamic_range`): it is the reference ``mbcapture design`` is checked against.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NoiseModel:
    """Read variance sigma^2 (e-^2), full well W (e-)."""

    read_variance_e2: float
    full_well_e: float


def snr_at(rate: np.ndarray, exposures_s: np.ndarray, model: NoiseModel) -> np.ndarray:
    """SNR of the maximum-likelihood merge of the shots at each photo-electron rate (e-/s); 0 where every shot
    saturates."""
    lam = np.asarray(rate, dtype=np.float64)[:, None]
    t = np.asarray(exposures_s, dtype=np.float64)[None, :]
    usable = lam * t < model.full_well_e
    info = np.where(usable, t**2 / (lam * t + model.read_variance_e2), 0.0).sum(axis=1)
    return lam[:, 0] * np.sqrt(info)


def worst_snr(exposures_s: np.ndarray, rate_lo: float, rate_hi: float, model: NoiseModel) -> float:
    """The least SNR over [rate_lo, rate_hi]: at its low end or just above a shot's saturation rate, where that
    shot drops out (between those points the SNR rises with the rate, so the least is at one of them)."""
    t = np.asarray(exposures_s, dtype=np.float64)
    cuts = model.full_well_e / t
    points = np.concatenate([[rate_lo, rate_hi], cuts[(cuts >= rate_lo) & (cuts < rate_hi)] * (1 + 1e-9)])
    return float(snr_at(points, t, model).min())


def optimum(n: int, budget_s: float, rate_lo: float, rate_hi: float, model: NoiseModel, seed: int = 0):
    """(exposures, worst SNR) of the best n shots spending ``budget_s``: the shots' shares of the budget by
    differential evolution (shares as a softmax of n - 1 free logits; the optimum is polished by L-BFGS-B)."""
    from scipy.optimize import differential_evolution

    def exposures(z: np.ndarray) -> np.ndarray:
        w = np.exp(np.concatenate([[0.0], z]))
        return np.sort(budget_s * w / w.sum())

    if n == 1:
        t = np.array([budget_s])
        return t, worst_snr(t, rate_lo, rate_hi, model)
    res = differential_evolution(
        lambda z: -worst_snr(exposures(z), rate_lo, rate_hi, model),
        bounds=[(-12.0, 12.0)] * (n - 1),
        seed=seed,
        tol=1e-10,
        maxiter=2000,
        polish=True,
    )
    t = exposures(res.x)
    return t, worst_snr(t, rate_lo, rate_hi, model)


def db(snr: float) -> float:
    return 20.0 * math.log10(snr) if snr > 0 else -math.inf
