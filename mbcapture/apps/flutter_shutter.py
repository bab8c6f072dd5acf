"""Flutter shutter without light loss: coded-exposure motion deblurring (Raskar, Agrawal and Tumblin,
"Coded exposure photography: motion deblurring using fluttered shutter", SIGGRAPH 2006) on a
multi-bucket sensor (the multi-bucket paper's section 6: "our multi-bucket sensor can perform
flutter shutter without throwing away 50% of the light").

Protocol ``flutter_shutter`` (``app.code``: the chops, ``app.shutter``: how they are gated)
    The exposure T = ``capture.unit_exposure_s`` is cut into n equal chops (n = the code's length),
    repeated ``capture.periods`` times (1 in the shipped config: one pass of the code, as in Raskar's
    camera). ``two_bucket``: chops whose code bit is 1 go to bucket 1 (read ``open``), the others to
    bucket 2 (read ``closed``): together the two buckets collect all the light of a box exposure.
    ``flutter``: the classic flutter shutter, bucket 1 only, the closed chops drained (half the light
    for a code with half its bits set). ``box``: every chop in bucket 1 (read ``box``), a conventional
    exposure of T. ``capture.sequential: true`` takes the reads as contiguous frames one after another
    (the code is lost: each frame is a box).

    ``app.code``: ``raskar2006``, the 52-chop code published by Raskar et al. 2006 (found there by a
    randomized linear search for a flat, zero-free spectrum; 26 chops open), or any string of 0s and 1s.

Reconstruction (``app.method``: which reads; ``app.deblur``: :data:`DEBLUR_METHODS`), pure numpy
    The motion is known: the scene's motion points, projected, give the image displacement d(t) of
    the object (a fronto-parallel card moves rigidly; only motion along the image rows is supported).
    A read r is b_r(x) = integral g_r(t) f(x - d(t)) dt per row and channel: f the sharp image at the
    capture's mid-time, g_r the read's gate. The kernel comes from the timeline's exact gate integrals
    over 40 000 time steps (:func:`read_samples`: seconds at each fractional shift). The black
    background makes the model exact (nothing is occluded); the sharp image is taken as black where its
    blurred light would leave the frame, so each row has more observations than unknowns (Raskar et
    al.'s model: a blur of k px over an n px object gives n + k - 1 observations).
    ``single`` uses the first read (the open chops: Raskar's single-code deconvolution); ``joint`` every
    read (both buckets), each weighted by w_rc = 1 / its mean noise variance in channel c (shot + read
    noise), so the two complementary buckets count by their signal.
    ``fourier`` (default): least squares per frequency over the zero-padded row,
    F = sum_r w_r conj(H_r) B_r / (sum_r w_r |H_r|^2 + lambda), with H_r(w) = sum_i t_i exp(-i w s_i)
    (band-limited fractional shifts). ``pixel_least_squares``: banded least squares in the pixel
    domain, fractional shifts by linear interpolation onto integer shifts. Measured at 640x512 (1 px
    per chop): linear interpolation smooths every 1-px chop by [1/2, 1/2], a zero at the Nyquist
    frequency, and raises the joint deblur's white-noise gain from 15 to 174 (``white_noise_gain``).
    lambda = ``app.regularization`` x the mean of the denominator (1e-6: numerical safety only; the
    box kernel's spectral zeros are what makes its deblur noisy, as in Raskar et al.).

Comparison at equal exposure (report.json ``comparison``; two_bucket captures)
    From the same render and the same gating three shutters are scored: ``box`` (one bucket
    collecting every chop: its noise-free electrons are exactly bucket 1 + bucket 2, read with its own
    shot and read noise), ``flutter`` (the open bucket alone: what the classic flutter shutter records,
    the closed chops drained), ``two_bucket_flutter`` (both buckets, joint). Each gives PSNR and SSIM
    (scikit-image) of the luminance against the truth, over the image and over the region the card
    sweeps, ``noise_rms`` (deblurred noisy minus deblurred noise-free, radiance, over the swept region),
    ``noise_amplification`` (that over the noise of one read holding all the light of the capture's
    reads, divided by its exposure: for two_bucket the box read, i.e. relative to a static scene shot
    with the same total time; ``reference_noise_rms``) and ``model_rms`` (deblurred noise-free reads against the truth: the
    blur model's own error).

Ground truth: the scene rendered sharp at the capture's mid-time (``app.truth_spp`` samples).
The render plan must resolve the code: ``strata`` reports the largest image motion inside a render
stratum against the motion during one chop (``resolved``: no stratum moves further than one chop).
"""

from __future__ import annotations

from fractions import Fraction
from typing import Callable, Literal

import numpy as np
from pydantic import Field, field_validator

from ..strict import StrictModel
from ..errors import ConfigError
from ..metrics import luminance, psnr
from ..reconstruct.deblur import deblur_fourier, pixel_least_squares, read_samples, spread_kernel, white_noise_gain
from ..sensor import dn_to_electrons
from ..exposure.simulate import sense_frame
from ..timing.timeline import DRAIN, ReadEvent, SlotSeconds, exact
from . import AppOutput, CaptureData, register, register_protocol

#: Raskar, Agrawal and Tumblin 2006: their 52-chop code (26 open).
RASKAR_2006 = "1010000111000001010000110011110111010111001001100111"
CODES = {"raskar2006": RASKAR_2006}


def code_bits(code: str) -> np.ndarray:
    """The chops (0/1 int array) of a named code or a 0/1 string."""
    s = CODES.get(code, code)
    if not s or set(s) - {"0", "1"} or "1" not in s:
        raise ConfigError(f"app.code: expected one of {sorted(CODES)} or a string of 0s and 1s with a 1, got {code!r}")
    return np.array([int(c) for c in s], np.int64)


class FlutterParams(StrictModel):
    code: str = Field(
        "raskar2006",
        description="Chop code: 'raskar2006' (the 52-chop code of Raskar et al. 2006) or a "
        "string of 0s and 1s; read by the flutter_shutter protocol.",
    )
    shutter: Literal["two_bucket", "flutter", "box"] = Field(
        "two_bucket",
        description="flutter_shutter protocol: 'two_bucket' (open chops to bucket 1, closed to bucket 2), "
        "'flutter' (classic: closed chops drained) or 'box' (every chop to bucket 1, a conventional exposure).",
    )
    method: Literal["joint", "single"] = Field(
        "joint",
        description="Deblurred image shown: 'joint' (least squares over "
        "every read) or 'single' (the first read alone).",
    )
    deblur: str = Field(
        "fourier",
        description="Deconvolution: 'fourier' (least squares per frequency over the zero-padded "
        "row, band-limited fractional shifts) or 'pixel_least_squares' (banded least squares, fractional "
        "shifts by linear interpolation).",
    )
    regularization: float = Field(
        1e-6,
        ge=0.0,
        le=1.0,
        description="Tikhonov weight, relative to the mean diagonal of "
        "the normal matrix (numerical safety; 0: plain least squares).",
    )
    truth_spp: int = Field(64, ge=1, le=4096, description="Samples per pixel of the sharp ground-truth render.")

    @field_validator("code")
    @classmethod
    def _code(cls, v: str) -> str:
        code_bits(v)
        return v

    @field_validator("deblur")
    @classmethod
    def _deblur(cls, v: str) -> str:
        if v not in DEBLUR_METHODS:
            raise ValueError(f"unknown deconvolution {v!r}; expected one of {sorted(DEBLUR_METHODS)}")
        return v


# --------------------------------------------------------------------------------- protocol
@register_protocol("flutter_shutter", app="flutter_shutter")
def flutter_shutter_protocol(cfg):
    """n chops of T/(n N) per period (N = capture.periods); open -> bucket 1, closed -> bucket 2 / drain."""
    _, params = cfg.app.resolve(cfg.capture.protocol)
    code = code_bits(getattr(params, "code", FlutterParams().code))
    shutter = getattr(params, "shutter", FlutterParams().shutter)
    need = 2 if shutter == "two_bucket" else 1
    if cfg.sensor.bucket_count < need:
        raise ConfigError(
            f"capture.protocol: 'flutter_shutter' ({shutter}) needs {need} buckets but sensor.bucket_count "
            f"is {cfg.sensor.bucket_count}"
        )
    chop = exact(cfg.capture.unit_exposure_s) / Fraction(len(code) * cfg.capture.periods)
    closed = {"two_bucket": 1, "flutter": DRAIN, "box": 0}[shutter]
    slots = [SlotSeconds(0 if bit else closed, chop) for bit in code]
    if shutter == "two_bucket":
        return slots, [ReadEvent("open", (0,)), ReadEvent("closed", (1,))], 2
    return slots, [ReadEvent("box" if shutter == "box" else "open", (0,))], 1


#: Deblurring methods (``app.deblur``): ``fn(reads (R, H, W, C), samples [(shifts px, seconds)] per read,
#: weights (R, C), regularization) -> (H, W, C)``.
DEBLUR_METHODS: dict[str, Callable] = {"fourier": deblur_fourier, "pixel_least_squares": pixel_least_squares}


def read_weights(expected_e: np.ndarray, k_e: np.ndarray, read_noise_e: float, region: np.ndarray) -> np.ndarray:
    """(R, C) inverse noise variance of each read in radiance x seconds: k_e^2 / (mean e- + read noise^2)
    over ``region`` (H, W)."""
    mean_e = expected_e[:, region].mean(axis=1) if region.any() else expected_e.mean(axis=(1, 2))
    return k_e[None] ** 2 / (mean_e + read_noise_e**2)


def ssim(x: np.ndarray, y: np.ndarray, data_range: float) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(x, y, data_range=data_range))


def score(f: np.ndarray, f0: np.ndarray, truth: np.ndarray, region: np.ndarray, ref_noise: float) -> dict:
    """PSNR/SSIM of luminance against the truth (peak: the truth's largest luminance), noise and model error."""
    lf, l0, lt = luminance(f), luminance(f0), luminance(truth)
    peak = float(lt.max()) or 1.0
    out = {
        "psnr_db": psnr(lf, lt, peak=peak),
        "ssim": ssim(lf, lt, peak),
        "noise_rms": float(np.sqrt(np.mean((lf - l0)[region] ** 2))) if region.any() else None,
        "model_rms": float(np.sqrt(np.mean((l0 - lt) ** 2))),
    }
    if region.any():
        out["psnr_db_object"] = psnr(lf, lt, mask=region, peak=peak)
        out["noise_amplification"] = out["noise_rms"] / ref_noise if ref_noise > 0 else None
    return out


def strata_check(data: CaptureData, code_len: int) -> dict:
    """Largest image motion inside one render stratum against the image motion during one chop."""
    scene, tl, plan = data.scene, data.timeline, data.plan
    if scene.is_static or plan is None:
        return {"note": "static scene"}
    W, H = data.cfg.render.width, data.cfg.render.height

    def moved(a_s, b_s):
        p = scene.camera.project(np.asarray(scene.motion_points(np.array([a_s, b_s]))), W, H)
        return float(np.linalg.norm(p[1] - p[0], axis=-1).max())

    strata = [moved(float(tl.seconds(a)), float(tl.seconds(b))) for a, b in zip(plan.starts_ticks, plan.ends_ticks)]
    chop_s = float(data.cfg.capture.unit_exposure_s) / (code_len * data.cfg.capture.periods)
    t0 = float(tl.seconds(tl.start_tick))
    chop = min(moved(t, t + chop_s) for t in t0 + chop_s * np.arange(code_len * data.cfg.capture.periods))
    return {
        "max_stratum_motion_px": max(strata),
        "chop_motion_px": chop,
        "strata": len(strata),
        "resolved": bool(max(strata) <= chop + 1e-9),
    }


# --------------------------------------------------------------------------------- app
CAPTIONS = {
    "blurred": "the first read's bucket as exposed (radiance, tone-mapped): the object smeared by its motion, coded by the "
    "shutter",
    "deblurred": "the object deblurred with the known motion and code (least squares; both buckets for the two-bucket "
    "flutter shutter)",
    "truth": "reference: the object rendered sharp at the capture's mid-time",
    "deblurred_box": "a box shutter of the same total time, deblurred the same way: its code has spectral zeros",
    "deblurred_flutter": "the classic flutter shutter (open chops only, the closed chops' light drained), deblurred",
}


def deblurred_reads(data: CaptureData, params: FlutterParams, samples, weights, b: np.ndarray) -> dict:
    """Each way of deblurring the reads ``b`` (electrons over k_e): the first read alone (``single``) and, with two
    buckets, both jointly (``joint``); each as (deblurred, the same from the noise-free reads, white-noise gain)."""
    W = data.cfg.render.width
    b0 = data.reads_e_expected / np.asarray(data.k_e, float)
    deblur = DEBLUR_METHODS[params.deblur]  # the name was checked when the config loaded

    def both(idx):
        s_ = [samples[i] for i in idx]
        return (
            deblur(b[idx], s_, weights[idx], params.regularization),
            deblur(b0[idx], s_, weights[idx], params.regularization),
            white_noise_gain(s_, np.ones(len(idx)), W, float(data.exposure_s.sum())),
        )

    results = {"single": both([0])}
    if len(data.timeline.reads) > 1:
        results["joint"] = both(list(range(len(data.timeline.reads))))
    return results


def box_baseline(data: CaptureData, k_e: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The box exposure a conventional sensor takes over the same chops: every chop in one bucket, the sum of the
    reads' noise-free electrons read as one frame through the sensor stage (its own noise, its dark current over its
    exposure). Returns its expected electrons (H, W, C), its read in render units x seconds (1, H, W, C) and its
    exposure (s)."""
    box_e = data.reads_e_expected.sum(axis=0)
    box_seed = (
        np.random.SeedSequence(data.seed.entropy, spawn_key=(*data.seed.spawn_key, 0xB0C5))
        if data.seed is not None
        else 0
    )
    box_t = float(data.exposure_s.sum())
    box_read = sense_frame(box_e, data.cfg.sensor, box_seed, box_t)
    return box_e, dn_to_electrons(box_read.reads_dn, data.cfg.sensor) / k_e, box_t


@register(
    "flutter_shutter",
    output_channels=21,
    previews=5,
    memory_scale=2.5,
    params=FlutterParams,
    description="flutter shutter: coded-exposure deblurring, single code or joint over both buckets, vs box",
)
def reconstruct(data: CaptureData, params: FlutterParams) -> AppOutput:
    cfg, tl = data.cfg, data.timeline
    W, H = cfg.render.width, cfg.render.height
    t_ref = float(Fraction(tl.start_tick + tl.end_tick, 2) * tl.tick_s)
    samples = [read_samples(tl, r, data.scene, t_ref, W, H) for r in tl.reads]
    k_e = np.asarray(data.k_e, float)
    region = data.moving_mask
    sensor = cfg.sensor
    weights = read_weights(data.reads_e_expected, k_e, sensor.read_noise_e, region)
    b = data.reads_e() / k_e
    results = deblurred_reads(data, params, samples, weights, b)
    main_key = params.method if params.method in results else "single"
    main = results[main_key][0]

    # the box baseline: every chop in one bucket = the sum of the reads' noise-free electrons, its own noise
    box_e, box_b, box_t = box_baseline(data, k_e)
    box_samples = [(np.concatenate([s_ for s_, _ in samples]), np.concatenate([w_ for _, w_ in samples]))]
    ref_noise = (
        float(np.sqrt(np.mean(luminance((box_b[0] - box_e / k_e) / box_t)[region] ** 2))) if region.any() else 0.0
    )
    kernels = [spread_kernel(*sm) for sm in samples]

    metrics: dict = {
        "code": CODES.get(params.code, params.code),
        "chops": int(len(code_bits(params.code))),
        "open_fraction": float(code_bits(params.code).mean()),
        "shutter": params.shutter,
        "reads": data.read_names,
        "method": main_key,
        "deblur": params.deblur,
        "kernels_px": {
            n: {"first_shift": f, "length": len(h), "seconds": float(h.sum())}
            for n, (f, h) in zip(data.read_names, kernels)
        },
        "saturated_px": int(data.saturated.any(axis=(0, -1)).sum()),
        "strata": strata_check(data, len(code_bits(params.code))),
    }
    images = {"deblurred": main.astype(np.float32)}
    for n, i in zip(data.read_names, range(len(tl.reads))):
        images[f"blurred_{n}"] = (b[i] / data.exposure_s[i]).astype(np.float32)
    png = {"deblurred": ("deblurred", cfg.output.png_percentile)}
    summary = [
        f"flutter shutter ({params.shutter}, {len(code_bits(params.code))} chops): deblurred by {main_key} "
        f"least squares ({params.deblur})"
    ]

    if data.renderer is not None:
        truth = _truth(data, params, t_ref)
        images["truth"] = truth.astype(np.float32)
        png["truth"] = ("truth", cfg.output.png_percentile)
        table = {}
        for key, (f, f0, gain) in results.items():
            table[key] = {**score(f, f0, truth, region, ref_noise), "white_noise_gain": gain}
        if not data.sequential and params.shutter == "two_bucket":
            w_box = read_weights(box_e[None], k_e, sensor.read_noise_e, region)
            fb = DEBLUR_METHODS[params.deblur](box_b, box_samples, w_box, params.regularization)
            fb0 = DEBLUR_METHODS[params.deblur]((box_e / k_e)[None], box_samples, w_box, params.regularization)
            images["deblurred_box"] = fb.astype(np.float32)
            images["blurred_box"] = (box_b[0] / box_t).astype(np.float32)
            png["deblurred_box"] = ("deblurred_box", cfg.output.png_percentile)
            comparison = {
                "box": {
                    "light_fraction": 1.0,
                    **score(fb, fb0, truth, region, ref_noise),
                    "white_noise_gain": white_noise_gain(box_samples, np.ones(1), W, box_t),
                },
                "flutter": {"light_fraction": float(data.exposure_s[0] / box_t), **table["single"]},
                "two_bucket_flutter": {"light_fraction": float(data.exposure_s.sum() / box_t), **table["joint"]},
            }
            metrics["comparison"] = comparison
            images["deblurred_flutter"] = results["single"][0].astype(np.float32)
            png["deblurred_flutter"] = ("deblurred_flutter", cfg.output.png_percentile)
            for k, v in comparison.items():
                summary.append(
                    f"  {k:>18}: PSNR {v['psnr_db']:.2f} dB, SSIM {v['ssim']:.3f}, noise x"
                    f"{v.get('noise_amplification') or float('nan'):.2f}"
                )
        metrics["deblurred"] = table
        metrics["truth"] = {
            "time_s": t_ref,
            "spp": params.truth_spp,
            "object_px": int(region.sum()),
            "what": "the scene rendered sharp at the capture's mid-time",
        }
        metrics["reference_noise_rms"] = ref_noise
        m = table[main_key]
        summary.insert(1, f"deblurred ({main_key}): PSNR {m['psnr_db']:.2f} dB, SSIM {m['ssim']:.3f}")
    png["blurred"] = (f"blurred_{data.read_names[0]}", cfg.output.png_percentile)
    return AppOutput(images=images, metrics=metrics, png=png, summary=summary, captions=CAPTIONS)


def _sum_kernels(kernels) -> tuple[np.ndarray, np.ndarray]:
    """(shifts, weights) of the sum of kernels, for :func:`spread_kernel` (integer shifts: exact)."""
    shifts = np.concatenate([f + np.arange(len(h)) for f, h in kernels]).astype(float)
    return shifts, np.concatenate([h for _, h in kernels])


def _truth(data: CaptureData, params: FlutterParams, t_ref: float) -> np.ndarray:
    groups = list(data.plan.groups)
    seed = int(np.random.default_rng(data.seed).integers(0, 2**31 - 1))
    rad = data.renderer.render(t_ref, params.truth_spp, seed, groups).astype(np.float64)
    return rad.sum(axis=0)
