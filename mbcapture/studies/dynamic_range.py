"""``mbcapture snr``: the signal-to-noise ratio of a configured HDR capture against scene luminance, for
each read and for the merged HDR, and the dynamic range of the whole capture.

What a sensor engineer reads off a datasheet curve (ISETCam's SNR-against-luminance plot, EMVA 1288's
SNR curve), here for a multi-bucket design: the reads' exposures, which buckets each sums, how long
each bucket stores charge, the merge, all from the config (:func:`design_of`).

**The analytic curve** (:func:`analytic`), for a flat grey scene of radiance L (W m^-2 sr^-1 in every
channel; luminance 683 L cd/m^2, the Rec. 709 luma weights summing to 1), on the green channel's
photo-electron rate lambda = k L (``k`` from the sensor's optics and quantum efficiency):

* bucket b collects lambda e_b (its gated time e_b) plus dark charge d s_b (dark current d over its
  storage time s_b); read i sums its buckets, so reads i and j share the charge of the buckets in
  both: Cov(x_i, x_j) = sum over b in i and j of (lambda e_b + d s_b), plus the read variance
  r^2 = read noise^2 + row noise^2 + 1/(12 g^2) (quantization) on the diagonal;
* a read's SNR is lambda t_i / sqrt(Var x_i) (t_i its exposure) up to where it saturates: a bucket's
  expected charge reaches its full well, the sum the floating diffusion's, or the code the ADC's top;
* the merge is linear in the reads it uses, rate = sum_i c_i x_i with sum_i c_i t_i = 1: ``c`` the
  merge's own weights at the true rate (``ramp_fit``: generalized least squares with its covariance
  model; ``inverse_variance``; ``debevec``'s hat weights of the expected codes), at the rate the merge
  sees (the dark charge's mean included), so its variance is c^T Cov c and its SNR
  lambda / sqrt(c^T Cov c). For ``debevec`` this holds once the expected codes are well above the
  black level: below, each noisy code's hat weight differs and the merge is noisier than the formula
  (the simulated points show how much). The reads it uses are the unsaturated ones (for
  cumulative reads, those before the first saturated one), so the curve dips where the merge drops a
  read: the *switch points*.

The SNR is temporal (EMVA 1288's definition): the fixed pattern (PRNU, DSNU) is a spread between
pixels, not a noise of one pixel's value. Parasitic light and transfer loss are not in the formula.

**Dynamic range** of the merged capture: from the radiance where its SNR reaches 1 up to where its
last usable read saturates (the shortest read, for cumulative reads), in dB (20 log10 of the ratio);
beside it, the longest read's own.

**The check** (:func:`simulated`): a flat-field ramp through the sensor stage itself
(:func:`mbcapture.sensor.simulate_reads`, the configured sensor with its fixed pattern off and no
mosaic) and the merge (:func:`mbcapture.reconstruct.hdr.merge_hdr`), SNR = lambda / std over
``pixels`` pixels per level, with its standard error SNR / sqrt(2 (n - 1)) (a normal sample's
standard deviation). The signal is the true rate, not the merged mean: the merge does not subtract
the dark charge's mean, a bias (d s / t) that is not noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .. import application as apps
from ..config import CaptureConfig
from ..errors import ConfigError
from ..output.io import staged_outputs
from ..output.plots import snr_png
from ..reconstruct.hdr import merge_hdr, quantization_read_variance_e2, resolve_method
from ..sensor import SensorConfig, electrons_per_radiance_second, simulate_reads
from ..timing import protocols

#: The channel whose curve is drawn (green: the luminance's largest weight).
GREEN = 1
#: cd/m^2 per W m^-2 sr^-1 of a grey scene in linear sRGB (the Rec. 709 luma weights sum to 1).
LUMINOUS_EFFICACY_LM_PER_W = 683.0
#: Hat weights below this (relative to the peak) are raised to it, as in the ``debevec`` merge.
_HAT_FLOOR = 1e-6


@dataclass(frozen=True)
class Design:
    """A capture's reads as the SNR sees them. Times in seconds; K buckets (or a sequential capture's
    frames), R reads."""

    label: str
    read_names: tuple[str, ...]
    bucket_s: np.ndarray  # (K,) gated time of each bucket
    reads: tuple[tuple[int, ...], ...]  # the buckets each read sums
    read_s: np.ndarray  # (R,) each read's exposure
    storage_s: np.ndarray  # (K,) how long each bucket holds charge before it is read
    cumulative: bool
    sequential: bool
    method: str
    sensor: SensorConfig
    k_e: float  # green photo-electrons per (W m^-2 sr^-1 s)
    capture_span_s: float  # from the first gate opening to the last read's end (moving things move over it)


def design_of(cfg: CaptureConfig, label: str = "") -> Design:
    """The design a config captures: its timeline's reads, their buckets, exposures and storage
    times, and the HDR merge it would use. A ConfigError for a protocol whose reads are not merged
    into HDR, or for per-pixel gate codes."""
    if apps.protocol_app(cfg.capture.protocol) != "hdr":
        raise ConfigError(
            f"capture.protocol {cfg.capture.protocol!r}: mbcapture snr is for captures merged into HDR "
            "(photon_efficient_hdr, interleaved_hdr, custom; capture.sequential for the conventional twin)"
        )
    if cfg.capture.gate_code is not None:
        raise ConfigError("capture.gate_code: mbcapture snr is for global gates (every pixel's reads alike)")
    tl = protocols.build(cfg)
    cumulative = not tl.sequential and any(len(r.buckets) > 1 for r in tl.reads)
    return Design(
        label=label or cfg.capture.protocol,
        read_names=tuple(r.name for r in tl.reads),
        bucket_s=np.array([float(tl.seconds(tl.exposure_ticks(b))) for b in range(tl.n_buckets)]),
        reads=tuple(tuple(r.buckets) for r in tl.reads),
        read_s=np.array([float(tl.seconds(tl.read_exposure_ticks(r))) for r in tl.reads]),
        storage_s=np.asarray(tl.storage_s(), dtype=np.float64),
        cumulative=cumulative,
        sequential=tl.sequential,
        method=resolve_method(cfg.hdr.method, cumulative),
        sensor=cfg.sensor,
        k_e=float(electrons_per_radiance_second(cfg.sensor)[GREEN]),
        capture_span_s=float(tl.seconds(tl.end_tick - tl.start_tick)),
    )


def _read_variance_e2(sensor: SensorConfig) -> float:
    """Per-read variance that is not shot noise: read noise (pixel and row) and quantization, e-^2."""
    return quantization_read_variance_e2(sensor) + sensor.read_noise_row_e**2


def saturation_radiance(design: Design) -> np.ndarray:
    """(R,) the radiance at which each read's expected charge reaches a limit: one of its buckets' full
    wells, the floating diffusion's, or the ADC's top code."""
    s = design.sensor
    k = design.k_e
    dark = s.dark_current_e_per_s * design.storage_s
    code_limit_e = (s.adc_max_dn - s.black_level_dn) / s.gain_dn_per_e
    out = []
    for buckets, t in zip(design.reads, design.read_s):
        dark_i = float(dark[list(buckets)].sum())
        limits = [(s.full_well_e - dark[b]) / (k * design.bucket_s[b]) for b in buckets if design.bucket_s[b] > 0]
        limits += [(min(s.fd_full_well_e, code_limit_e) - dark_i) / (k * t)]
        out.append(max(min(limits), 0.0))
    return np.array(out)


def usable_reads(design: Design, radiance: np.ndarray) -> np.ndarray:
    """(R, L) which reads the merge uses at each radiance (cumulative: those before the first saturated)."""
    usable = np.asarray(radiance)[None, :] < saturation_radiance(design)[:, None]
    if design.cumulative:
        usable = np.logical_and.accumulate(usable, axis=0)
    return usable


def _covariance(design: Design, lam: float, reads: np.ndarray) -> np.ndarray:
    """Cov of the reads ``reads`` at rate ``lam``: shared buckets' charge plus the read variance."""
    charge = lam * design.bucket_s + design.sensor.dark_current_e_per_s * design.storage_s
    n = reads.size
    cov = np.empty((n, n))
    for a, i in enumerate(reads):
        for b, j in enumerate(reads):
            shared = set(design.reads[i]) & set(design.reads[j])
            cov[a, b] = sum(charge[q] for q in shared)
    return cov + _read_variance_e2(design.sensor) * np.eye(n)


def merge_weights(design: Design, lam: float, reads: np.ndarray) -> np.ndarray:
    """The merge's weights c (rate = c . x, c . t = 1) for the reads ``reads`` at the true rate ``lam``:
    what :mod:`mbcapture.reconstruct.hdr`'s method computes from its first-pass estimate."""
    t = design.read_s[reads]
    s = design.sensor
    r2 = quantization_read_variance_e2(s)  # the merge's own noise model
    if design.method == "ramp_fit":
        shared = np.array([[sum(design.bucket_s[q] for q in set(design.reads[i]) & set(design.reads[j])) for j in reads]
                           for i in reads])  # fmt: skip
        solved = np.linalg.solve(max(lam, 0.0) * shared + r2 * np.eye(t.size), t)
        return solved / (t @ solved)
    if design.method == "inverse_variance":
        w = t**2 / (max(lam, 0.0) * t + r2)
    else:  # debevec: the hat weight of each read's expected code
        z = s.black_level_dn + s.gain_dn_per_e * lam * t
        z_min, z_max = s.black_level_dn, float(s.adc_max_dn)
        w = np.maximum(np.minimum(z - z_min, z_max - z) / (0.5 * (z_max - z_min)), _HAT_FLOOR)
    return (w / t) / w.sum()


@dataclass(frozen=True)
class Curves:
    """A design's analytic SNR at each radiance (L,): ``per_read`` (R, L), NaN where that read is
    saturated; ``merged`` (L,), NaN where no read is usable."""

    radiance: np.ndarray
    per_read: np.ndarray
    merged: np.ndarray

    @property
    def luminance_cd_m2(self) -> np.ndarray:
        return LUMINOUS_EFFICACY_LM_PER_W * self.radiance


def analytic(design: Design, radiance: np.ndarray) -> Curves:
    """The SNR of every read and of the merge at each radiance (see the module docstring)."""
    radiance = np.asarray(radiance, dtype=np.float64)
    sat = saturation_radiance(design)
    usable = usable_reads(design, radiance)
    dark = design.sensor.dark_current_e_per_s * design.storage_s
    r2 = _read_variance_e2(design.sensor)
    lam = design.k_e * radiance
    per_read = np.full((len(design.reads), radiance.size), np.nan)
    for i, (buckets, t) in enumerate(zip(design.reads, design.read_s)):
        ok = radiance < sat[i]
        dark_i = float(dark[list(buckets)].sum())
        per_read[i, ok] = lam[ok] * t / np.sqrt(lam[ok] * t + dark_i + r2)
    read_dark = np.array([dark[list(b)].sum() for b in design.reads])
    merged = np.full(radiance.size, np.nan)
    for j, rate in enumerate(lam):
        reads = np.flatnonzero(usable[:, j])
        if reads.size:
            # the merge weighs by the rate it sees, the dark charge's mean included (its first pass)
            seen = rate + read_dark[reads].sum() / design.read_s[reads].sum()
            c = merge_weights(design, seen, reads)
            merged[j] = rate / math.sqrt(float(c @ _covariance(design, rate, reads) @ c))
    return Curves(radiance, per_read, merged)


def _crossing(radiance: np.ndarray, snr: np.ndarray, level: float = 1.0) -> float:
    """The lowest radiance where ``snr`` reaches ``level`` (interpolated in log radiance); NaN if never."""
    above = np.flatnonzero(np.nan_to_num(snr, nan=-1.0) >= level)
    if above.size == 0:
        return math.nan
    j = int(above[0])
    if j == 0:
        return float(radiance[0])
    x0, x1 = math.log(radiance[j - 1]), math.log(radiance[j])
    y0, y1 = snr[j - 1], snr[j]
    return float(math.exp(x0 + (level - y0) * (x1 - x0) / (y1 - y0)))


def radiance_grid(designs: list[Design], levels: int = 400) -> np.ndarray:
    """Log-spaced radiances from a twentieth of an electron in the longest read to twice the highest
    saturation radiance of any read (every curve's whole range)."""
    lo = min(0.05 / (d.k_e * d.read_s.max()) for d in designs)
    hi = 2.0 * max(saturation_radiance(d).max() for d in designs)
    return np.geomspace(lo, hi, levels)


def summary(design: Design, curves: Curves) -> dict:
    """Dynamic range and switch points (radiances in W m^-2 sr^-1, luminances in cd/m^2)."""
    sat = saturation_radiance(design)
    top = float(sat[0] if design.cumulative else sat.max())
    low = _crossing(curves.radiance, curves.merged)
    longest = int(np.argmax(design.read_s))
    low_longest = _crossing(curves.radiance, curves.per_read[longest])
    dr = top / low if low > 0 else math.nan
    dr_longest = float(sat[longest]) / low_longest if low_longest > 0 else math.nan
    return {
        "label": design.label,
        "reads": [
            {"read": n, "buckets": [b + 1 for b in r], "exposure_s": float(t), "saturates_at_radiance": float(s)}
            for n, r, t, s in zip(design.read_names, design.reads, design.read_s, sat)
        ],
        "merge": design.method,
        "capture_span_s": design.capture_span_s,
        "snr_1_radiance": low,
        "saturation_radiance": top,
        "dynamic_range": dr,
        "dynamic_range_db": 20 * math.log10(dr) if dr > 0 else math.nan,
        "longest_read_dynamic_range_db": 20 * math.log10(dr_longest) if dr_longest > 0 else math.nan,
        "peak_snr_db": float(20 * np.log10(np.nanmax(curves.merged))),
        # reads that saturate with the last one (within 0.1 %: the same full well, another dark charge) are no switch
        "switch_radiances": sorted({float(s) for s in sat if s < 0.999 * top}),
    }


@dataclass(frozen=True)
class Simulated:
    """SNR measured on a flat-field ramp: ``snr`` and its standard error ``se`` at each radiance (L,)."""

    radiance: np.ndarray
    snr: np.ndarray
    se: np.ndarray


def temporal_sensor(sensor: SensorConfig) -> SensorConfig:
    """The sensor with its fixed pattern off and one plain photosite per pixel (no mosaic)."""
    off = {k: 0.0 for k in ("prnu", "prnu_row", "prnu_col", "dsnu_e", "dsnu_row_e", "dsnu_col_e")}
    return sensor.model_copy(update={**off, "cfa": "none"})


def simulated(design: Design, radiance: np.ndarray, pixels: int, seed: int) -> Simulated:
    """The flat-field check: ``pixels`` pixels per radiance through the sensor stage and the merge.
    NaN where any pixel's merge had no usable read."""
    radiance = np.asarray(radiance, dtype=np.float64)
    sensor = temporal_sensor(design.sensor)
    lam = design.k_e * radiance
    # rows are pixels, columns radiances: the row noise, one draw per row, stays a noise of each level
    expected = lam[None, None, :, None] * design.bucket_s[:, None, None, None]
    expected = np.broadcast_to(expected, (design.bucket_s.size, pixels, radiance.size, 1)).copy()
    out = simulate_reads(
        expected,
        design.reads,
        sensor,
        np.random.SeedSequence(seed),
        storage_s=design.storage_s,
        shared_photodiode=not design.sequential,
    )
    res = merge_hdr(
        out.reads_dn[..., 0],
        design.read_s,
        sensor,
        method=design.method,
        cumulative=design.cumulative,
        saturated=out.saturated[..., 0],
    )
    std = res.rate_e_per_s.std(axis=0, ddof=1)  # (L,) over the pixels
    snr = np.where(res.valid.all(axis=0), lam / std, np.nan)
    return Simulated(radiance, snr, snr / np.sqrt(2.0 * (pixels - 1)))


def check_levels(design: Design, levels: int) -> np.ndarray:
    """Radiances for the simulated check: log-spaced over the merged range, none within 10 % of a switch
    point (where some pixels of a level saturate and others not, a mixture no single curve describes)."""
    sat = saturation_radiance(design)
    top = float(sat[0] if design.cumulative else sat.max())
    lo = 0.5 / (design.k_e * design.read_s.max())
    grid = np.geomspace(lo, 0.85 * top, 4 * levels)
    far = np.all(np.abs(grid[:, None] / sat[None, :] - 1.0) > 0.1, axis=1)
    grid = grid[far]
    return grid[np.linspace(0, grid.size - 1, min(levels, grid.size)).round().astype(int)]


def study(designs: list[Design], out_dir: Path | None, *, pixels: int = 4000, levels: int = 16, seed: int = 0) -> dict:
    """Every design's analytic curves, summary and simulated check; with ``out_dir``, written there
    (atomically): snr.json (the summaries and the check), snr.parquet (every curve, one row per design,
    curve and radiance), snr.png (the figure). ``pixels`` = 0: no simulated check."""
    grid = radiance_grid(designs)
    doc, rows, drawn = {"designs": []}, [], []
    for i, d in enumerate(designs):
        curves = analytic(d, grid)
        entry = summary(d, curves)
        points = None
        if pixels > 0:
            lv = check_levels(d, levels)
            sim = simulated(d, lv, pixels, seed + i)
            want = analytic(d, lv).merged
            z = (sim.snr - want) / sim.se
            entry["check"] = {
                "pixels": pixels,
                "radiance": lv.tolist(),
                "snr_simulated": sim.snr.tolist(),
                "snr_se": sim.se.tolist(),
                "snr_analytic": want.tolist(),
                "within_95": int(np.sum(np.abs(z) <= 1.96)),
                "levels": int(lv.size),
            }
            points = (LUMINOUS_EFFICACY_LM_PER_W * lv, sim.snr, 1.96 * sim.se)
            rows += [(d.label, "simulated", r, s, e) for r, s, e in zip(lv, sim.snr, sim.se)]
        doc["designs"].append(entry)
        rows += [(d.label, "merged", r, s, math.nan) for r, s in zip(grid, curves.merged)]
        for name, snr in zip(d.read_names, curves.per_read):
            rows += [(d.label, name, r, s, math.nan) for r, s in zip(grid, snr)]
        drawn.append(
            {
                "label": d.label,
                "luminance": curves.luminance_cd_m2,
                "merged": curves.merged,
                "per_read": dict(zip(d.read_names, curves.per_read)),
                "switch_luminances": [LUMINOUS_EFFICACY_LM_PER_W * x for x in entry["switch_radiances"]],
                "points": points,
            }
        )
    if out_dir is not None:
        table = pd.DataFrame(rows, columns=["design", "curve", "radiance_w_m2_sr", "snr", "snr_se"])
        table.insert(3, "luminance_cd_m2", LUMINOUS_EFFICACY_LM_PER_W * table["radiance_w_m2_sr"])
        with staged_outputs(Path(out_dir)) as st:
            st.write_json("snr.json", doc)
            table.to_parquet(st.path("snr.parquet"), index=False)
            st.write_bytes("snr.png", snr_png(drawn))
    return doc


def summary_lines(doc: dict) -> list[str]:
    """What ``mbcapture snr`` prints: per design its dynamic range, peak SNR, switch points and check."""
    lines = []
    for e in doc["designs"]:
        reads = ", ".join(f"{r['read']} {1e3 * r['exposure_s']:.3g} ms" for r in e["reads"])
        lines.append(
            f"{e['label']}: reads {reads} ({e['merge']}) over {1e3 * e['capture_span_s']:.3g} ms; dynamic range {e['dynamic_range_db']:.1f} dB "
            f"(longest read alone {e['longest_read_dynamic_range_db']:.1f} dB), peak SNR {e['peak_snr_db']:.1f} dB, "
            f"SNR 1 at {LUMINOUS_EFFICACY_LM_PER_W * e['snr_1_radiance']:.3g} cd/m2, saturation at "
            f"{LUMINOUS_EFFICACY_LM_PER_W * e['saturation_radiance']:.3g} cd/m2"
        )
        if "check" in e:
            c = e["check"]
            lines.append(
                f"  simulated flat field ({c['pixels']} pixels a level): {c['within_95']} of {c['levels']} levels "
                "within the 95 % interval of the analytic curve"
            )
    return lines
