"""Regression images: every protocol and application at tiny size, and the pure-numpy stages,
against the golden images in tests/golden/ (linear float, relative L2, per-image tolerances).

A change that alters an image fails here; on failure the expected, obtained and difference
images are written to out/golden-failures/<case>/. After an intended change:
``pytest tests/test_golden.py --regen-golden`` (fails once, for review), then commit the .npz.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mbcapture.reconstruct.hdr import merge_hdr
from mbcapture.sensor import SensorConfig, simulate_reads

ROOT = Path(__file__).resolve().parents[1]
TINY = ["render.width=32", "render.height=24", "render.spp=2", "render.max_motion_px=2.0"]

# Noise-free images depend on the renderer only: LLVM code generation may reorder float sums
# across CPUs, so allow 1e-4. Noisy images add Poisson and read noise drawn from the seed;
# a tiny change of an expected value can flip a few samples, so allow 2e-3.
TOL_NOISE_FREE, TOL_NOISY = 1e-4, 2e-3

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
]


def _noisy(name: str) -> bool:
    return name.startswith("reads_dn") or name not in ("truth", "moving") and not name.startswith("expected")


@pytest.mark.render
@pytest.mark.parametrize("case,config,overrides", CAPTURE_CASES, ids=[c[0] for c in CAPTURE_CASES])
def test_capture_matches_golden(golden, case, config, overrides):
    from mbcapture import load_config, run_capture

    res = run_capture(load_config(ROOT / "configs" / config, [*TINY, *overrides]), progress=False)
    images = {f"expected_{r.name}": res.reads_expected_e[i] for i, r in enumerate(res.timeline.reads)}
    images |= {f"reads_dn_{r.name}": res.reads_dn[i] for i, r in enumerate(res.timeline.reads)}
    images |= {k: v for k, v in res.images.items() if np.asarray(v).dtype != bool}
    tol = {k: (TOL_NOISY if _noisy(k) else TOL_NOISE_FREE) for k in images}
    golden.check(case, images, tol)


def _synthetic_exposure(shape=(4, 12, 16, 3)) -> np.ndarray:
    """Bucket electrons spanning dark to saturated: a horizontal ramp over 5 decades, 4:2:1:1."""
    ramp = np.geomspace(0.5, 5e4, shape[2])[None, None, :, None] * np.linspace(0.5, 1.0, shape[1])[None, :, None, None]
    ratio = np.array([4.0, 2.0, 1.0, 1.0])[:, None, None, None] / 8
    return np.broadcast_to(ramp * ratio, shape).astype(np.float64) * np.array([1.0, 0.8, 0.6])


def test_sensor_reads_match_golden(golden):
    cfg = SensorConfig()  # default: fixed-pattern noise, dark current, transfer inefficiency on
    out = simulate_reads(_synthetic_exposure(), [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)], cfg,
                         np.random.default_rng(7), storage_s=np.full(4, 8e-3))
    golden.check("sensor_reads", {"reads_dn": out.reads_dn, "expected_e": out.reads_e_expected,
                                  "saturated": out.saturated.astype(np.float32)}, {"reads_dn": 1e-6,
                                  "expected_e": 1e-6, "saturated": 0.0})


@pytest.mark.parametrize("method", ["ramp_fit", "inverse_variance", "debevec"])
def test_hdr_merge_matches_golden(golden, method):
    cfg = SensorConfig()
    out = simulate_reads(_synthetic_exposure(), [(3,), (3, 2), (3, 2, 1), (3, 2, 1, 0)], cfg,
                         np.random.default_rng(8), storage_s=np.full(4, 8e-3))
    res = merge_hdr(out.reads_dn, np.array([1e-3, 2e-3, 4e-3, 8e-3]), cfg, method=method, cumulative=True,
                    saturated=out.saturated)
    golden.check(f"hdr_{method}", {"rate": res.rate_e_per_s, "sigma": res.sigma_e_per_s,
                                   "valid": res.valid.astype(np.float32)}, {"rate": 1e-6, "sigma": 1e-6, "valid": 0.0})


def test_golden_check_fails_on_a_changed_image_and_writes_the_evidence(tmp_path, monkeypatch):
    import conftest

    monkeypatch.setattr(conftest, "GOLDEN_DIR", tmp_path / "golden")
    monkeypatch.setattr(conftest, "FAILURE_DIR", tmp_path / "failures")
    img = np.random.default_rng(0).random((6, 8, 3))
    with pytest.raises(pytest.fail.Exception, match="rewrote"):
        conftest.Golden(regen=True).check("case", {"img": img}, 1e-3)
    checker = conftest.Golden(regen=False)
    checker.check("case", {"img": img * (1 + 1e-5)}, 1e-3)  # within tolerance
    changed = img.copy()
    changed[2, 3] += 0.5
    with pytest.raises(AssertionError, match="relative L2 error"):
        checker.check("case", {"img": changed}, 1e-3)
    written = {p.name for p in (tmp_path / "failures" / "case").iterdir()}
    assert {"img_expected.exr", "img_obtained.exr", "img_difference.exr", "img_difference.png"} <= written
