"""The golden-image cases: what each one computes, shared by tests/test_golden.py and by
scripts/golden_spread.py (which computes them under several CPU targets to measure how much
they legitimately differ between machines).

A case is a name and a function returning named float images. Capture cases run a shipped
config at 32x24; the others exercise the pure-numpy sensor and HDR stages on a synthetic
exposure ramp.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TINY = ["render.width=32", "render.height=24", "render.spp=4", "render.max_motion_px=2.0"]  # 2 spp per half: the default
# sampler (multijitter) stratifies; at 1 spp it draws what the independent sampler draws

# (case name, config file, overrides). Applications add their configs here as they land.
CAPTURE_CASES = [
    ("photon_efficient_hdr", "metronome_hdr.yaml", []),
    ("interleaved_hdr", "metronome_hdr.yaml", ["capture.protocol=interleaved_hdr"]),
    ("sequential_hdr", "metronome_hdr.yaml", ["capture.sequential=true"]),
    ("flash_no_flash", "flash_no_flash.yaml", []),
    ("flash_no_flash_sequential", "flash_no_flash.yaml", ["capture.sequential=true"]),
    ("multi_flash", "multi_flash.yaml", []),
    ("flash_matting", "flash_matting.yaml", []),
    ("moving_light", "moving_light.yaml", []),
    ("rgb_illumination", "rgb_illumination.yaml", []),
    ("structured_light", "structured_light.yaml", []),
    ("flutter_shutter", "flutter_shutter.yaml", []),
    ("metronome_shake", "metronome_shake.yaml", []),
    ("burst", "burst.yaml", []),
    ("hdr_video", "hdr_video.yaml", ["capture.frames=3"]),
]

#: Images of a config's captures that are not pinned, and why: a wrapped phase jumps by 2 pi where a
#: read one electron apart (another CPU's last-bit render difference) moves it across 0.
UNPINNED = {"structured_light.yaml": {"phase": "wrapped to [0, 2 pi): a pixel near 0 flips by 2 pi"}}

#: Images that are zero by construction (up to float64 rounding): compared with an absolute
#: bound, since a relative error of rounding noise means nothing.
ZERO_BY_CONSTRUCTION = {("moving_light", "read_spread_rel")}

HDR_METHODS = ("ramp_fit", "inverse_variance", "debevec")
CUMULATIVE_READS = [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)]


def capture_images(config: str, overrides: list[str], extra: list[str] = ()) -> dict[str, np.ndarray]:
    """Every image a capture case pins: each read's expected electrons and DN, and the
    application's non-boolean images."""
    from mbcapture import load_config, run_capture

    res = run_capture(load_config(ROOT / "configs" / config, [*TINY, *overrides, *extra]), progress=False)
    return {k: v for k, v in result_images(res).items() if k not in UNPINNED.get(config, {})}


def result_images(res) -> dict[str, np.ndarray]:
    images = {f"expected_{r.name}": res.reads_expected_e[i] for i, r in enumerate(res.timeline.reads)}
    images |= {f"reads_dn_{r.name}": res.reads_dn[i] for i, r in enumerate(res.timeline.reads)}
    images |= {k: v for k, v in res.images.items() if np.asarray(v).dtype != bool}
    video = getattr(res, "video", None)
    if video is not None:  # a video run: every later frame's HDR radiance and the alternating-exposure video's
        images |= {f"frame{i}_radiance": f.images["radiance"] for i, f in enumerate(video.frames) if i}
        if video.alternating_radiance is not None:
            images |= {f"alternating{i}_radiance": a for i, a in enumerate(video.alternating_radiance)}
    return images


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

    out = simulate_reads(synthetic_exposure(), CUMULATIVE_READS, sensor_config(), np.random.SeedSequence(seed),
                         storage_s=np.full(4, 8e-3))
    return {"reads_dn": out.reads_dn, "expected_e": out.reads_e_expected, "saturated": out.saturated}


def hdr_images(method: str) -> dict[str, np.ndarray]:
    from mbcapture.reconstruct.hdr import merge_hdr
    from mbcapture.sensor import simulate_reads

    cfg = sensor_config()
    out = simulate_reads(synthetic_exposure(), CUMULATIVE_READS, cfg, np.random.SeedSequence(8),
                         storage_s=np.full(4, 8e-3))
    res = merge_hdr(out.reads_dn, np.array([1e-3, 2e-3, 4e-3, 8e-3]), cfg, method=method, cumulative=True,
                    saturated=out.saturated)
    return {"rate": res.rate_e_per_s, "sigma": res.sigma_e_per_s, "valid": res.valid}


def all_cases() -> dict[str, Callable[[], dict[str, np.ndarray]]]:
    """Every golden case by name (capture cases need Mitsuba)."""
    cases: dict[str, Callable[[], dict[str, np.ndarray]]] = {
        name: (lambda c=config, o=overrides: capture_images(c, o)) for name, config, overrides in CAPTURE_CASES
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


def is_discrete(image: np.ndarray) -> bool:
    """Thresholded images take at most a few distinct values (0/1 masks, 0/0.5/1 trimaps)."""
    finite = image[np.isfinite(image)]
    return finite.size > 0 and np.unique(finite).size <= 4


def compare(obtained: np.ndarray, expected: np.ndarray) -> dict:
    """Differences of two images, both as stored (float32):

    ``rel_l2``      ||a - b|| / ||b|| over the samples finite in both (0 for two zero images);
    ``flips``       samples that differ at all (the measure for thresholded images);
    ``nonfinite``   samples finite in one image and not in the other (e.g. sigma = inf where
                    every read saturated);
    ``max_abs``     largest |a - b| over the samples finite in both.
    """
    a = np.asarray(obtained, np.float32).astype(np.float64)
    b = np.asarray(expected, np.float32).astype(np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shape {a.shape} != {b.shape}")
    fa, fb = np.isfinite(a), np.isfinite(b)
    both = fa & fb
    d = a[both] - b[both]
    norm = float(np.linalg.norm(b[both]))
    diff = float(np.linalg.norm(d))
    same_nonfinite = (~fa & ~fb) & ((a == b) | (np.isnan(a) & np.isnan(b)))
    return {
        "rel_l2": diff / norm if norm > 0 else diff,
        "flips": int(np.count_nonzero(d != 0) + np.count_nonzero(~both & ~same_nonfinite)),
        "nonfinite": int(np.count_nonzero(fa != fb)),
        "max_abs": float(np.abs(d).max()) if d.size else 0.0,
    }


def tolerance(case: str, name: str, golden: np.ndarray, measured: dict | None) -> dict:
    """What ``compare(obtained, golden)`` may reach for image ``name`` of ``case``.

    ``measured``: the largest differences found between CPU targets (cross_target.json), or
    None when the image was not measured (then only the floors apply).
    """
    m = measured or {"rel_l2": 0.0, "flips": 0, "nonfinite": 0, "max_abs": 0.0}
    if (case, name) in ZERO_BY_CONSTRUCTION:
        return {"kind": "zero", "max_abs": ZERO_ABS}
    nonfinite = max(int(np.ceil(SAFETY * m["nonfinite"])), FLOOR_FLIPS if np.any(~np.isfinite(golden)) else 0)
    if is_discrete(golden):
        return {"kind": "discrete", "flips": max(int(np.ceil(SAFETY * m["flips"])), FLOOR_FLIPS), "nonfinite": nonfinite}
    return {"kind": "continuous", "rel_l2": max(SAFETY * m["rel_l2"], FLOOR_REL_L2), "nonfinite": nonfinite}


def within(diff: dict, tol: dict, obtained: np.ndarray) -> str | None:
    """None if ``diff`` (from :func:`compare`) is within ``tol``, else why not."""
    if tol["kind"] == "zero":
        worst = float(np.nanmax(np.abs(np.asarray(obtained, np.float64)))) if np.size(obtained) else 0.0
        return None if worst <= tol["max_abs"] else f"max |value| {worst:.3g} > {tol['max_abs']:g} (zero by construction)"
    if diff["nonfinite"] > tol["nonfinite"]:
        return f"{diff['nonfinite']} samples finite in one image only > {tol['nonfinite']}"
    if tol["kind"] == "discrete":
        return None if diff["flips"] <= tol["flips"] else f"{diff['flips']} samples differ > {tol['flips']}"
    return None if diff["rel_l2"] <= tol["rel_l2"] else f"relative L2 error {diff['rel_l2']:.3g} > {tol['rel_l2']:.3g}"
