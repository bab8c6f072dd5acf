"""Shared test options and fixtures.

``--regen-golden`` rewrites the golden images of tests/golden/ from the current code, recording
on which machine and CPU target they were made, and every golden test still fails so that the
change is reviewed (``git diff --stat tests/golden``) before it is committed; then
``python scripts/golden_spread.py`` measures how much each image differs between CPU targets,
which sets its tolerance.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from golden_cases import (
    SPREAD_FILE,
    compare,
    count_differences,
    stored_inputs,
    tolerance,
    within,
)

from mbcapture.errors import EnvironmentProblem
from mbcapture.render import llvm
from mbcapture.sensor.cfa import BAYER_PATTERNS, to_mosaic

GOLDEN_DIR = Path(__file__).resolve().parent / "golden"
FAILURE_DIR = Path(__file__).resolve().parents[1] / "out" / "golden-failures"
#: Key of the JSON metadata (machine, target, versions, date) inside each golden .npz.
META_KEY = "__meta__"


_OWN_CACHE: str | None = None


def pytest_configure(config):
    """Renders are cached in a folder of this test session (shared by xdist workers, which inherit
    the environment, and by the second-CPU golden run, whose keys differ by CPU target), never in
    the user's cache; removed at the end."""
    global _OWN_CACHE
    if hasattr(config, "workerinput") or os.environ.get("MBCAPTURE_TEST_CACHE_SET") == "1":
        return
    import tempfile

    _OWN_CACHE = tempfile.mkdtemp(prefix="mbcapture-test-cache-")
    os.environ["MBCAPTURE_CACHE_DIR"] = _OWN_CACHE
    os.environ["MBCAPTURE_TEST_CACHE_SET"] = "1"


def pytest_unconfigure(config):
    if _OWN_CACHE is not None:
        import shutil

        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


def pytest_addoption(parser):
    parser.addoption(
        "--regen-golden",
        action="store_true",
        default=False,
        help="rewrite tests/golden/*.npz from the current code (the golden tests then fail for review)",
    )


def machine_description() -> dict:
    """Where an image was computed: CPU model, Dr.Jit's compile target, library versions, commit."""
    import platform
    import subprocess
    from datetime import datetime, timezone
    from importlib import metadata

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    target = {"cpu": None, "vector_width": None}
    try:
        from mbcapture.render.llvm import llvm_target

        target = llvm_target()
    except Exception as exc:  # no usable Dr.Jit: the numpy-only goldens still record the rest
        target = {"cpu": f"unavailable ({exc})", "vector_width": None}
    try:
        commit = (
            subprocess.run(
                ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=GOLDEN_DIR, timeout=10
            ).stdout.strip()
            or None
        )
    except (OSError, subprocess.SubprocessError):
        commit = None
    versions = {}
    for pkg in ("mitsuba", "drjit", "numpy", "scipy", "opencv-contrib-python-headless", "pymatting"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            versions[pkg] = None
    return {
        "cpu": cpu,
        "llvm_target": target.get("cpu"),
        "vector_width": target.get("vector_width"),
        "emulated": os.environ.get("MBCAPTURE_LLVM_TARGET"),
        "commit": commit,
        "versions": versions,
        "made": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


def read_golden(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """(images, metadata) of a golden .npz."""
    with np.load(path) as data:
        images = {k: data[k] for k in data.files if k != META_KEY}
        meta = json.loads(str(data[META_KEY])) if META_KEY in data.files else {}
    return images, meta


class Golden:
    """Compare named images with ``tests/golden/<case>.npz`` within tolerances derived from the
    differences measured between CPU targets (see tests/golden_cases.py).

    :meth:`check` only compares (the tests that show the checker catches a change use it, so
    ``--regen-golden`` can never store a perturbed image); :meth:`pin` is what the golden tests
    call: it compares, or with ``--regen-golden`` rewrites the golden and fails for review."""

    def __init__(self, regen: bool):
        self.regen = regen
        self._spread: dict | None = None

    def measured(self, case: str, name: str) -> dict | None:
        if self._spread is None:
            self._spread = json.loads(SPREAD_FILE.read_text()) if SPREAD_FILE.exists() else {"cases": {}}
        return self._spread["cases"].get(case, {}).get(name)

    @staticmethod
    def as_stored(images: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Images as a golden keeps them: sensor-stage inputs (``*_in``) in float64, the stage
        goldens replay them exactly; everything else in float32."""
        return {k: np.asarray(v, dtype=np.float64 if k.endswith("_in") else np.float32) for k, v in images.items()}

    def stored_inputs(self, case: str) -> list[np.ndarray] | None:
        """The sensor-stage inputs of ``case``'s golden, to replay (None when regenerating or missing)."""
        path = GOLDEN_DIR / f"{case}.npz"
        if self.regen or not path.exists():
            return None
        return stored_inputs(read_golden(path)[0])

    def pin(self, case: str, images: dict[str, np.ndarray]) -> None:
        """A golden test: with ``--regen-golden`` rewrite the case's golden (and fail for review),
        else :meth:`check`."""
        if not self.regen:
            return self.check(case, images)
        path = GOLDEN_DIR / f"{case}.npz"
        GOLDEN_DIR.mkdir(exist_ok=True)
        meta = np.array(json.dumps(machine_description()))
        np.savez_compressed(path, **self.as_stored(images), **{META_KEY: meta})
        pytest.fail(
            f"--regen-golden: rewrote {path.name}; review the change, run scripts/golden_spread.py "
            "to measure its cross-target differences, and run the tests again without the flag"
        )

    def check(self, case: str, images: dict[str, np.ndarray]) -> None:
        """Compare ``images`` with the golden of ``case``; never writes a golden."""
        path = GOLDEN_DIR / f"{case}.npz"
        images = self.as_stored(images)
        if not path.exists():
            pytest.fail(f"{path} is missing: run pytest --regen-golden to create it, then review it")
        expected, meta = read_golden(path)
        assert sorted(expected) == sorted(images), (
            f"{case}: image names changed: {sorted(expected)} -> {sorted(images)}"
        )
        failures = []
        for name, exp in expected.items():
            got = images[name]
            if got.shape != exp.shape:
                failures.append(f"{name}: shape {got.shape} != golden {exp.shape}")
                continue
            why = within(compare(got, exp), tolerance(case, name, exp, self.measured(case, name)), got)
            if why:
                failures.append(f"{name}: {why}")
                self._write_failure(case, name, exp, got)
        self._fail(case, meta, failures)

    def check_counts(self, case: str, run) -> None:
        """The end-to-end reads of a capture case (``golden_cases.CaseRun``: the sensor on this
        machine's own renders) against the golden's reads, as counts (:func:`golden_cases.count_differences`)."""
        if self.regen:
            return
        expected, meta = read_golden(GOLDEN_DIR / f"{case}.npz")
        failures = []
        for i, (fresh_in, fresh_dn, reads) in enumerate(zip(run.fresh_in, run.fresh_dn, run.reads)):
            golden_in = expected[f"sensor{i}_in"]
            if run.cfas[i] in BAYER_PATTERNS:  # a Bayer sensor: the photosites' inputs
                fresh_in, golden_in = to_mosaic(fresh_in, run.cfas[i]), to_mosaic(golden_in, run.cfas[i])
            elif run.cfas[i] == "mono":  # one photosite per pixel: the channels' mean
                fresh_in, golden_in = fresh_in.mean(-1, keepdims=True), golden_in.mean(-1, keepdims=True)
            why = count_differences(fresh_dn, expected[f"sensor{i}_dn"], fresh_in, golden_in, reads, run.gain_dn_per_e)
            failures += [f"sensor{i}_dn end to end, {w}" for w in why]
        self._fail(case, meta, failures)

    @staticmethod
    def _fail(case: str, meta: dict, failures: list[str]) -> None:
        made = (
            f"golden made on {meta.get('cpu')}, {meta.get('llvm_target')} x{meta.get('vector_width')}" if meta else ""
        )
        assert not failures, (
            f"{case} differs from its golden images ({made}; evidence in {FAILURE_DIR / case}): " + "; ".join(failures)
        )

    @staticmethod
    def _write_failure(case: str, name: str, expected: np.ndarray, obtained: np.ndarray) -> None:
        from mbcapture.output.io import write_exr, write_png

        out = FAILURE_DIR / case
        out.mkdir(parents=True, exist_ok=True)
        with np.errstate(invalid="ignore"):  # inf - inf where both saturated
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


@pytest.fixture(scope="module")
def mitsuba_ready():
    """Skip a rendering test where no usable libLLVM is installed (mbcapture.render.llvm)."""
    try:
        llvm.ensure_llvm()
    except EnvironmentProblem as exc:
        pytest.skip(str(exc))
