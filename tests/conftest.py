"""Shared test options and fixtures.

``--regen-golden`` rewrites the golden images of tests/golden/ from the current code, and every
golden test still fails so that the change is reviewed (``git diff --stat tests/golden``) before
it is committed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
FAILURE_DIR = Path(__file__).resolve().parents[1] / "out" / "golden-failures"


def pytest_addoption(parser):
    parser.addoption("--regen-golden", action="store_true", default=False,
                     help="rewrite tests/golden/*.npz from the current code (the golden tests then fail for review)")


def relative_l2(obtained: np.ndarray, expected: np.ndarray) -> float:
    """||obtained - expected|| / ||expected|| over the finite samples (float64); 0 for two all-zero
    images; inf when the non-finite samples (e.g. sigma = inf where every read saturated) differ."""
    a, b = np.asarray(obtained, np.float64), np.asarray(expected, np.float64)
    finite = np.isfinite(b)
    if not np.array_equal(finite, np.isfinite(a)) or not np.array_equal(a[~finite], b[~finite], equal_nan=True):
        return float("inf")
    a, b = a[finite], b[finite]
    norm = float(np.linalg.norm(b))
    diff = float(np.linalg.norm(a - b))
    return diff / norm if norm > 0 else diff


class Golden:
    """Compare named float images with ``tests/golden/<case>.npz`` (linear float, relative L2)."""

    def __init__(self, regen: bool):
        self.regen = regen

    def check(self, case: str, images: dict[str, np.ndarray], tolerance: dict[str, float] | float) -> None:
        path = GOLDEN_DIR / f"{case}.npz"
        images = {k: np.asarray(v, dtype=np.float32) for k, v in images.items()}
        if self.regen:
            GOLDEN_DIR.mkdir(exist_ok=True)
            np.savez_compressed(path, **images)
            pytest.fail(f"--regen-golden: rewrote {path.name}; review the change and run the tests again without it")
        if not path.exists():
            pytest.fail(f"{path} is missing: run pytest --regen-golden to create it, then review it")
        with np.load(path) as data:
            expected = {k: data[k] for k in data.files}
        assert sorted(expected) == sorted(images), f"{case}: image names changed: {sorted(expected)} -> {sorted(images)}"
        failures = []
        for name, exp in expected.items():
            got = images[name]
            tol = tolerance if isinstance(tolerance, float) else tolerance[name]
            if got.shape != exp.shape:
                failures.append(f"{name}: shape {got.shape} != golden {exp.shape}")
                continue
            err = relative_l2(got, exp)
            if not np.isfinite(err) or err > tol:
                failures.append(f"{name}: relative L2 error {err:.3g} > {tol:g}")
                self._write_failure(case, name, exp, got)
        assert not failures, f"{case} differs from its golden images ({FAILURE_DIR / case}): " + "; ".join(failures)

    @staticmethod
    def _write_failure(case: str, name: str, expected: np.ndarray, obtained: np.ndarray) -> None:
        from mbcapture.io import write_exr, write_png

        out = FAILURE_DIR / case
        out.mkdir(parents=True, exist_ok=True)
        diff = np.abs(obtained.astype(np.float64) - expected)
        for label, img in (("expected", expected), ("obtained", obtained), ("difference", diff)):
            arr = np.asarray(img, np.float32)
            flat = arr.reshape(arr.shape[0], arr.shape[1], -1) if arr.ndim >= 2 else arr.reshape(1, -1, 1)
            if flat.shape[-1] not in (1, 3):
                flat = flat[..., :1]
            write_exr(out / f"{name}_{label}.exr", {label: flat if flat.shape[-1] == 3 else flat[..., 0]})
            write_png(out / f"{name}_{label}.png", flat)


@pytest.fixture(scope="session")
def golden(request) -> Golden:
    return Golden(request.config.getoption("--regen-golden"))
