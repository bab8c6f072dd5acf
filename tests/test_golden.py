"""Regression images: every protocol and application at tiny size, and the pure-numpy sensor and
HDR stages, against the golden images in tests/golden/ (tests/golden_cases.py defines the cases).

Tolerances are derived per image from the differences measured between CPU targets
(tests/golden/cross_target.json, written by scripts/golden_spread.py): SAFETY x the largest
measured difference, with floors for float32 storage and for thresholded images; images that
are zero by construction get an absolute bound. The goldens must hold on any x86-64 machine, so
this file also runs itself again in a child process that emulates a second CPU (another vector
width for Dr.Jit, numpy, OpenBLAS, numba and OpenCV: mbcapture.portability).

A change that alters an image fails here; on failure the expected, obtained and difference
images are written to out/golden-failures/<case>/. After an intended change:
``pytest tests/test_golden.py --regen-golden`` (fails once, for review), then
``python scripts/golden_spread.py``, and commit both.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import conftest
from golden_cases import (
    CAPTURE_CASES,
    HDR_METHODS,
    ROOT,
    SPREAD_FILE,
    TINY,
    capture_images,
    hdr_images,
    result_images,
    sensor_images,
)
from mbcapture.portability import emulation_env, second_target

#: Set in the child process that re-runs the golden tests on an emulated CPU.
NESTED_ENV = "MBCAPTURE_GOLDEN_NESTED"


@pytest.mark.golden
@pytest.mark.render
@pytest.mark.parametrize("case,config,overrides", CAPTURE_CASES, ids=[c[0] for c in CAPTURE_CASES])
def test_capture_matches_golden(golden, case, config, overrides):
    golden.check(case, capture_images(config, overrides))


@pytest.mark.golden
def test_sensor_reads_match_golden(golden):
    golden.check("sensor_reads", sensor_images())


@pytest.mark.golden
@pytest.mark.parametrize("method", HDR_METHODS)
def test_hdr_merge_matches_golden(golden, method):
    golden.check(f"hdr_{method}", hdr_images(method))


def test_every_golden_image_has_a_measured_cross_target_spread():
    """Tolerances come from measurements: a golden image nobody measured across CPUs would only
    get the floors. Regenerated goldens need scripts/golden_spread.py run again."""
    import json

    spread = json.loads(SPREAD_FILE.read_text())
    assert len(spread["targets"]) >= 3, "measure at least three CPU targets"
    for path in sorted(conftest.GOLDEN_DIR.glob("*.npz")):
        images, meta = conftest.read_golden(path)
        assert meta.get("cpu") and meta.get("llvm_target"), f"{path.name}: no record of the machine that made it"
        measured = spread["cases"].get(path.stem, {})
        missing = sorted(set(images) - set(measured))
        assert not missing, f"{path.name}: no measured spread for {missing}: run python scripts/golden_spread.py"
        assert spread["golden_made"][path.stem] == meta["made"], \
            f"{path.name} was regenerated after its spread was measured: run python scripts/golden_spread.py"


@pytest.mark.render
@pytest.mark.skipif(os.environ.get(NESTED_ENV) == "1", reason="already the second-target run")
def test_goldens_hold_on_a_second_cpu_target():
    """The same golden tests, in a child process compiled and dispatched for another CPU."""
    target = second_target()
    if target is None:
        pytest.skip("no second x86-64 target this host can run")
    env = emulation_env(target)
    env[NESTED_ENV] = "1"
    env.pop("PYTEST_XDIST_WORKER", None)
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
           str(ROOT / "tests" / "test_golden.py"), "-m", "golden"]
    proc = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"golden tests fail on emulated {target}:\n{proc.stdout[-6000:]}{proc.stderr[-2000:]}"
    summary = proc.stdout.strip().splitlines()[-1]
    assert " passed" in summary and "skipped" not in summary and "deselected" in summary, summary


# --------------------------------------------------------------------------- the checker itself


def test_golden_check_fails_on_a_changed_image_and_writes_the_evidence(tmp_path, monkeypatch):
    monkeypatch.setattr(conftest, "GOLDEN_DIR", tmp_path / "golden")
    monkeypatch.setattr(conftest, "FAILURE_DIR", tmp_path / "failures")
    img = np.random.default_rng(0).random((6, 8, 3))
    with pytest.raises(pytest.fail.Exception, match="rewrote"):
        conftest.Golden(regen=True).check("case", {"img": img})
    _, meta = conftest.read_golden(tmp_path / "golden" / "case.npz")
    assert meta["cpu"] and "made" in meta and "vector_width" in meta
    checker = conftest.Golden(regen=False)
    checker.check("case", {"img": img * (1 + 1e-7)})  # below float32 storage precision x 16
    changed = img.copy()
    changed[2, 3] += 0.5
    with pytest.raises(AssertionError, match="relative L2 error"):
        checker.check("case", {"img": changed})
    written = {p.name for p in (tmp_path / "failures" / "case").iterdir()}
    assert {"img_expected.exr", "img_obtained.exr", "img_difference.exr", "img_difference.png"} <= written


@pytest.fixture(scope="module")
def photon_efficient_capture():
    from mbcapture import load_config, run_capture

    case, config, overrides = CAPTURE_CASES[0]
    return run_capture(load_config(ROOT / "configs" / config, [*TINY, *overrides]), progress=False)


@pytest.mark.render
def test_goldens_catch_a_one_percent_radiance_change(golden, photon_efficient_capture):
    """1 % more light (quantum efficiency x 1.01): expected electrons, reads and HDR all move."""
    case, config, overrides = CAPTURE_CASES[0]
    qe = np.array(photon_efficient_capture.config.sensor.quantum_efficiency) * 1.01
    images = capture_images(config, overrides, [f"sensor.quantum_efficiency={qe.tolist()}"])
    with pytest.raises(AssertionError) as err:
        golden.check(case, images)
    for name in ("expected_J1", "reads_dn_J4", "radiance"):
        assert f"{name}: relative L2" in str(err.value)


@pytest.mark.render
def test_goldens_catch_a_swapped_bucket(golden, photon_efficient_capture):
    case = CAPTURE_CASES[0][0]
    images = result_images(photon_efficient_capture)
    golden.check(case, images)  # unchanged: passes
    images["expected_J1"], images["expected_J2"] = images["expected_J2"], images["expected_J1"]
    with pytest.raises(AssertionError, match="expected_J1: relative L2"):
        golden.check(case, images)


@pytest.mark.parametrize("change", ["numpy_poisson", "read_noise_x1.5", "no_transfer_loss"])
def test_goldens_catch_a_changed_noise_model(golden, monkeypatch, change):
    """The sensor golden pins the noise draws, not only their statistics."""
    import golden_cases
    import mbcapture.sensor.readout as readout

    if change == "numpy_poisson":  # the same law, drawn by numpy's rejection sampler
        monkeypatch.setattr(readout, "poisson_quantile_memo",
                            lambda u, lam: np.random.default_rng(0).poisson(lam).astype(np.float64))
    else:
        base = golden_cases.sensor_config()
        update = {"read_noise_e": base.read_noise_e * 1.5} if change == "read_noise_x1.5" else {"transfer_inefficiency": 0.0}
        monkeypatch.setattr(golden_cases, "sensor_config", lambda: base.model_copy(update=update))
    with pytest.raises(AssertionError, match="reads_dn"):
        golden.check("sensor_reads", sensor_images())
