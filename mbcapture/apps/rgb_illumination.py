"""RGB illumination: a colour image from a monochrome multi-bucket sensor and R, G, B LEDs.

Protocol ``rgb_illumination`` (needs 4 buckets): every period, bucket 1 collects while the red LED
(group ``led_r``) is on, bucket 2 with ``led_g``, bucket 3 with ``led_b``, bucket 4 with no LED
(ambient only); each slot is ``capture.unit_exposure_s / capture.periods`` long, so every bucket
integrates T = ``capture.unit_exposure_s``. Reads: ``R``, ``G``, ``B``, ``ambient``, one bucket each.
The colours come from the LEDs, so the sensor has no colour filters: ``sensor.spectral_response:
"monochrome:<camera>"`` in a spectral variant (:mod:`mbcapture.sensor.spectral`); a camera or the
RGB mode is read as panchromatic by summing its three channels.
``capture.sequential: true`` takes the four frames one after another: a shaken chart is then at
a different place in R, G and B (colour fringes at its edges); interleaved, every bucket sees the
same motion blur and the colours stay registered.

Reconstruction (``app.method``): LED signals s_k = rate_k - rate_ambient (e-/s), then a 3x3
matrix to CIE XYZ:

``chart_fit``  least squares on the chart's patch interiors against the patches' true XYZ
``analytic``   from the spectra: XYZ = X R^-1 s with X[:, k] = integral cmf E_k, R[c, k] = integral
               S_c E_k (a surface's reflectance taken constant over each LED's band), one scale
               fixed by the white patch

True colours: colour-science's reflectances (``ColorChecker N Ohta``) under the stated illuminant
"the three LEDs together" (the sum of the scene's LED spectra), CIE 1931 2-degree XYZ with a perfect
white at Y = 1, CIE Lab with that illuminant's white point.
Reference: the chart at rest (``scene.extra['rest_time_s']``) under the three LEDs, no ambient,
rendered noise-free (``app.reference_spp``) onto a film whose channels are the CIE colour-matching
functions (spectral variants; RGB variants: linear sRGB to XYZ), scaled so that the white patch has
its true Y.

Bayer comparison (``app.bayer``, computed inside the app from the capture's scene): one ordinary
frame of a colour camera (``app.bayer_camera``'s R, G, B curves, peak QE ``sensor.quantum_efficiency``,
colour filter array ``app.bayer_pattern``, same pixel, optics and noise model) exposed over the interleaved capture's
span [start, start + 4T] with the three LEDs on together (each delivering the same energy as in its
bucket: drive T / 4T) and the ambient on throughout, no ambient frame to subtract. The frame goes
through the sensor stage with ``sensor.cfa`` set to the pattern (mbcapture.sensor.cfa: one channel per
photosite, demosaiced with ``app.demosaic``), the same path as any capture on a Bayer sensor, and
is colour-corrected with the same ``app.method``.

Metrics: CIEDE2000 (colour.delta_E, method 'CIE 2000') against the reference, mean and max over the
whole image and over the patch interiors; the patches' mean colours against their true Lab.
"""

from __future__ import annotations

from typing import Callable, Literal

import numpy as np
from pydantic import Field

from ..strict import StrictModel
from ..scene.camera_motion import still
from ..errors import ConfigError
from ..render import Renderer
from ..sensor import dn_to_electrons, electrons_per_render_second
from ..exposure.simulate import sense_frame
from ..sensor.spectral import channel_quantum_efficiency, film_sensitivity, is_monochrome
from ..timing.timeline import ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol

LED_GROUPS = ("led_r", "led_g", "led_b")
READ_NAMES = ("R", "G", "B", "ambient")
CMFS_NAME = "CIE 1931 2 Degree Standard Observer"
#: ΔE maps in the PNG previews: this ΔE is white.
DELTA_E_PNG_WHITE = 20.0
#: What each preview shows (report.html).
CAPTIONS = {
    "colour": "the colour image from the three LED buckets (ambient subtracted, app.method matrix to XYZ), sRGB",
    "reference": "reference: the chart at rest under the three LEDs, noise-free",
    "delta_e2000": "CIEDE2000 against the reference, linear: white = %g" % DELTA_E_PNG_WHITE,
    "bayer": "an ordinary Bayer colour camera over the same span, for comparison",
    "delta_e2000_bayer": "the Bayer image's CIEDE2000 against the reference, linear: white = %g" % DELTA_E_PNG_WHITE,
}


@register_protocol("rgb_illumination", app="rgb_illumination")
def rgb_illumination_protocol(cfg):
    """One period: bucket 1 red LED, bucket 2 green, bucket 3 blue, bucket 4 ambient, each T/N."""
    if cfg.sensor.bucket_count < 4:
        raise ConfigError(
            f"capture.protocol: 'rgb_illumination' needs 4 buckets but sensor.bucket_count is {cfg.sensor.bucket_count}"
        )
    T, N = exact(cfg.capture.unit_exposure_s), cfg.capture.periods
    slots = [SlotSeconds(b, T / N, frozenset({g})) for b, g in enumerate(LED_GROUPS)]
    slots.append(SlotSeconds(3, T / N, frozenset()))
    reads = [ReadEvent(name, (b,)) for b, name in enumerate(READ_NAMES)]
    return slots, reads, 4


class Params(StrictModel):
    method: Literal["chart_fit", "analytic"] = Field(
        "chart_fit",
        description="Colour correction from LED signals to XYZ: 'chart_fit' (3x3 least squares on the "
        "chart patches against their true colours) or 'analytic' (from the LED and sensor spectra, white patch scale).",
    )
    patch_interior_fraction: float = Field(
        0.5,
        gt=0.0,
        le=1.0,
        description="Side of the patch interior used for fits and patch metrics, as a fraction "
        "of the patch side (a margin against motion blur and fringes).",
    )
    reference_spp: int = Field(
        64, ge=1, le=4096, description="Samples per pixel of the noise-free static reference render."
    )
    bayer: bool = Field(
        True, description="Also simulate an ordinary Bayer-filter capture of the same scene and score it."
    )
    bayer_camera: str = Field(
        "Nikon 5100 (NPL)",
        description="Camera whose R, G, B curves the Bayer capture uses "
        "(colour.MSDS_CAMERA_SENSITIVITIES; spectral variants only).",
    )
    bayer_pattern: Literal["RGGB", "BGGR", "GRBG", "GBRG"] = Field(
        "RGGB", description="Colour filter array layout, rows 0-1 x columns 0-1."
    )
    demosaic: Literal["bilinear", "malvar2004", "menon2007"] = Field(
        "menon2007",
        description="Demosaicing of the Bayer capture, as sensor.demosaic (the sensor stage's colour "
        "filter array, colour-demosaicing): bilinear, malvar2004 or menon2007.",
    )
    bayer_spp: int | None = Field(
        None,
        ge=1,
        le=4096,
        description="Samples per pixel of the Bayer frame's renders "
        "(default: the capture's largest samples per pixel per stratum, render.spp or the noise budget's).",
    )


# -- pure numpy: signals, masks, colour -------------------------------------------------------
def mono_signal(reads_e: np.ndarray, monochrome: bool) -> np.ndarray:
    """(R, H, W, C) electrons -> (R, H, W) panchromatic electrons: channel 0 of a monochrome film
    (its channels are identical renders of one pixel), else the sum over the colour channels
    (a pixel that collects all three bands)."""
    return reads_e[..., 0] if monochrome else reads_e.sum(axis=-1)


def led_signals(mono_e: np.ndarray, exposure_s: np.ndarray, ambient_index: int = 3) -> np.ndarray:
    """Ambient subtraction: (R, H, W) electrons of reads R, G, B, ambient and their exposures (R,)
    -> (H, W, 3) LED-only electron rates e-/s, s_k = e_k / t_k - e_amb / t_amb."""
    rate = mono_e / np.asarray(exposure_s, float)[:, None, None]
    leds = [i for i in range(rate.shape[0]) if i != ambient_index][:3]
    return np.stack([rate[i] - rate[ambient_index] for i in leds], axis=-1)


def patch_boxes_px(scene, width: int, height: int) -> np.ndarray:
    """(P, 4) pixel boxes (x0, y0, x1, y1) of the chart patches at rest, from the scene's camera."""
    boxes = []
    for _, (cx, cy, cz), half in scene.extra["patches"]:
        corners = np.array([[cx - half, cy - half, cz], [cx + half, cy + half, cz]])
        px = scene.camera.project(corners, width, height)
        boxes.append([px[:, 0].min(), px[:, 1].min(), px[:, 0].max(), px[:, 1].max()])
    return np.array(boxes)


def interior_masks(boxes_px: np.ndarray, width: int, height: int, fraction: float) -> np.ndarray:
    """(P, H, W) bool: pixels whose centres lie in the central ``fraction`` (per side) of each box.
    A patch too small to hold a pixel centre gets its nearest pixel."""
    yy, xx = np.mgrid[0:height, 0:width] + 0.5
    out = np.zeros((len(boxes_px), height, width), bool)
    for i, (x0, y0, x1, y1) in enumerate(boxes_px):
        cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * fraction / 2, (y1 - y0) * fraction / 2
        m = (np.abs(xx - cx) <= hx) & (np.abs(yy - cy) <= hy)
        if not m.any():
            m[min(max(int(cy), 0), height - 1), min(max(int(cx), 0), width - 1)] = True
        out[i] = m
    return out


def patch_means(image: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(H, W, C) image, (P, H, W) masks -> (P, C) mean of each patch."""
    return np.stack([image[m].mean(axis=0) for m in masks])


def fit_chart_matrix(signals: np.ndarray, target_xyz: np.ndarray) -> np.ndarray:
    """3x3 M minimizing ||signals @ M - target_xyz||^2 over the patches ((P, 3) each)."""
    m, *_ = np.linalg.lstsq(np.asarray(signals, float), np.asarray(target_xyz, float), rcond=None)
    return m


def analytic_matrix(response: np.ndarray, led_xyz: np.ndarray, white_signal: np.ndarray, white_y: float) -> np.ndarray:
    """M (3x3, signals @ M = XYZ) from spectra: ``response`` (C, K) = integral S_c E_k (each channel's
    signal per unit reflectance under LED k), ``led_xyz`` (3, K) = integral cmf E_k. A surface with
    reflectance rho_k over LED k's band gives signals response @ rho and XYZ led_xyz @ rho, so
    XYZ = led_xyz response^-1 s; the unknown geometry scale is fixed so that the white patch's mean
    signal ``white_signal`` (C,) maps to Y = ``white_y``."""
    m = (np.asarray(led_xyz, float) @ np.linalg.inv(np.asarray(response, float))).T
    y = float(np.asarray(white_signal, float) @ m[:, 1])
    if not y > 0:
        raise ValueError("analytic colour matrix: the white patch has no signal")
    return m * (white_y / y)


COLOUR_METHODS: dict[str, Callable] = {"chart_fit": fit_chart_matrix, "analytic": analytic_matrix}


def colour_matrix(
    method: str,
    signals_patch: np.ndarray,
    true_xyz: np.ndarray,
    white_index: int,
    response: np.ndarray | None = None,
    led_xyz: np.ndarray | None = None,
) -> np.ndarray:
    """Dispatch ``app.method``; an unknown name lists the valid ones."""
    if method not in COLOUR_METHODS:
        raise ConfigError(f"app.method: unknown colour method {method!r}; expected one of {sorted(COLOUR_METHODS)}")
    if method == "chart_fit":
        return fit_chart_matrix(signals_patch, true_xyz)
    return analytic_matrix(response, led_xyz, signals_patch[white_index], float(true_xyz[white_index, 1]))


def xyz_to_lab(xyz: np.ndarray, white_xy: np.ndarray) -> np.ndarray:
    import colour

    return colour.XYZ_to_Lab(np.clip(xyz, 0.0, None), white_xy)


def delta_e2000(xyz_a: np.ndarray, xyz_b: np.ndarray, white_xy: np.ndarray) -> np.ndarray:
    """CIEDE2000 between two XYZ images (white Y = 1) under the white point ``white_xy``."""
    import colour

    return colour.delta_E(xyz_to_lab(xyz_a, white_xy), xyz_to_lab(xyz_b, white_xy), method="CIE 2000")


def xyz_to_linear_srgb(xyz: np.ndarray, white_xy: np.ndarray) -> np.ndarray:
    """For previews: XYZ (illuminant white_xy) -> linear sRGB, chromatically adapted to D65."""
    import colour

    return colour.XYZ_to_RGB(
        xyz,
        colour.RGB_COLOURSPACES["sRGB"],
        illuminant=white_xy,
        chromatic_adaptation_transform="Bradford",
        apply_cctf_encoding=False,
    )


def true_colours(scene) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Patch names, their XYZ (P, 3) under the three LEDs together (perfect white Y = 1) and that
    illuminant's white point xy."""
    import colour

    wl, total = _led_sum(scene)
    illum = colour.SpectralDistribution(dict(zip(wl, total / total.max())))
    names, xyz = [], []
    shape = colour.SpectralShape(360, 780, 1)  # the CMFs' range in sd_to_XYZ; the LEDs emit inside it
    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        illum = illum.copy().align(shape)
        for name, spec in scene.extra["reflectances"].items():
            sd = colour.SpectralDistribution(dict(zip(*spec.arrays))).copy().align(shape)
            xyz.append(colour.sd_to_XYZ(sd, illuminant=illum) / 100.0)
            names.append(name)
        white = colour.sd_to_XYZ(colour.sd_ones(shape), illuminant=illum) / 100.0
    return names, np.array(xyz), colour.XYZ_to_xy(white)


def _led_sum(scene) -> tuple[np.ndarray, np.ndarray]:
    """The three LEDs' summed spectrum on the union of their wavelength grids (each is zero outside
    its own samples, as Mitsuba treats it)."""
    specs = [scene.extra["led_spectra"][g] for g in LED_GROUPS]
    wl = np.unique(np.concatenate([np.asarray(s.wavelengths_nm) for s in specs]))
    return wl, sum(np.interp(wl, *s.arrays, left=0.0, right=0.0) for s in specs)


def led_matrices(
    scene, curves_wl: np.ndarray, curves: np.ndarray, per_led_channel: bool
) -> tuple[np.ndarray, np.ndarray]:
    """(response (C, K), led_xyz (3, K)) for the analytic method. ``curves`` (C, n) on ``curves_wl``
    are the capturing channels' sensitivities; ``per_led_channel``: channel k sees only LED k (the
    multi-bucket sensor), so response is diagonal."""
    import colour

    grid = np.arange(360.0, 831.0, 1.0)
    cmfs = colour.MSDS_CMFS[CMFS_NAME].copy().align(colour.SpectralShape(360, 830, 1)).values  # (n, 3)
    sens = np.stack([np.interp(grid, curves_wl, c, left=0.0, right=0.0) for c in curves])
    e = np.stack([np.interp(grid, *scene.extra["led_spectra"][g].arrays, left=0.0, right=0.0) for g in LED_GROUPS])
    response = np.trapezoid(sens[:, None, :] * e[None], grid, axis=-1)  # (C, K)
    if per_led_channel:
        response = np.diag(np.diag(response))
    led_xyz = np.trapezoid(cmfs.T[:, None, :] * e[None], grid, axis=-1)  # (3, K)
    return response, led_xyz


# -- renders ----------------------------------------------------------------------------------
def _cmf_curves() -> tuple[np.ndarray, np.ndarray]:
    import colour

    cmfs = colour.MSDS_CMFS[CMFS_NAME].copy().align(colour.SpectralShape(360, 830, 5))
    return np.asarray(cmfs.wavelengths, float), np.asarray(cmfs.values, float).T.copy()


def colour_renderer(data: CaptureData, scene) -> Renderer:
    """An RGB renderer of ``scene`` that keeps its colour channels apart: the capture's own when it is
    that scene's and the sensor is not mono (whose renderer mixes them), else a new one sharing its cache."""
    if scene is data.scene and data.cfg.sensor.cfa != "mono":
        return data.renderer
    return Renderer.from_config(scene, data.cfg, mono=None, cache=getattr(data.renderer, "cache", None))


def reference_xyz(data: CaptureData, params: Params, white_mask: np.ndarray, white_y: float) -> np.ndarray:
    """The chart at rest under the three LEDs, noise-free, XYZ scaled so the white patch has Y = white_y."""
    import colour

    cfg, scene = data.cfg, data.scene
    spectral = cfg.render.variant.endswith("_spectral")
    rest = still(scene)  # the chart at rest through a still camera (camera.shake moves only the capture)
    renderer = (
        Renderer.from_config(
            rest, cfg, film_curves=_cmf_curves(), sensor=None, cache=getattr(data.renderer, "cache", None)
        )
        if spectral
        else colour_renderer(data, rest)
    )
    seed = int(np.random.default_rng(data.seed.spawn(1)[0]).integers(0, 2**31 - 1))
    img = renderer.render(float(scene.extra["rest_time_s"]), params.reference_spp, seed, list(LED_GROUPS)).sum(0)
    img = img.astype(np.float64)
    if not spectral:
        img = colour.RGB_to_XYZ(img, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    y_white = float(img[white_mask, 1].mean())
    return img * (white_y / y_white)


def bayer_window(data: CaptureData) -> tuple[float, float]:
    """The interleaved capture's span [start, start + 4T] (s), whether this run is sequential or not."""
    c = data.cfg.capture
    return float(c.start_s), float(c.start_s) + 4.0 * float(c.unit_exposure_s)


def _strata(scene, t0: float, t1: float, width: int, height: int, max_motion_px: float, max_strata: int) -> np.ndarray:
    """Midpoints of equal strata of [t0, t1] inside which no motion point moves more than max_motion_px."""
    if scene.is_static:
        return np.array([(t0 + t1) / 2])
    times = np.linspace(t0, t1, 257)
    px = scene.image_points(times, width, height)  # moving parts, and the frame under camera shake
    path = np.linalg.norm(np.diff(px, axis=0), axis=-1).sum(axis=0).max()
    n = int(min(max(np.ceil(path / max_motion_px), 1), max_strata))
    edges = np.linspace(t0, t1, n + 1)
    return (edges[:-1] + edges[1:]) / 2


def bayer_capture(data: CaptureData, params: Params) -> dict:
    """Simulate the ordinary Bayer frame; returns its demosaiced electron rates (H, W, 3), its
    channel curves and the number of render passes."""

    cfg, scene = data.cfg, data.scene
    spectral = cfg.render.variant.endswith("_spectral")
    W, H = cfg.render.width, cfg.render.height
    # the sensor stage's own colour filter array (mbcapture.sensor.cfa): one channel per photosite, demosaiced
    bayer = {"cfa": params.bayer_pattern, "demosaic": params.demosaic}
    if spectral:
        sensor = cfg.sensor.model_copy(update={"spectral_response": params.bayer_camera, **bayer})
        try:
            curves_wl, curves = film_sensitivity(sensor)
            channel_quantum_efficiency(sensor)
        except ValueError as exc:
            raise ConfigError(f"app.bayer_camera: {exc}") from None
        renderer = Renderer.from_config(scene, cfg, sensor=sensor, cache=getattr(data.renderer, "cache", None))
    else:
        sensor, curves_wl, curves = cfg.sensor.model_copy(update=bayer), None, None
        renderer = colour_renderer(data, scene)
    t0, t1 = bayer_window(data)
    T = float(cfg.capture.unit_exposure_s)
    mids = _strata(scene, t0, t1, W, H, cfg.render.max_motion_px, cfg.render.max_strata)
    dt = (t1 - t0) / len(mids)
    spp = params.bayer_spp or int(data.plan.spp.max())  # the capture's own samples (render.spp or the budget's)
    groups = ["ambient", *LED_GROUPS]
    seeds = np.random.default_rng(data.seed.spawn(2)[1]).integers(0, 2**31 - 1, size=len(mids))
    drive = np.array([1.0] + [T / (t1 - t0)] * 3)  # ambient always; each LED delivers T's worth
    exposure = np.zeros((H, W, 3))
    for t, s in zip(mids, seeds):
        img = renderer.render(float(t), spp, int(s), groups).astype(np.float64)
        exposure += dt * np.einsum("g,ghwc->hwc", drive, img)
    k_e = electrons_per_render_second(sensor, cfg.render.variant)
    expected = exposure * k_e
    rng = np.random.default_rng(data.seed.spawn(3)[2])
    out = sense_frame(expected, sensor, rng, t1 - t0)
    rgb = dn_to_electrons(out.reads_dn, sensor)[0] / (t1 - t0)  # demosaiced by the sensor stage
    return {
        "rates": rgb,
        "curves": (curves_wl, curves),
        "passes": len(mids),
        "window_s": [t0, t1],
        "saturated_fraction": float(out.mosaic_saturated.mean()),
        "sensor": sensor,
    }


def _scores(
    xyz: np.ndarray, ref: np.ndarray, masks: np.ndarray, true_xyz: np.ndarray, white_xy
) -> tuple[dict, np.ndarray]:
    de = delta_e2000(xyz, ref, white_xy)
    interior = masks.any(axis=0)
    patch_de = delta_e2000(patch_means(xyz, masks), true_xyz, white_xy)
    return {
        "delta_e2000_mean": float(de.mean()),
        "delta_e2000_max": float(de.max()),
        "delta_e2000_p99": float(np.percentile(de, 99)),
        "delta_e2000_patch_interior_mean": float(de[interior].mean()),
        "delta_e2000_patch_interior_max": float(de[interior].max()),
        "delta_e2000_patch_colour_vs_true_mean": float(patch_de.mean()),
        "delta_e2000_patch_colour_vs_true_max": float(patch_de.max()),
    }, de


@register(
    "rgb_illumination",
    output_channels=30,
    previews=5,
    libraries_mb=315,
    params=Params,
    description="colour from R, G, B LEDs in three buckets, ambient subtracted; CIEDE2000 vs a static reference",
)
def reconstruct(data: CaptureData, params: Params) -> AppOutput:
    cfg, scene = data.cfg, data.scene
    missing = [g for g in LED_GROUPS if g not in scene.groups] + [
        k for k in ("patches", "reflectances", "led_spectra") if k not in scene.extra
    ]
    if missing:
        raise ConfigError(
            f"app.name: 'rgb_illumination' needs a scene with LED groups {list(LED_GROUPS)} and a "
            f"chart (scene 'colour_chart'); scene {scene.name!r} lacks {missing}"
        )
    if data.read_names[:4] != list(READ_NAMES):
        raise ConfigError(
            f"app.name: 'rgb_illumination' reads {list(READ_NAMES)} (capture.protocol "
            f"'rgb_illumination'), got {data.read_names}"
        )
    W, H = cfg.render.width, cfg.render.height
    names, true_xyz, white_xy = true_colours(scene)
    white_index = names.index(next(n for n in names if n.startswith("white")))
    masks = interior_masks(patch_boxes_px(scene, W, H), W, H, params.patch_interior_fraction)

    # the multi-bucket capture: ambient subtraction, colour matrix
    monochrome = is_monochrome(cfg.sensor.spectral_response)
    signals = led_signals(mono_signal(data.reads_e(), monochrome), data.exposure_s)
    sat = data.saturated[:4].any(axis=(0, -1))
    spectral = cfg.render.variant.endswith("_spectral")
    if params.method == "analytic" and not spectral:
        raise ConfigError(
            "app.method: 'analytic' needs the sensor's spectral curves, i.e. a spectral render.variant "
            f"(got {cfg.render.variant!r}); use 'chart_fit'"
        )
    response = led_xyz = None
    if spectral:
        wl, curves = film_sensitivity(cfg.sensor)
        mono_curve = curves[:1] if monochrome else curves.sum(axis=0, keepdims=True)
        response, led_xyz = led_matrices(scene, wl, np.repeat(mono_curve, 3, axis=0), per_led_channel=True)
    m = colour_matrix(params.method, patch_means(signals, masks), true_xyz, white_index, response, led_xyz)
    xyz = signals @ m

    ref = reference_xyz(data, params, masks[white_index], float(true_xyz[white_index, 1]))
    scores, de = _scores(xyz, ref, masks, true_xyz, white_xy)
    label = "sequential" if data.sequential else "interleaved"
    metrics: dict = {
        "method": params.method,
        "capture": label,
        "illuminant": "the three LEDs together (sum of the scene's LED spectra); CIE 1931 2-degree observer",
        "reference": "chart at rest (scene time %g s) under the three LEDs, no ambient, noise-free, %d spp"
        % (scene.extra["rest_time_s"], params.reference_spp),
        "colour_matrix": m.tolist(),
        "saturated_fraction": float(sat.mean()),
        label: scores,
    }
    images = {
        "colour": xyz_to_linear_srgb(xyz, white_xy),
        "reference": xyz_to_linear_srgb(ref, white_xy),
        "delta_e2000": np.repeat(de[..., None], 3, -1),
        "xyz": xyz,
        "reference_xyz": ref,
        "led_signals": signals,
    }
    png = {"colour": ("colour", None), "reference": ("reference", None), "delta_e2000": ("delta_e2000_png", None)}
    images["delta_e2000_png"] = images["delta_e2000"] / DELTA_E_PNG_WHITE
    summary = [
        f"{label}: CIEDE2000 vs static reference mean {scores['delta_e2000_mean']:.2f}, max "
        f"{scores['delta_e2000_max']:.1f}; patch interiors mean {scores['delta_e2000_patch_interior_mean']:.2f}"
    ]

    if params.bayer:
        bay = bayer_capture(data, params)
        b_resp = b_xyz = None
        if bay["curves"][0] is not None:
            b_resp, b_xyz = led_matrices(scene, bay["curves"][0], bay["curves"][1], per_led_channel=False)
        mb = colour_matrix(params.method, patch_means(bay["rates"], masks), true_xyz, white_index, b_resp, b_xyz)
        xyz_b = bay["rates"] @ mb
        scores_b, de_b = _scores(xyz_b, ref, masks, true_xyz, white_xy)
        metrics["bayer"] = {
            **scores_b,
            "camera": params.bayer_camera,
            "pattern": params.bayer_pattern,
            "demosaic": params.demosaic,
            "window_s": bay["window_s"],
            "render_passes": bay["passes"],
            "saturated_fraction": bay["saturated_fraction"],
            "colour_matrix": mb.tolist(),
        }
        images["bayer"] = xyz_to_linear_srgb(xyz_b, white_xy)
        images["delta_e2000_bayer"] = np.repeat(de_b[..., None], 3, -1)
        images["delta_e2000_bayer_png"] = images["delta_e2000_bayer"] / DELTA_E_PNG_WHITE
        png["bayer"] = ("bayer", None)
        png["delta_e2000_bayer"] = ("delta_e2000_bayer_png", None)
        summary.append(
            f"bayer: CIEDE2000 mean {scores_b['delta_e2000_mean']:.2f}, max {scores_b['delta_e2000_max']:.1f}; "
            f"patch interiors mean {scores_b['delta_e2000_patch_interior_mean']:.2f}"
        )
    return AppOutput(images=images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)
