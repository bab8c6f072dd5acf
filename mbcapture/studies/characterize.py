"""``mbcapture characterize``: measure the configured sensor the way EMVA 1288 Release 4.0 (Linear)
measures a real camera, from captures the simulator takes itself, and write its datasheet.

The set-up (the standard's, simulated):

* **light**: the ``flatfield`` scene, rendered by Mitsuba at the configured film's variant. Its
  radiance is chosen per channel so that every channel reaches saturation at the same exposure
  time (the standard measures each colour channel in light of its own wavelength,
  ``sensor.wavelength_nm``). The camera's optics stay as configured (f-number, transmittance), but
  vignetting and diffraction are left out: the standard illuminates the bare sensor uniformly.
  The photons per pixel follow from the rendered radiance: mu_p = E A t lambda / (h c), with the
  sensor-plane irradiance E = pi tau L / (4 N^2) and the pixel area A (fill factor not included:
  the datasheet's quantum efficiency is the pixel's, fill factor times the material's QE).
* **series**: ``steps`` exposure times, equally spaced from dark to 1.25x saturation, two frames
  each (A and B) with light and two without; ``dark_steps`` longer dark exposures for the dark
  current; ``frames`` frames averaged in the dark and at 50 % saturation for DSNU and PRNU.
* **reads**: a multi-bucket pixel is characterized twice where its reads differ: ``bucket``, one
  bucket integrating the whole exposure and read alone; ``sum``, every bucket integrating an equal
  share of it, summed on the floating diffusion (a cumulative read: its saturation is the
  buckets' together or the floating diffusion's, its dark current every bucket's).

Every frame is the sensor stage itself (:func:`mbcapture.sensor.simulate_reads`) on the rendered
flat field, with the configured fixed pattern (``sensor.fpn_seed``: one physical sensor) and its
own temporal noise. The figures are computed by :mod:`mbcapture.sensor.emva`.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field

import numpy as np

from ..sensor import emva
from ..config import CaptureConfig
from ..errors import ConfigError
from ..progress import bar as progress_bar
from ..output.htmlparts import CSS, esc, figure, fmt, table
from ..output.io import staged_outputs
from ..output.plots import datasheet_pngs
from ..render import Renderer
from ..scene.scenes import load_module, make_scene
from ..sensor import simulate_reads
from ..sensor.photons import electrons_per_radiance_second
from ..sensor.presets import DATASHEET_SCHEMA
from ..sensor.spectral import channel_quantum_efficiency, is_spectral_variant

CHANNELS = ("R", "G", "B")
#: The light series reaches saturation at this exposure time (the dark current is negligible there).
SATURATION_TIME_S = 0.01
#: ... and runs on to this multiple of it, so that the variance maximum is inside the series.
SERIES_END = 1.25


@dataclass
class Settings:
    """What a characterization measures: film size, steps of the light and dark-current series,
    frames averaged for the nonuniformities."""

    width: int = 128
    height: int = 128
    steps: int = 50
    dark_steps: int = 10
    frames: int = 16

    def check(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"characterize: --size must be at least 16x16 pixels, got {self.width}x{self.height}")
        if self.steps < 20:
            raise ConfigError(
                f"characterize: --steps must be at least 20 (the fits need points below 70 % of "
                f"saturation), got {self.steps}"
            )
        if self.dark_steps < 3 or self.frames < 2:
            raise ConfigError("characterize: --dark-steps must be at least 3 and --frames at least 2")


@dataclass
class ReadCurves:
    """One read mode's measured series, per channel (arrays (steps, C) unless said)."""

    t_s: np.ndarray
    mu_p: np.ndarray
    light: emva.PairStats
    dark: emva.PairStats
    dark_t_s: np.ndarray
    dark_series: emva.PairStats
    dark_frame: np.ndarray  # (H, W, C), averaged
    light_frame: np.ndarray  # (H, W, C), averaged at 50 % saturation
    figures: dict[str, dict[str, emva.Figure]] = field(default_factory=dict)  # channel -> name -> Figure


def read_modes(bucket_count: int) -> dict[str, tuple[int, ...]]:
    """The reads a datasheet characterizes: one bucket alone, and (with more than one) all summed."""
    modes = {"bucket": (0,)}
    if bucket_count > 1:
        modes["sum"] = tuple(range(bucket_count))
    return modes


def charge_limit_e(cfg: CaptureConfig, buckets: int) -> float:
    """Electrons where a read of ``buckets`` buckets stops being linear: the buckets' full wells, the
    floating diffusion's, or the ADC's top code, whichever comes first."""
    s = cfg.sensor
    adc_e = (s.adc_max_dn - s.black_level_dn) / s.gain_dn_per_e
    return min(buckets * s.full_well_e, s.fd_full_well_e, adc_e)


def monochromatic(cfg: CaptureConfig) -> CaptureConfig:
    """The config a characterization measures: the standard's light is monochromatic, one wavelength
    per channel (``sensor.wavelength_nm``). A sensor with spectral curves (``sensor.spectral_response``
    a camera, a spectral ``render.variant``) is measured at those wavelengths: its curves' quantum
    efficiency there, in the RGB render's one-wavelength-per-channel model, which for monochromatic
    light is exact. A colour filter array (``sensor.cfa``) is taken off: the standard measures the raw
    photosites of each colour, and behind their filter a Bayer sensor's are the three-channel model's
    (a mono sensor is measured per band)."""
    if cfg.sensor.cfa != "none":
        cfg = cfg.model_copy(update={"sensor": cfg.sensor.model_copy(update={"cfa": "none"})})
    if not is_spectral_variant(cfg.render.variant) and cfg.sensor.spectral_response == "effective_wavelength":
        return cfg
    wl, qe = channel_quantum_efficiency(cfg.sensor)
    at = [float(np.interp(w, wl, qe[c], left=0.0, right=0.0)) for c, w in enumerate(cfg.sensor.wavelength_nm)]
    if min(at) <= 0.0:
        raise ConfigError(
            f"characterize: sensor.spectral_response {cfg.sensor.spectral_response!r} has no response at "
            f"sensor.wavelength_nm {cfg.sensor.wavelength_nm} in every channel; set wavelengths inside "
            f"its curves ({wl.min():g}-{wl.max():g} nm)"
        )
    sensor = cfg.sensor.model_copy(update={"spectral_response": "effective_wavelength", "quantum_efficiency": at})
    variant = cfg.render.variant.replace("_spectral", "_rgb")
    return cfg.model_copy(update={"sensor": sensor, "render": cfg.render.model_copy(update={"variant": variant})})


def render_flat_field(cfg: CaptureConfig, settings: Settings) -> tuple[np.ndarray, np.ndarray]:
    """The flat field the sensor sees: (H, W, C) radiance (W m^-2 sr^-1) rendered by Mitsuba, and the
    electrons per second per pixel it gives, (C,), chosen so that one bucket saturates at
    ``SATURATION_TIME_S`` in every channel."""
    variant = cfg.render.variant
    k = electrons_per_radiance_second(cfg.sensor)
    rate = charge_limit_e(cfg, 1) / SATURATION_TIME_S
    radiance = rate / k
    scene = make_scene("flatfield", load_module("flatfield").Params(radiance=[float(x) for x in radiance]))
    renderer = Renderer(scene, settings.width, settings.height, variant=variant, max_depth=1, sensor=cfg.sensor)
    image = renderer.render(0.0, 1, 0, ("field",))[0].astype(np.float64)
    spread = np.ptp(image, axis=(0, 1)) / image.mean(axis=(0, 1))
    if np.any(spread > 1e-5):
        raise RuntimeError(f"the flat field is not flat: relative spread {spread} (a renderer problem)")
    return image, image.mean(axis=(0, 1)) * k


def photons_per_pixel(cfg: CaptureConfig, radiance: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """mu_p: photons on one pixel's area, (steps, C), for per-channel radiance (C,) over t_s (steps,):
    the sensor model's electrons per radiance-second (the camera equation times the photon count,
    :func:`~mbcapture.sensor.electrons_per_radiance_second`) without its fill factor and QE."""
    s = cfg.sensor
    photons = electrons_per_radiance_second(s) / (s.fill_factor * np.asarray(s.quantum_efficiency, np.float64))
    return np.asarray(t_s)[:, None] * (photons * np.asarray(radiance))[None, :]


class _Sensor:
    """Frames of the configured sensor: its fixed pattern, a new temporal noise for every frame."""

    def __init__(self, cfg: CaptureConfig, shape: tuple[int, int], rate_e_per_s: np.ndarray):
        self.cfg, self.shape, self.rate = cfg, shape, np.asarray(rate_e_per_s, np.float64)
        self.seed = cfg.sensor.noise_seed if cfg.sensor.noise_seed is not None else cfg.seed

    def frame(self, buckets: tuple[int, ...], t_s: float, lit: bool, key: tuple[int, ...]) -> np.ndarray:
        """(H, W, C) DN: the read of ``buckets`` after an exposure of t_s split equally over them."""
        n = len(buckets)
        share = self.rate * (t_s / n) if lit else np.zeros(3)
        expected = np.broadcast_to(share, (n, *self.shape, 3)).copy()
        noise = np.random.SeedSequence(self.seed, spawn_key=(0xE3A, *key))
        reads = simulate_reads(expected, [tuple(range(n))], self.cfg.sensor, noise, storage_s=[t_s] * n)
        return reads.reads_dn[0]


def _pairs(sensor: _Sensor, buckets, times, lit: bool, key: tuple[int, ...], bar) -> tuple[np.ndarray, np.ndarray]:
    """Frames A and B at each exposure time, stacked: two (steps, H, W, C) arrays."""
    a, b = [], []
    for i, t in enumerate(times):
        a.append(sensor.frame(buckets, float(t), lit, (*key, i, 0)))
        b.append(sensor.frame(buckets, float(t), lit, (*key, i, 1)))
        bar.update(2)
    return np.stack(a), np.stack(b)


def _per_channel(a: np.ndarray, b: np.ndarray) -> list[emva.PairStats]:
    return [emva.pair_stats(a[..., c], b[..., c]) for c in range(3)]


def _stack(stats: list[emva.PairStats]) -> emva.PairStats:
    return emva.PairStats(
        mean=np.stack([s.mean for s in stats], -1),
        variance=np.stack([s.variance for s in stats], -1),
        pixels=stats[0].pixels,
    )


def measure(cfg: CaptureConfig, settings: Settings | None = None, *, progress: bool = True) -> dict[str, ReadCurves]:
    """Take the series of every read mode and compute its figures (per channel)."""

    settings = settings or Settings()
    settings.check()
    cfg = monochromatic(cfg)
    radiance, rate = render_flat_field(cfg, settings)
    sensor = _Sensor(cfg, (settings.height, settings.width), rate)
    modes = read_modes(cfg.sensor.bucket_count)
    per_mode = 4 * settings.steps + 2 * settings.dark_steps + 2 * settings.frames
    out: dict[str, ReadCurves] = {}
    dc = cfg.sensor.dark_current_e_per_s
    with progress_bar(total=per_mode * len(modes), desc="characterize", unit="frame", enabled=progress) as bar:
        for m, (mode, buckets) in enumerate(modes.items()):
            t_sat = charge_limit_e(cfg, len(buckets)) / rate.max()
            t = np.arange(1, settings.steps + 1) * (SERIES_END * t_sat / settings.steps)
            light = _per_channel(*_pairs(sensor, buckets, t, True, (m, 0), bar))
            dark = _per_channel(*_pairs(sensor, buckets, t, False, (m, 1), bar))
            # dark current: exposures up to the time its signal reaches a tenth of the charge limit
            t_dark_end = 0.1 * charge_limit_e(cfg, len(buckets)) / (dc * len(buckets)) if dc > 0 else 1.0
            t_dark = np.linspace(0.0, t_dark_end, settings.dark_steps)
            dark_series = _per_channel(*_pairs(sensor, buckets, t_dark, False, (m, 2), bar))
            t_half = 0.5 * t_sat
            dark_avg = np.mean(
                [sensor.frame(buckets, t_half, False, (m, 3, f)) for f in range(settings.frames)], axis=0
            )
            bar.update(settings.frames)
            light_avg = np.mean(
                [sensor.frame(buckets, t_half, True, (m, 4, f)) for f in range(settings.frames)], axis=0
            )
            bar.update(settings.frames)
            curves = ReadCurves(
                t_s=t,
                mu_p=photons_per_pixel(cfg, radiance.mean(axis=(0, 1)), t),
                light=_stack(light),
                dark=_stack(dark),
                dark_t_s=t_dark,
                dark_series=_stack(dark_series),
                dark_frame=dark_avg,
                light_frame=light_avg,
            )
            i_half = int(np.argmin(np.abs(t - t_half)))
            for c, name in enumerate(CHANNELS):
                figs = emva.sensitivity(curves.mu_p[:, c], light[c], dark[c], t)
                figs.update(emva.dark_current(t_dark, dark_series[c], figs["system_gain_dn_per_e"]))
                figs.update(
                    emva.nonuniformity(
                        dark_avg[..., c],
                        light_avg[..., c],
                        settings.frames,
                        float(dark[c].variance[i_half]),
                        float(light[c].variance[i_half]),
                        figs["system_gain_dn_per_e"],
                    )
                )
                curves.figures[name] = figs
            out[mode] = curves
    return out


def configured_figures(cfg: CaptureConfig, buckets: int) -> dict[str, list[float]]:
    """What the config says each figure should be, per channel: the reader's comparison (and the
    tests'). The standard's saturation capacity (the variance maximum) has no configured value: it
    sits below the charge limit by the spread of the pixels' saturation (PRNU) and the series' step."""
    s = monochromatic(cfg).sensor
    qe = [s.fill_factor * q for q in s.quantum_efficiency]
    line = lambda p, r, c: math.sqrt(p**2 + r**2 + c**2)  # noqa: E731
    return {
        "system_gain_dn_per_e": [s.gain_dn_per_e] * 3,
        "quantum_efficiency": qe,
        "temporal_dark_noise_e": [math.hypot(s.read_noise_e, s.read_noise_row_e)] * 3,
        "charge_limit_e": [charge_limit_e(cfg, buckets)] * 3,
        "dark_current_e_per_s": [s.dark_current_e_per_s * buckets] * 3,
        "dsnu_e": [line(s.dsnu_e, s.dsnu_row_e, s.dsnu_col_e)] * 3,
        "dsnu_row_e": [s.dsnu_row_e] * 3,
        "dsnu_column_e": [s.dsnu_col_e] * 3,
        "dsnu_pixel_e": [s.dsnu_e] * 3,
        "prnu_percent": [100 * line(s.prnu, s.prnu_row, s.prnu_col)] * 3,
        "prnu_row_percent": [100 * s.prnu_row] * 3,
        "prnu_column_percent": [100 * s.prnu_col] * 3,
        "prnu_pixel_percent": [100 * s.prnu] * 3,
        "linearity_error_percent": [0.0] * 3,
    }


def datasheet(cfg: CaptureConfig, curves: dict[str, ReadCurves], settings: Settings, source: str) -> dict:
    """characterization.json: the set-up, and per read mode and channel every figure with its
    uncertainty, unit and section, beside what the config says; in the schema a sensor preset loads
    (``sensor.preset: path/to/characterization.json``)."""
    s = cfg.sensor
    modes = read_modes(s.bucket_count)
    return {
        "schema": DATASHEET_SCHEMA,
        "standard": "EMVA 1288 Release 4.0 Linear (figures computed by mbcapture.sensor.emva)",
        "config": source,
        "sensor": {
            "pixel_pitch_um": s.pixel_pitch_um,
            "bucket_count": s.bucket_count,
            "adc_bits": s.adc_bits,
            "spectral_response": s.spectral_response,
            "wavelength_nm": list(s.wavelength_nm),
            "black_level_dn": s.black_level_dn,
            "f_number": s.f_number,
            "lens_transmittance": s.lens_transmittance,
        },
        "setup": {
            "film": [settings.width, settings.height],
            "steps": settings.steps,
            "dark_steps": settings.dark_steps,
            "frames_averaged": settings.frames,
            "saturation_time_s": SATURATION_TIME_S,
            "light": "flatfield scene, one radiance per channel at sensor.wavelength_nm, no vignetting or "
            "diffraction; photons counted on the pixel area (fill factor in the quantum efficiency)",
        },
        "reads": {
            mode: {
                "buckets": list(modes[mode]),
                "channels": {ch: {k: f.as_dict() for k, f in rc.figures[ch].items()} for ch in CHANNELS},
                "configured": configured_figures(cfg, len(modes[mode])),
                "curves": {
                    "t_s": rc.t_s.tolist(),
                    "mu_p": rc.mu_p.tolist(),
                    "mu_y": rc.light.mean.tolist(),
                    "var_y": rc.light.variance.tolist(),
                    "mu_y_dark": rc.dark.mean.tolist(),
                    "var_y_dark": rc.dark.variance.tolist(),
                    "dark_t_s": rc.dark_t_s.tolist(),
                    "dark_series_mu_y": rc.dark_series.mean.tolist(),
                },
            }
            for mode, rc in curves.items()
        },
    }


#: The figures of the datasheet's summary table, in the standard's order, with their labels.
SUMMARY = (
    ("quantum_efficiency", "quantum efficiency η"),
    ("system_gain_dn_per_e", "system gain K"),
    ("temporal_dark_noise_e", "temporal dark noise σ_d"),
    ("temporal_dark_noise_dn", "temporal dark noise σ_y.dark"),
    ("saturation_capacity_e", "saturation capacity μ_e.sat"),
    ("charge_limit_e", "charge limit (not in the standard)"),
    ("absolute_sensitivity_threshold_photons", "absolute sensitivity threshold μ_p.min"),
    ("absolute_sensitivity_threshold_e", "absolute sensitivity threshold μ_e.min"),
    ("snr_max_db", "SNR_max"),
    ("dynamic_range_db", "dynamic range"),
    ("linearity_error_percent", "linearity error LE"),
    ("dark_current_e_per_s", "dark current μ_I"),
    ("dsnu_e", "DSNU"),
    ("dsnu_row_e", "DSNU, row"),
    ("dsnu_column_e", "DSNU, column"),
    ("dsnu_pixel_e", "DSNU, pixel"),
    ("prnu_percent", "PRNU"),
    ("prnu_row_percent", "PRNU, row"),
    ("prnu_column_percent", "PRNU, column"),
    ("prnu_pixel_percent", "PRNU, pixel"),
)


def _value(f: dict) -> str:
    u = f["uncertainty"]
    return f"{f['value']:.4g} ± {u:.2g}" if u is not None else f"{f['value']:.4g}"


def report_html(sheet: dict, plots: dict[str, str]) -> str:
    """report.html: the summary table per read mode (measured ± uncertainty beside configured), and
    the photon transfer, SNR, linearity and spectrogram plots."""
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>EMVA 1288 datasheet: {esc(sheet['config'])}"
        f"</title><style>{CSS}</style></head><body>",
        f"<h1>EMVA 1288 datasheet of the simulated sensor</h1><p class='lead'>{esc(sheet['config'])}: "
        f"{esc(sheet['standard'])}. Light: {esc(sheet['setup']['light'])}. Film "
        f"{sheet['setup']['film'][0]}x{sheet['setup']['film'][1]}, {sheet['setup']['steps']} exposure steps of two "
        f"frames, {sheet['setup']['frames_averaged']} frames averaged for DSNU and PRNU. Uncertainties are 1σ, "
        "from the number of pixels and frames.</p>",
    ]
    sensor = sheet["sensor"]
    parts.append(table([[k, v] for k, v in sensor.items()], ["sensor", "value"]))
    for mode, data in sheet["reads"].items():
        parts.append(f"<h2>Read: {esc(mode)} (buckets {esc(data['buckets'])})</h2>")
        rows = []
        for key, label in SUMMARY:
            first = data["channels"]["R"][key]
            row = [label, first["unit"]]
            for ch in CHANNELS:
                f = data["channels"][ch][key]
                conf = data["configured"].get(key)
                row.append(_value(f) + (f" ({fmt(conf[CHANNELS.index(ch)])})" if conf is not None else ""))
            rows.append(row)
        parts.append(table(rows, ["figure", "unit", "R (configured)", "G (configured)", "B (configured)"]))
        parts.append(
            "<div class='grid'>"
            + "".join(figure(src, esc(cap), plot=True) for src, cap in plots.items() if src.startswith(f"{mode}_"))
            + "</div>"
        )
    parts.append(
        "<p class='muted'>Every figure with its uncertainty, unit and section of the standard, and the "
        "measured curves: <a href='characterization.json'>characterization.json</a> (loads as a sensor "
        "preset: <code>sensor.preset: path/to/characterization.json</code>).</p></body></html>"
    )
    return "".join(parts)


def characterize(
    cfg: CaptureConfig,
    out_dir,
    *,
    source: str,
    settings: Settings | None = None,
    progress: bool = True,
    summary: bool = True,
) -> dict:
    """Measure the sensor of ``cfg`` and write characterization.json, report.html and its plots into
    ``out_dir`` (atomically). Returns the datasheet. ``progress``: a bar over the frames; ``summary``: one
    line of the main figures at the end (stderr)."""
    settings = settings or Settings()
    curves = measure(cfg, settings, progress=progress)
    sheet = datasheet(cfg, curves, settings, source)
    with staged_outputs(out_dir) as st:
        captions = {}
        for mode, rc in curves.items():
            for name, (png, caption) in datasheet_pngs(rc, mode).items():
                st.write_bytes(f"{mode}_{name}.png", png)
                captions[f"{mode}_{name}.png"] = caption
        st.write_json("characterization.json", sheet)
        st.write_bytes("report.html", report_html(sheet, captions).encode())
    if summary:
        g = sheet["reads"]["bucket"]["channels"]["G"]
        print(
            f"mbcapture: characterized ({sheet['config']}), green channel: K {_value(g['system_gain_dn_per_e'])} "
            f"DN/e-, QE {_value(g['quantum_efficiency'])}, dark noise {_value(g['temporal_dark_noise_e'])} e-, "
            f"saturation {_value(g['saturation_capacity_e'])} e-; {out_dir}/report.html",
            file=sys.stderr,
        )
    return sheet
