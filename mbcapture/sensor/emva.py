"""The figures of an EMVA 1288 datasheet from flat-field and dark frames, by the formulas of the
standard's Release 4.0 *Linear* document (the camera model of Release 3.1 with its corrections).

The model: a pixel turns mu_p photons into mu_e = eta mu_p electrons; the camera outputs
mu_y = mu_y.dark + K mu_e digital numbers, with temporal variance
sigma_y^2 = K^2 sigma_d^2 + sigma_q^2 + K (mu_y - mu_y.dark)   (sigma_q^2 = 1/12 DN^2).

Each function below names the section of Release 4.0 Linear it follows ("sensitivity, linearity
and noise", "dark current", "spatial nonuniformity"). They work on plain arrays, so they can be
checked against any camera's frames; :mod:`mbcapture.studies.characterize` takes the frames from the
simulated sensor.

Written here rather than imported: the EMVA's reference implementation (the ``emva1288``
package) pins numpy < 2 and is not maintained for current Pythons. Every uncertainty is a standard
uncertainty (1 sigma) propagated from the number of pixels and frames behind each point:
the variance of a mean of n values is s^2 / n, that of a sample variance of n values 2 s^4 / n
(normal approximation), and fits are weighted by those variances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..metrics import row_column_pixel_variances

#: Quantization noise variance of an ideal ADC, DN^2.
SIGMA_Q2_DN2 = 1.0 / 12.0
#: Release 4.0's lower limit of the dark variance: below it quantization dominates, DN^2.
MIN_DARK_VARIANCE_DN2 = 0.24
#: The photon transfer and responsivity fits use the points up to this fraction of saturation.
FIT_UP_TO = 0.70
#: The linearity error is evaluated between these fractions of saturation.
LINEARITY_RANGE = (0.05, 0.95)


@dataclass(frozen=True)
class Figure:
    """One datasheet figure: its value, standard uncertainty (None where none can be given), unit and
    the part of the standard it follows."""

    value: float
    uncertainty: float | None
    unit: str
    section: str

    def as_dict(self) -> dict:
        return {
            "value": float(self.value),
            "uncertainty": None if self.uncertainty is None else float(self.uncertainty),
            "unit": self.unit,
            "section": self.section,
        }


@dataclass(frozen=True)
class PairStats:
    """Mean and temporal variance of frame pairs, per exposure step (arrays of one length)."""

    mean: np.ndarray
    variance: np.ndarray
    pixels: int


def pair_stats(frames_a: np.ndarray, frames_b: np.ndarray) -> PairStats:
    """Release 4.0 Linear, 'sensitivity, linearity and noise': two frames A, B per step (S, H, W);
    mu_y = (<A> + <B>) / 2 and sigma_y^2 = <((A - <A>) - (B - <B>))^2> / 2, the temporal variance free of
    the fixed pattern (it cancels in the difference) and of a drift between the frames."""
    a = np.asarray(frames_a, dtype=np.float64)
    b = np.asarray(frames_b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"frames: expected two (steps, H, W) stacks of one shape, got {a.shape} and {b.shape}")
    ma, mb = a.mean(axis=(1, 2)), b.mean(axis=(1, 2))
    d = (a - ma[:, None, None]) - (b - mb[:, None, None])
    return PairStats(mean=(ma + mb) / 2, variance=(d**2).mean(axis=(1, 2)) / 2, pixels=int(a.shape[1] * a.shape[2]))


def weighted_line(
    x: np.ndarray, y: np.ndarray, var_y: np.ndarray, *, through_origin: bool = False
) -> tuple[float, float, np.ndarray]:
    """Least squares y = a + b x weighted by 1 / var_y: (b, a, covariance of (a, b)). With
    ``through_origin`` a = 0. The covariance is the one the stated point variances give (not scaled by
    the residuals), so it is what the number of pixels and frames implies."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    w = 1.0 / np.maximum(np.asarray(var_y, np.float64), 1e-300)
    X = x[:, None] if through_origin else np.stack([np.ones_like(x), x], axis=1)
    if X.shape[0] < X.shape[1] + 1:
        raise ValueError(f"a line needs at least {X.shape[1] + 1} points, got {X.shape[0]}")
    cov = np.linalg.inv(X.T @ (w[:, None] * X))
    coef = cov @ (X.T @ (w * y))
    if through_origin:
        return float(coef[0]), 0.0, np.array([[0.0, 0.0], [0.0, cov[0, 0]]])
    return float(coef[1]), float(coef[0]), cov


def _var_of_variance(s2: np.ndarray, n: int) -> np.ndarray:
    return 2.0 * np.asarray(s2) ** 2 / n


def dark_variance_at_zero(t_s: np.ndarray, dark: PairStats) -> tuple[float, float]:
    """The temporal dark variance (DN^2) extrapolated to t = 0 along the dark frames (their variance grows with the
    dark current's shot noise), at least :data:`MIN_DARK_VARIANCE_DN2`, and its uncertainty."""
    n = dark.pixels
    if np.unique(t_s).size > 2:
        _, s2_dark0, cov_d = weighted_line(t_s, dark.variance, _var_of_variance(dark.variance, n))
        s_s2_dark0 = float(np.sqrt(cov_d[0, 0]))
    else:
        s2_dark0, s_s2_dark0 = float(dark.variance[0]), float(np.sqrt(_var_of_variance(dark.variance[0], n)))
    s2_dark0 = max(s2_dark0, MIN_DARK_VARIANCE_DN2)
    return s2_dark0, s_s2_dark0


def linearity_error(mu_p, y, var_mean, y_sat: float, i_sat: int) -> tuple[float, float]:
    """Half the spread (%) of the relative deviations from a line through the origin fitted between 5 % and 95 % of
    saturation, and the deviation the means' noise alone gives."""
    lin = (y >= LINEARITY_RANGE[0] * y_sat) & (y <= LINEARITY_RANGE[1] * y_sat) & (np.arange(y.size) < i_sat)
    if lin.sum() < 3:
        raise ValueError("fewer than 3 steps between 5 % and 95 % of saturation: raise the steps")
    slope_l, _, _ = weighted_line(mu_p[lin], y[lin], var_mean[lin], through_origin=True)
    line = slope_l * mu_p[lin]
    dev = (y[lin] - line) / line * 100.0
    le = (dev.max() - dev.min()) / 2
    s_le = float(np.max(np.sqrt(var_mean[lin]) / line) * 100.0)  # the deviation the mean's noise alone gives
    return le, s_le


def sensitivity(mu_p: np.ndarray, light: PairStats, dark: PairStats, t_s: np.ndarray) -> dict[str, Figure]:
    """Release 4.0 Linear, 'sensitivity, linearity and noise' (photon transfer method), from a series of
    steps of mu_p photons per pixel at exposure times t_s, with their light and dark frame pairs.

    * saturation: the step where the temporal variance is largest (its photons mu_p.sat; the
      uncertainty is half the series' step there);
    * system gain K: slope of sigma_y^2 - sigma_y.dark^2 against mu_y - mu_y.dark up to 70 % of
      saturation;
    * responsivity R and quantum efficiency eta = R / K: slope of mu_y - mu_y.dark against mu_p
      over the same range (through the origin);
    * temporal dark noise: sigma_y.dark^2 extrapolated to t = 0 along the dark frames (their dark
      current adds shot noise in t), at least 0.24 DN^2; sigma_d = sqrt(sigma_y.dark^2 - sigma_q^2) / K;
    * absolute sensitivity threshold: the photons at SNR = 1,
      mu_p.min = (sqrt(sigma_y.dark^2 / K^2 + 1/4) + 1/2) / eta (Release 4.0's exact root of the SNR
      equation; Release 3.1 approximated it by (sigma_y.dark / K + 1/2) / eta);
    * SNR_max = mu_e.sat / sqrt(sigma_y.dark^2 / K^2 + mu_e.sat); dynamic range mu_p.sat / mu_p.min;
    * linearity error: half the spread of the relative deviations from a line through the origin
      fitted between 5 % and 95 % of saturation, in %.
    """
    mu_p, t_s = np.asarray(mu_p, np.float64), np.asarray(t_s, np.float64)
    n = light.pixels
    y = light.mean - dark.mean
    s2 = light.variance - dark.variance
    i_sat = int(np.argmax(light.variance))
    if i_sat < 4:
        raise ValueError("the series saturates within its first steps: lower the irradiance or raise the steps")
    y_sat = float(y[i_sat])
    mu_p_sat = float(mu_p[i_sat])
    step_p = float(np.diff(mu_p)[max(i_sat - 1, 0)])
    fit = (y >= 0) & (y <= FIT_UP_TO * y_sat) & (np.arange(y.size) < i_sat)
    if fit.sum() < 4:
        raise ValueError("fewer than 4 steps below 70 % of saturation: raise the steps")
    var_s2 = _var_of_variance(light.variance, n) + _var_of_variance(dark.variance, n)
    K, _, covK = weighted_line(y[fit], s2[fit], var_s2[fit])
    sK = float(np.sqrt(covK[1, 1]))
    var_mean = (light.variance + dark.variance) / (2 * n)
    R, _, covR = weighted_line(mu_p[fit], y[fit], var_mean[fit], through_origin=True)
    sR = float(np.sqrt(covR[1, 1]))
    eta, s_eta = R / K, R / K * np.hypot(sR / R, sK / K)

    s2_dark0, s_s2_dark0 = dark_variance_at_zero(t_s, dark)
    sigma_y_dark = float(np.sqrt(s2_dark0))
    s_sigma_y_dark = s_s2_dark0 / (2 * sigma_y_dark)
    sigma_d = float(np.sqrt(max(s2_dark0 - SIGMA_Q2_DN2, 0.0)) / K)
    s_sigma_d = sigma_d * np.hypot(s_s2_dark0 / (2 * max(s2_dark0 - SIGMA_Q2_DN2, 1e-12)), sK / K)

    mu_e_sat = eta * mu_p_sat
    s_mu_e_sat = mu_e_sat * np.hypot(s_eta / eta, 0.5 * step_p / mu_p_sat)
    noise_e2 = s2_dark0 / K**2
    mu_e_min = 0.5 + np.sqrt(noise_e2 + 0.25)
    mu_p_min = mu_e_min / eta
    # d mu_e_min / d (noise_e2) = 1 / (2 sqrt(noise_e2 + 1/4)); noise_e2's relative error: s2 and 2 K
    s_noise_e2 = noise_e2 * np.hypot(s_s2_dark0 / s2_dark0, 2 * sK / K)
    s_mu_e_min = s_noise_e2 / (2 * np.sqrt(noise_e2 + 0.25))
    s_mu_p_min = mu_p_min * np.hypot(s_mu_e_min / mu_e_min, s_eta / eta)
    snr_max = mu_e_sat / np.sqrt(noise_e2 + mu_e_sat)
    s_snr_max = snr_max * 0.5 * s_mu_e_sat / mu_e_sat  # SNR_max ~ sqrt(mu_e.sat)
    dr = mu_p_sat / mu_p_min
    s_dr = dr * np.hypot(0.5 * step_p / mu_p_sat, s_mu_p_min / mu_p_min)

    le, s_le = linearity_error(mu_p, y, var_mean, y_sat, i_sat)

    # the charge where the read clips, from the last step when it lies beyond saturation (every pixel
    # clipped: its mean is black level + K x limit); not a figure of the standard: a preset needs it,
    # as the standard's saturation capacity (the variance maximum) lies below it by the fixed
    # pattern's spread of the pixels' saturation and the series' step
    limit_e = y[-1] / K
    s_limit_e = limit_e * np.hypot(np.sqrt(var_mean[-1]) / max(y[-1], 1e-12), sK / K)

    sec = "Release 4.0 Linear: sensitivity, linearity and noise"
    return {
        "charge_limit_e": Figure(
            limit_e,
            s_limit_e,
            "e-",
            "not in the standard: the mean of the series' last step "
            "(1.25x saturation, every pixel clipped) less the dark mean, over K",
        ),
        "system_gain_dn_per_e": Figure(K, sK, "DN/e-", sec),
        "responsivity_dn_per_photon": Figure(R, sR, "DN/p", sec),
        "quantum_efficiency": Figure(eta, s_eta, "e-/p", sec),
        "temporal_dark_noise_dn": Figure(sigma_y_dark, s_sigma_y_dark, "DN", sec),
        "temporal_dark_noise_e": Figure(sigma_d, s_sigma_d, "e-", sec),
        "saturation_photons": Figure(mu_p_sat, 0.5 * step_p, "p", sec),
        "saturation_capacity_e": Figure(mu_e_sat, s_mu_e_sat, "e-", sec),
        "snr_max": Figure(snr_max, s_snr_max, "1", sec),
        "snr_max_db": Figure(20 * np.log10(snr_max), 20 / np.log(10) * s_snr_max / snr_max, "dB", sec),
        "absolute_sensitivity_threshold_photons": Figure(mu_p_min, s_mu_p_min, "p", sec),
        "absolute_sensitivity_threshold_e": Figure(mu_e_min, s_mu_e_min, "e-", sec),
        "dynamic_range": Figure(dr, s_dr, "1", sec),
        "dynamic_range_db": Figure(20 * np.log10(dr), 20 / np.log(10) * s_dr / dr, "dB", sec),
        "linearity_error_percent": Figure(le, s_le, "%", sec),
    }


def dark_current(t_s: np.ndarray, dark: PairStats, system_gain: Figure) -> dict[str, Figure]:
    """Release 4.0 Linear, 'dark current': the slope of the dark mean against exposure time, in DN/s,
    divided by K: electrons per second (the slope of the dark variance gives it too, over K^2: reported
    as a check, noisier)."""
    t_s = np.asarray(t_s, np.float64)
    n = dark.pixels
    slope, _, cov = weighted_line(t_s, dark.mean, dark.variance / (2 * n))
    K, sK = system_gain.value, system_gain.uncertainty or 0.0
    mu_i = slope / K
    s_mu_i = np.hypot(np.sqrt(cov[1, 1]) / K, mu_i * sK / K)
    vslope, _, vcov = weighted_line(t_s, dark.variance, _var_of_variance(dark.variance, n))
    sec = "Release 4.0 Linear: dark current"
    return {
        "dark_current_e_per_s": Figure(mu_i, float(s_mu_i), "e-/s", sec),
        "dark_current_from_variance_e_per_s": Figure(vslope / K**2, float(np.sqrt(vcov[1, 1]) / K**2), "e-/s", sec),
    }


def _split(image: np.ndarray, temporal_var: float, frames: int) -> tuple[dict[str, float], dict[str, float]]:
    """Spatial variance of an averaged frame, total and its row / column / pixel components (the
    averaged temporal noise, temporal_var / frames, removed from the pixel part), with standard
    errors: a variance over n independent values has relative error sqrt(2 / (n - 1))."""
    H, W = image.shape
    s_r, s_c, s_p = row_column_pixel_variances(image)
    s_p -= temporal_var / frames
    parts = {"row": max(s_r, 0.0), "column": max(s_c, 0.0), "pixel": max(s_p, 0.0)}
    total = sum(parts.values())
    noise_p = s_p + temporal_var / frames
    err = {
        "row": np.sqrt(2 / (H - 1)) * (s_r + noise_p / W),
        "column": np.sqrt(2 / (W - 1)) * (s_c + noise_p / H),
        "pixel": np.sqrt(2 / (H * W - 1)) * noise_p,
    }
    parts["total"] = total
    err["total"] = float(np.sqrt(sum(e**2 for e in err.values())))
    return parts, err


def nonuniformity(
    dark_mean_frame: np.ndarray,
    light_mean_frame: np.ndarray,
    frames: int,
    dark_temporal_var: float,
    light_temporal_var: float,
    system_gain: Figure,
) -> dict[str, Figure]:
    """Release 4.0 Linear, 'spatial nonuniformity': from frames averaged over ``frames`` captures, dark
    and at about 50 % saturation, each (H, W) in DN.

    DSNU = s_y.dark / K in electrons; PRNU = sqrt(s_y.50^2 - s_y.dark^2) / (mu_y.50 - mu_y.dark) in %,
    where s^2 is the spatial variance less the averaged temporal variance; each split into row,
    column and pixel components (:func:`mbcapture.metrics.row_column_pixel_variances`)."""
    dark = np.asarray(dark_mean_frame, np.float64)
    light = np.asarray(light_mean_frame, np.float64)
    K, sK = system_gain.value, system_gain.uncertainty or 0.0
    d_parts, d_err = _split(dark, dark_temporal_var, frames)
    # PRNU from the light frame less the dark one (the offsets cancel; both temporal noises remain)
    p_parts, p_err = _split(light - dark, light_temporal_var + dark_temporal_var, frames)
    signal = float(light.mean() - dark.mean())
    out: dict[str, Figure] = {}
    sec = "Release 4.0 Linear: spatial nonuniformity"
    for comp in ("total", "row", "column", "pixel"):
        name = "" if comp == "total" else f"_{comp}"
        dsnu = np.sqrt(d_parts[comp]) / K
        s_dsnu = np.hypot(d_err[comp] / (2 * max(np.sqrt(d_parts[comp]), 1e-12)) / K, dsnu * sK / K)
        out[f"dsnu{name}_e"] = Figure(dsnu, float(s_dsnu), "e-", sec)
        prnu = np.sqrt(p_parts[comp]) / signal * 100.0
        s_prnu = p_err[comp] / (2 * max(np.sqrt(p_parts[comp]), 1e-12)) / signal * 100.0
        out[f"prnu{name}_percent"] = Figure(prnu, float(s_prnu), "%", sec)
    return out


def spectrogram(image: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Release 4.0 Linear's spectrogram of an averaged frame's spatial variations, (frequencies in
    cycles per pixel, amplitude): the power spectrum along ``axis`` (1: horizontal, along the rows;
    0: vertical), averaged over the other axis, its square root, of the frame less its mean. The
    amplitude is in the frame's unit: white fixed-pattern noise of std s gives a flat s."""
    img = np.asarray(image, np.float64)
    img = img - img.mean()
    n = img.shape[axis]
    power = (np.abs(np.fft.rfft(img, axis=axis)) ** 2).mean(axis=1 - axis) / n
    return np.fft.rfftfreq(n), np.sqrt(power)
