"""The golden-image cases: what each one computes, shared by tests/test_golden.py and by
scripts/golden_spread.py (which computes them under several CPU targets to measure how much
they legitimately differ between machines).

A case is a name and a function returning named float images. Capture cases run a shipped
config at 32x24; the others exercise the pure-numpy sensor and HDR stages on a synthetic
exposure ramp.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TINY = ["render.width=32", "render.height=24", "render.spp=4", "render.max_motion_px=2.0", "render.min_strata=1"]
# 2 spp per half: the default sampler (multijitter) stratifies; at 1 spp it draws what the independent sampler
# draws. Few strata (one where the image moves under 2 px): the goldens pin the pixel pipeline, not the plan's
# time noise (render.min_strata's subject), on a plan that renders fast

# (case name, config file, overrides). Applications add their configs here as they land.
CAPTURE_CASES = [
    ("photon_efficient_hdr", "metronome_hdr.yaml", []),
    ("interleaved_hdr", "metronome_hdr.yaml", ["capture.protocol=interleaved_hdr"]),
    ("sequential_hdr", "metronome_hdr.yaml", ["capture.sequential=true"]),
    ("flash_no_flash", "flash_no_flash.yaml", []),
    ("flash_no_flash_sequential", "flash_no_flash.yaml", ["capture.sequential=true"]),
    ("multi_flash", "multi_flash.yaml", []),
    # per-pixel gates: two buckets, five sub-frames sent by a Hadamard code, demultiplexed
    ("coded_multi_flash", "coded_multi_flash.yaml", []),
    ("flash_matting", "flash_matting.yaml", []),
    ("moving_light", "moving_light.yaml", []),
    ("rgb_illumination", "rgb_illumination.yaml", []),
    ("structured_light", "structured_light.yaml", []),
    ("flutter_shutter", "flutter_shutter.yaml", []),
    ("metronome_shake", "metronome_shake.yaml", []),
    ("burst", "burst.yaml", []),
    ("hdr_video", "hdr_video.yaml", ["capture.frames=3"]),
    # the thin lens (camera.lens: thin) at f/1.4: at 32x24 its blur radius is under a tenth of a pixel, but its renders
    # draw lens samples a pinhole does not; its blur law is tested in tests/test_optics.py
    ("thin_lens", "metronome_hdr.yaml", ["camera.lens=thin", "sensor.f_number=1.4"]),
    # a Bayer sensor (sensor.cfa): the stage's codes are the photosites' (R, H, W, 1); the HDR merge runs on
    # them and its radiance is demosaiced (menon2007, the default)
    ("bayer", "metronome_hdr.yaml", ["sensor.cfa=RGGB"]),
    # indirect time of flight: the phasor channels, the taps' combination, the sensor and the depth; the 2-tap
    # sequential design's sub-frames (segments with a readout between them)
    ("tof_4tap", "tof_4tap.yaml", []),
    ("tof_2tap_sequential", "tof_4tap.yaml", ["capture.protocol=tof_2tap_sequential", "sensor.bucket_count=2"]),
]

#: Images of a config's captures that are not pinned, and why: a wrapped phase jumps by 2 pi where it
#: lies within rounding of 0 (the reads are the golden's, but the trigonometry rounds per CPU).
UNPINNED = {
    "structured_light.yaml": {"phase": "wrapped to [0, 2 pi): a pixel near 0 flips by 2 pi"},
    "tof_4tap.yaml": {
        "phase_f1": "wrapped to [0, 2 pi): a pixel near 0 (the window, whose phase is rounding's) flips by 2 pi",
    },
}

#: Images that are zero by construction (up to float64 rounding): compared with an absolute
#: bound, since a relative error of rounding noise means nothing.
ZERO_BY_CONSTRUCTION = {("moving_light", "read_spread_rel")}

HDR_METHODS = ("ramp_fit", "inverse_variance", "debevec")
CUMULATIVE_READS = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]


@dataclass
class CaseRun:
    """One run of a capture case, every sensor stage seen through its seam
    (:func:`mbcapture.sensor.sensor_stage_hook`).

    ``images``      what the golden pins: each stage's input ``sensor{i}_in`` (float64 expected
                    electrons, render + accumulate), its reads ``sensor{i}_dn`` simulated on the
                    *stored* input when one was given, and the application's images computed from
                    those reads;
    ``fresh_in``    each stage's input as rendered on this machine;
    ``fresh_dn``    the reads the sensor gives on ``fresh_in`` (the end-to-end result);
    ``reads``       the buckets each read of each stage sums;
    ``gain_dn_per_e`` the capture's conversion gain;
    ``cfas``        each stage's colour filter array (``sensor.cfa``; an application's comparison
                    captures may have their own).
    """

    images: dict[str, np.ndarray]
    fresh_in: list[np.ndarray]
    fresh_dn: list[np.ndarray]
    reads: list[tuple[tuple[int, ...], ...]]
    gain_dn_per_e: float
    result: object = None
    cfas: list[str] = field(default_factory=list)


def sensor_codes(reads) -> np.ndarray:
    """The integer codes a sensor stage read out: its photosites' on a colour-filter-array sensor
    (R, H, W, 1), whose one-count flips between CPUs the golden counts; the reads otherwise."""
    return reads.reads_dn if reads.mosaic_dn is None else reads.mosaic_dn[..., None]


class StageRecorder:
    """The hook of :func:`mbcapture.sensor.sensor_stage_hook` for a golden run: records every sensor
    stage's input and end-to-end reads, and, given the golden's stored inputs, simulates the sensor
    on those instead, so that each count downstream is pinned on its own stored input."""

    def __init__(self, stored: list[np.ndarray] | None):
        self.stored = stored
        self.fresh_in: list[np.ndarray] = []
        self.fresh_dn: list[np.ndarray] = []
        self.used_dn: list[np.ndarray] = []
        self.reads: list[tuple[tuple[int, ...], ...]] = []
        self.cfas: list[str] = []

    def __call__(self, expected_e: np.ndarray, simulate):
        i = len(self.fresh_in)
        fresh = simulate(expected_e)
        self.fresh_in.append(np.array(expected_e, np.float64))
        self.fresh_dn.append(sensor_codes(fresh))
        self.reads.append(fresh.reads)
        self.cfas.append(fresh.cfa)
        out = fresh
        if self.stored is not None:
            if i >= len(self.stored) or self.stored[i].shape != expected_e.shape:
                raise AssertionError(
                    f"sensor stage {i}: the golden stored {len(self.stored)} stage inputs "
                    f"({[x.shape for x in self.stored]}), this run has input {expected_e.shape}"
                )
            out = simulate(self.stored[i])
        self.used_dn.append(sensor_codes(out))
        return out


def run_capture_case(
    config: str, overrides: list[str], extra: list[str] = (), stored: list[np.ndarray] | None = None
) -> CaseRun:
    """Run a capture case; ``stored``: the golden's sensor-stage inputs to replay (None: none)."""
    from mbcapture import load_config, run_capture
    from mbcapture.sensor import sensor_stage_hook

    cfg = load_config(ROOT / "configs" / config, [*TINY, *overrides, *extra])
    recorder = StageRecorder(stored)
    with sensor_stage_hook(recorder):
        res = run_capture(cfg, progress=False)
    if stored is not None and len(recorder.fresh_in) != len(stored):
        raise AssertionError(f"{len(recorder.fresh_in)} sensor stages ran, the golden stored {len(stored)}")
    images = {f"sensor{i}_in": x for i, x in enumerate(recorder.fresh_in)}
    images |= {f"sensor{i}_dn": x for i, x in enumerate(recorder.used_dn)}
    images |= {k: v for k, v in app_images(res).items() if k not in UNPINNED.get(config, {})}
    return CaseRun(
        images, recorder.fresh_in, recorder.fresh_dn, recorder.reads, cfg.sensor.gain_dn_per_e, res, recorder.cfas
    )


#: Images of every application that the goldens do not pin, and why.
UNPINNED_EVERYWHERE = {
    "sigma": "hypot(sigma_temporal, the fixed pattern's sigma, a function of the radiance): sigma_temporal and "
    "radiance are pinned, and the formula is tested in tests/test_hdr.py",
}


def app_images(res) -> dict[str, np.ndarray]:
    """The application's non-boolean images of a capture (and of every frame of a video)."""
    images = {k: v for k, v in res.images.items() if np.asarray(v).dtype != bool and k not in UNPINNED_EVERYWHERE}
    video = getattr(res, "video", None)
    if video is not None:  # a video run: every later frame's HDR radiance and the alternating-exposure video's
        images |= {f"frame{i}_radiance": f.images["radiance"] for i, f in enumerate(video.frames) if i}
        if video.alternating_radiance is not None:
            images |= {f"alternating{i}_radiance": a for i, a in enumerate(video.alternating_radiance)}
    return images


def stored_inputs(images: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The sensor-stage inputs of a golden, in stage order."""
    n = sum(1 for k in images if k.startswith("sensor") and k.endswith("_in"))
    return [np.asarray(images[f"sensor{i}_in"], np.float64) for i in range(n)]


def synthetic_exposure(shape=(4, 12, 16, 3)) -> np.ndarray:
    """Bucket electrons spanning dark to saturated: a horizontal ramp over 5 decades, 4:2:1:1."""
    ramp = np.geomspace(0.5, 5e4, shape[2])[None, None, :, None] * np.linspace(0.5, 1.0, shape[1])[None, :, None, None]
    ratio = np.array([4.0, 2.0, 1.0, 1.0])[:, None, None, None] / 8
    return np.broadcast_to(ramp * ratio, shape).astype(np.float64) * np.array([1.0, 0.8, 0.6])


def sensor_config():
    """The default sensor with every effect on: fixed pattern, dark current, transfer
    inefficiency and parasitic light (the latter two are 0 by default)."""
    from mbcapture.sensor import SensorConfig

    return SensorConfig(transfer_inefficiency=2e-3, parasitic_light=1e-3)


def sensor_images(seed: int = 7) -> dict[str, np.ndarray]:
    from mbcapture.sensor import simulate_reads

    out = simulate_reads(
        synthetic_exposure(),
        CUMULATIVE_READS,
        sensor_config(),
        np.random.SeedSequence(seed),
        storage_s=np.full(4, 8e-3),
    )
    return {"reads_dn": out.reads_dn, "expected_e": out.reads_e_expected, "saturated": out.saturated}


def hdr_images(method: str) -> dict[str, np.ndarray]:
    from mbcapture.reconstruct.hdr import merge_hdr
    from mbcapture.sensor import simulate_reads

    cfg = sensor_config()
    out = simulate_reads(
        synthetic_exposure(), CUMULATIVE_READS, cfg, np.random.SeedSequence(8), storage_s=np.full(4, 8e-3)
    )
    res = merge_hdr(
        out.reads_dn, np.array([1e-3, 2e-3, 4e-3, 8e-3]), cfg, method=method, cumulative=True, saturated=out.saturated
    )
    return {"rate": res.rate_e_per_s, "sigma": res.sigma_temporal_e_per_s, "valid": res.valid}


def all_cases(golden_dir: Path | None = None) -> dict[str, Callable[[], dict[str, np.ndarray]]]:
    """Every golden case by name (capture cases need Mitsuba). With ``golden_dir``, capture cases
    replay the sensor-stage inputs stored there (as the golden tests do) and add each stage's
    end-to-end reads as ``sensor{i}_dn_fresh``."""

    def capture(config, overrides, name):
        stored = None
        if golden_dir is not None and (golden_dir / f"{name}.npz").exists():
            with np.load(golden_dir / f"{name}.npz") as data:
                stored = stored_inputs({k: data[k] for k in data.files})
        run = run_capture_case(config, overrides, stored=stored)
        return run.images | {f"sensor{i}_dn_fresh": x for i, x in enumerate(run.fresh_dn)}

    cases: dict[str, Callable[[], dict[str, np.ndarray]]] = {
        name: (lambda c=config, o=overrides, n=name: capture(c, o, n)) for name, config, overrides in CAPTURE_CASES
    }
    cases["sensor_reads"] = sensor_images
    for m in HDR_METHODS:
        cases[f"hdr_{m}"] = lambda m=m: hdr_images(m)
    return cases


# ---------------------------------------------------------------------------------------------
# Comparing images, and the tolerances derived from measured cross-target differences

#: Where the measured differences between CPU targets are kept (scripts/golden_spread.py).
SPREAD_FILE = ROOT / "tests" / "golden" / "cross_target.json"
#: Tolerance = SAFETY x the largest difference measured between emulated CPU targets: the targets
#: span vector widths 4, 8 and 16 with and without FMA, and a machine not among them may round a
#: little differently again.
SAFETY = 4.0
#: Below this relative L2 an image is equal up to float32 storage (16 ulps of float32).
FLOOR_REL_L2 = 16 * 2.0**-24
#: A thresholded image (a mask, a trimap, edges, saturation flags) may flip a sample on a machine
#: the emulation does not cover, where a value lies within rounding of its threshold.
FLOOR_FLIPS = 2
#: Bound on images that are zero by construction (float64 rounding is ~1e-16 of their inputs).
ZERO_ABS = 1e-12


#: Allowed end-to-end one-count flips: the (1 - COUNT_FLIP_P)-quantile of a Poisson law of mean
#: SAFETY x the expected number of flips (:func:`expected_flips`). At 1e-6 a run on any machine fails
#: by chance once in a million images.
COUNT_FLIP_P = 1e-6


def is_sensor_reads(name: str) -> bool:
    """``sensor{i}_dn``: the reads of a sensor stage simulated on the golden's own stored input."""
    return name.startswith("sensor") and name.endswith("_dn") and name[6:-3].isdigit()


def is_discrete(image: np.ndarray) -> bool:
    """Thresholded images take at most a few distinct values (0/1 masks, 0/0.5/1 trimaps)."""
    finite = image[np.isfinite(image)]
    return finite.size > 0 and np.unique(finite).size <= 4


def _nonfinite_class(x: np.ndarray) -> np.ndarray:
    """0 finite, 1 NaN, 2 +inf, 3 -inf."""
    return np.where(np.isfinite(x), 0, np.where(np.isnan(x), 1, np.where(x > 0, 2, 3)))


def compare(obtained: np.ndarray, expected: np.ndarray) -> dict:
    """Differences of two images, both as stored (float32, or float64 for a golden stored so):

    ``rel_l2``      ||a - b|| / ||b|| over the samples finite in both (0 for two zero images);
    ``flips``       samples that differ at all (the measure for thresholded images);
    ``nonfinite``   samples finite in one image and not in the other (e.g. sigma = inf where
                    every read saturated);
    ``nonfinite_kind`` samples non-finite in both but of another kind (inf in one, NaN in the
                    other): never allowed;
    ``max_abs``     largest |a - b| over the samples finite in both.
    """
    dtype = np.float64 if np.asarray(expected).dtype == np.float64 else np.float32
    a = np.asarray(obtained, dtype).astype(np.float64)
    b = np.asarray(expected, dtype).astype(np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shape {a.shape} != {b.shape}")
    fa, fb = np.isfinite(a), np.isfinite(b)
    both = fa & fb
    d = a[both] - b[both]
    norm = float(np.linalg.norm(b[both]))
    diff = float(np.linalg.norm(d))
    ca, cb = _nonfinite_class(a), _nonfinite_class(b)
    return {
        "rel_l2": diff / norm if norm > 0 else diff,
        "flips": int(np.count_nonzero(d != 0) + np.count_nonzero(ca != cb)),
        "nonfinite": int(np.count_nonzero(fa != fb)),
        "nonfinite_kind": int(np.count_nonzero(~fa & ~fb & (ca != cb))),
        "max_abs": float(np.abs(d).max()) if d.size else 0.0,
    }


def tolerance(case: str, name: str, golden: np.ndarray, measured: dict | None) -> dict:
    """What ``compare(obtained, golden)`` may reach for image ``name`` of ``case``.

    ``measured``: the largest differences found between CPU targets (cross_target.json), or
    None when the image was not measured (then only the floors apply). The reads of a sensor
    stage run on its stored input are exact: the same expected electrons and noise fields give
    the same counts on every machine.
    """
    m = measured or {"rel_l2": 0.0, "flips": 0, "nonfinite": 0, "max_abs": 0.0}
    if (case, name) in ZERO_BY_CONSTRUCTION:
        return {"kind": "zero", "max_abs": ZERO_ABS}
    if is_sensor_reads(name):
        return {"kind": "exact", "flips": 0, "nonfinite": 0}
    nonfinite = max(int(np.ceil(SAFETY * m["nonfinite"])), FLOOR_FLIPS if np.any(~np.isfinite(golden)) else 0)
    if is_discrete(golden):
        return {
            "kind": "discrete",
            "flips": max(int(np.ceil(SAFETY * m["flips"])), FLOOR_FLIPS),
            "nonfinite": nonfinite,
        }
    return {"kind": "continuous", "rel_l2": max(SAFETY * m["rel_l2"], FLOOR_REL_L2), "nonfinite": nonfinite}


def within(diff: dict, tol: dict, obtained: np.ndarray) -> str | None:
    """None if ``diff`` (from :func:`compare`) is within ``tol``, else why not."""
    if tol["kind"] == "zero":
        x = np.abs(np.asarray(obtained, np.float64))
        if not np.all(np.isfinite(x)):
            return f"{np.count_nonzero(~np.isfinite(x))} non-finite samples (zero by construction)"
        worst = float(x.max()) if x.size else 0.0
        return (
            None if worst <= tol["max_abs"] else f"max |value| {worst:.3g} > {tol['max_abs']:g} (zero by construction)"
        )
    if diff["nonfinite_kind"]:
        return f"{diff['nonfinite_kind']} non-finite samples changed kind (inf <-> NaN)"
    if diff["nonfinite"] > tol["nonfinite"]:
        return f"{diff['nonfinite']} samples finite in one image only > {tol['nonfinite']}"
    if tol["kind"] in ("discrete", "exact"):
        return None if diff["flips"] <= tol["flips"] else f"{diff['flips']} samples differ > {tol['flips']}"
    return None if diff["rel_l2"] <= tol["rel_l2"] else f"relative L2 error {diff['rel_l2']:.3g} > {tol['rel_l2']:.3g}"


def expected_flips(fresh_in: np.ndarray, golden_in: np.ndarray, reads) -> np.ndarray:
    """(R,) expected number of samples of each read whose count moves between two runs of the sensor
    on inputs ``fresh_in`` and ``golden_in`` (K, H, W, C) with the same noise fields.

    A bucket's count is the Poisson inversion n(lambda) = F^-1(u; lambda) of a fixed uniform u, so
    E_u[n(lambda)] = lambda: moving lambda by delta moves the count by delta on average, and for
    |delta| < 1 by 0 or 1, i.e. by one with probability |delta| (the sum over n of the shifts
    p(n; lambda) |delta| of the CDF steps). A read changes where one of its buckets does (the
    transfer-loss binomial follows the bucket's count; the read noise and ADC use the same fields):
    at most the sum of min(1, |delta|) over its buckets, summed over samples."""
    delta = np.abs(np.asarray(fresh_in, np.float64) - np.asarray(golden_in, np.float64))
    per_bucket = np.minimum(delta, 1.0).reshape(delta.shape[0], -1).sum(axis=1)
    return np.array([per_bucket[list(r)].sum() for r in reads])


def largest_count_change_e(fresh_in: np.ndarray, golden_in: np.ndarray, reads) -> np.ndarray:
    """(R, H, W, C) the most electrons by which a read's count can move between the two inputs:
    per bucket ceil(|delta| (1 + 3 / sqrt(lambda))), the count being lambda + sqrt(lambda) z with
    dn/dlambda = 1 + z / (2 sqrt(lambda)) and |z| <= 6; 0 where the inputs are equal."""
    fresh_in, golden_in = np.asarray(fresh_in, np.float64), np.asarray(golden_in, np.float64)
    lam = np.maximum(np.minimum(fresh_in, golden_in), 1.0)
    per_bucket = np.ceil(np.abs(fresh_in - golden_in) * (1.0 + 3.0 / np.sqrt(lam)))
    return np.stack([per_bucket[list(r)].sum(axis=0) for r in reads])


def allowed_flips(mean_flips: float) -> int:
    """Samples a read may show changed: the (1 - COUNT_FLIP_P) Poisson quantile of SAFETY x the mean."""
    from scipy.stats import poisson

    return int(poisson.ppf(1.0 - COUNT_FLIP_P, SAFETY * mean_flips)) if mean_flips > 0 else 0


#: How far two renders of the same request may differ at hundreds of samples per pixel, on one machine: the
#: renderer sums a pixel's samples with float32 atomic adds from several threads, in an order of the threads'
#: making, so two untiled runs of the default capture at 48x64 and 300 spp differed in 184 of 36864 exposure
#: samples by at most 2e-10 (relative 3e-8). At a few samples per pixel one thread sums each pixel and runs
#: agree bit for bit. What a tiled or a cluster run with the noise budget is compared to the local one with.
RENDER_REPEAT_RTOL = 1e-6


def count_differences(
    fresh_dn: np.ndarray,
    golden_dn: np.ndarray,
    fresh_in: np.ndarray,
    golden_in: np.ndarray,
    reads,
    gain_dn_per_e: float,
) -> list[str]:
    """Compare end-to-end reads as counts: each read may differ from its golden in at most
    :func:`allowed_flips` samples, each by no more than the DN its inputs' difference can make
    (:func:`largest_count_change_e` times the gain, rounded up: one count where the inputs differ by
    less than an electron), and a sample whose inputs are equal not at all. Returns why not, one
    line per read ([] when within)."""
    mean = expected_flips(fresh_in, golden_in, reads)
    most_dn = np.ceil(gain_dn_per_e * largest_count_change_e(fresh_in, golden_in, reads))
    out = []
    for r in range(len(reads)):
        d = np.asarray(fresh_dn[r], np.float64) - np.asarray(golden_dn[r], np.float64)
        if not np.all(np.isfinite(d)):
            out.append(f"read {r}: non-finite DN")
            continue
        big = np.abs(d) > most_dn[r]
        flips = int(np.count_nonzero(d))
        allowed = allowed_flips(float(mean[r]))
        if big.any():
            i = tuple(np.argwhere(big)[0])
            out.append(
                f"read {r}: {int(big.sum())} samples differ by more than their inputs allow, e.g. {d[i]:g} DN "
                f"at {i} where at most {most_dn[r][i]:g} DN (one count: {gain_dn_per_e:g} DN)"
            )
        elif flips > allowed:
            out.append(
                f"read {r}: {flips} samples differ > {allowed} allowed "
                f"(expected {mean[r]:.3g} from the inputs' differences)"
            )
    return out
