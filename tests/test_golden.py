"""Regression images: every protocol and application at tiny size, and the pure-numpy sensor and
HDR stages, against the golden images in tests/golden/ (tests/golden_cases.py defines the cases).

Each stage is pinned on its own stored input, and a count is compared as a count:

* render + accumulate: each sensor stage's input, the noise-free expected electrons
  ``sensor{i}_in`` (float64), within SAFETY x the difference measured between CPU targets
  (tests/golden/cross_target.json, written by scripts/golden_spread.py);
* the sensor: run on the golden's *stored* input (:func:`mbcapture.sensor.sensor_stage_hook`), its
  reads ``sensor{i}_dn`` must equal the golden's exactly;
* the reconstruction: computed from those reads, within the measured difference;
* end to end (the sensor on this machine's own renders): each read may differ from the golden
  by one count in as many samples as the inputs' differences make likely (Poisson density x
  difference, golden_cases.count_differences), and by more in none.

The goldens must hold on any x86-64 machine, so this file also runs itself again in a child
process that emulates a second CPU (another vector width for Dr.Jit, numpy, OpenBLAS, numba and
OpenCV: mbcapture.portability); the child proves which target it compiled for, and the parent
compares the child's images with its own.

A change that alters an image fails here; on failure the expected, obtained and difference
images are written to out/golden-failures/<case>/. After an intended change:
``pytest tests/test_golden.py --regen-golden`` (fails once, for review), then
``python scripts/golden_spread.py``, then ``python scripts/golden_spread.py --carry-over OLD`` with
OLD the committed cross_target.json (``git show HEAD:tests/golden/cross_target.json``), which keeps
the other hosts' measurements, and commit both.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import conftest
import numpy as np
import pytest
from golden_cases import (
    CAPTURE_CASES,
    HDR_METHODS,
    ROOT,
    SPREAD_FILE,
    compare,
    count_differences,
    hdr_images,
    run_capture_case,
    sensor_images,
    tolerance,
    within,
)
from script_modules import load_script

from mbcapture.portability import (
    EMULATED_TARGETS,
    emulation_env,
    host_vector_width,
    second_target,
)

#: Set in the child process that re-runs the golden tests on an emulated CPU.
NESTED_ENV = "MBCAPTURE_GOLDEN_NESTED"
#: A folder where that child leaves its images and the target it compiled for, for the parent.
DUMP_ENV = "MBCAPTURE_GOLDEN_DUMP"


def _dump(name: str, images: dict[str, np.ndarray]) -> None:
    folder = os.environ.get(DUMP_ENV)
    if folder:
        np.savez(Path(folder) / f"{name}.npz", **conftest.Golden.as_stored(images))


@pytest.mark.golden
@pytest.mark.render
@pytest.mark.parametrize("case,config,overrides", CAPTURE_CASES, ids=[c[0] for c in CAPTURE_CASES])
def test_capture_matches_golden(golden, case, config, overrides):
    run = run_capture_case(config, overrides, stored=golden.stored_inputs(case))
    _dump(case, run.images)
    golden.pin(case, run.images)
    golden.check_counts(case, run)


@pytest.mark.golden
def test_sensor_reads_match_golden(golden):
    golden.pin("sensor_reads", sensor_images())


@pytest.mark.golden
@pytest.mark.parametrize("method", HDR_METHODS)
def test_hdr_merge_matches_golden(golden, method):
    golden.pin(f"hdr_{method}", hdr_images(method))


@pytest.mark.golden
@pytest.mark.render
def test_this_process_compiles_for_the_target_it_was_given():
    """Dr.Jit's kernels and numpy's loops are those of MBCAPTURE_LLVM_TARGET when it is set (the
    second-target child), else of this host: the emulation proves it took effect."""
    from mbcapture.render import ensure_llvm
    from mbcapture.render.llvm import (
        TARGET_ENV_VAR,
        apply_target_from_env,
        llvm_target,
        parse_target,
    )

    ensure_llvm()
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    apply_target_from_env()
    got = llvm_target()
    features = np._core._multiarray_umath.__cpu_features__
    spec = os.environ.get(TARGET_ENV_VAR)
    if spec:
        cpu, _, width = parse_target(spec)
        assert (got["cpu"], got["vector_width"]) == (cpu, width), f"asked for {spec}, Dr.Jit compiles for {got}"
        if width < 16:
            assert not features.get("X86_V4", False), "numpy still dispatches to AVX-512 loops"
    else:
        assert got["vector_width"] == host_vector_width(), got
    folder = os.environ.get(DUMP_ENV)
    if folder:
        (Path(folder) / "target.json").write_text(json.dumps({**got, "numpy_x86_v4": bool(features.get("X86_V4"))}))


def test_every_golden_image_has_a_measured_cross_target_spread():
    """Tolerances come from measurements: a golden image nobody measured across CPUs would only
    get the floors. Regenerated goldens need scripts/golden_spread.py run again, and the file names
    the hosts the spreads were measured on."""
    spread = json.loads(SPREAD_FILE.read_text())
    assert len(spread["targets"]) >= 3, "measure at least three CPU targets"
    assert spread["hosts"] and all(h.get("cpu") and h.get("targets") for h in spread["hosts"])
    for path in sorted(conftest.GOLDEN_DIR.glob("*.npz")):
        images, meta = conftest.read_golden(path)
        assert meta.get("cpu") and meta.get("llvm_target"), f"{path.name}: no record of the machine that made it"
        measured = spread["cases"].get(path.stem, {})
        missing = sorted(set(images) - set(measured))
        assert not missing, f"{path.name}: no measured spread for {missing}: run python scripts/golden_spread.py"
        assert spread["golden_made"][path.stem] == meta["made"], (
            f"{path.name} was regenerated after its spread was measured: run python scripts/golden_spread.py"
        )


def _golden_spread():
    """scripts/golden_spread.py as a module (scripts are not a package)."""
    return load_script("golden_spread")


def test_spreads_from_another_host_keep_the_larger_difference_and_name_the_host():
    """scripts/golden_spread.py's merge: each image at the larger difference of the two files; a host is
    its CPU and its native target (two virtual Xeons of one name were a Rocket Lake and a Sapphire
    Rapids), so another target under the same name is kept and the same one is replaced."""
    gs = _golden_spread()
    diff = {"rel_l2": 1e-5, "flips": 2, "nonfinite": 0, "nonfinite_kind": 0, "max_abs": 1.0}
    xeon = "Intel(R) Xeon(R) Processor"
    doc = {
        "hosts": [{"cpu": xeon, "native_target": "sapphirerapids 16", "targets": ["native", "haswell"]}],
        "targets": {"native": "sapphirerapids 16"},
        "cases": {"a": {"img": dict(diff)}},
    }
    old = {
        "hosts": [
            {"cpu": xeon, "native_target": "rocketlake 16", "targets": ["native"]},
            {"cpu": xeon, "native_target": "sapphirerapids 16", "targets": ["native"]},
        ],
        "targets": {"haswell": "haswell 8"},
        "cases": {"a": {"img": {**diff, "rel_l2": 3e-5, "flips": 1}}, "b": {"img": dict(diff)}},
    }
    gs.merge(doc, old, ["a", "b"])
    assert doc["cases"]["a"]["img"]["rel_l2"] == 3e-5 and doc["cases"]["a"]["img"]["flips"] == 2
    assert [h["native_target"] for h in doc["hosts"]] == ["sapphirerapids 16", "rocketlake 16"]
    assert doc["targets"] == {"haswell": "haswell 8", "native": "sapphirerapids 16"}


def test_a_partial_run_keeps_each_hosts_record_of_the_other_cases():
    """Regenerated goldens of some cases, measured again on this host only: this host's earlier record of the
    other cases stays, and another host's record of the regenerated ones says it was carried over from
    their earlier goldens (its spreads kept), while its record of the others stays as it was."""
    gs = _golden_spread()
    diff = {"rel_l2": 1e-5, "flips": 2, "nonfinite": 0, "nonfinite_kind": 0, "max_abs": 1.0}
    amd, xeon = ("AMD EPYC", "znver5 16"), ("Intel(R) Xeon(R) Processor", "sapphirerapids 16")
    host = lambda cpu, **kw: {"cpu": cpu[0], "native_target": cpu[1], "targets": ["native"], **kw}  # noqa: E731
    committed = {
        "hosts": [host(amd, measured="then"), host(xeon, measured="then")],
        "targets": {},
        "golden_made": {"a": "old", "b": "old"},
        "cases": {"a": {"img": {**diff, "rel_l2": 3e-5}}, "b": {"img": dict(diff)}},
    }
    # the partial run of case a (its golden regenerated) on the AMD host, as main() builds it
    doc = {
        "hosts": [host(amd, measured="now", cases=["a"])],
        "targets": {},
        "golden_made": {"a": "new", "b": "old"},
        "cases": {"a": {"img": dict(diff)}, "b": dict(committed["cases"]["b"])},
    }
    gs.merge(doc, committed, ["b"])  # main(): the cases whose goldens did not change
    gs.merge(doc, committed, ["a", "b"], carried=["a"])  # --carry-over the committed file
    records = {
        (h["cpu"], h["measured"], tuple(h.get("cases", ())), tuple(h.get("carried_over", {}).get("cases", ())))
        for h in doc["hosts"]
    }
    assert records == {
        ("AMD EPYC", "now", ("a",), ()),
        ("AMD EPYC", "then", ("b",), ()),
        (xeon[0], "then", ("b",), ()),
        (xeon[0], "then", ("a",), ("a",)),
    }, records
    assert doc["cases"]["a"]["img"]["rel_l2"] == 3e-5  # the Xeon's spread of the earlier golden kept


@pytest.mark.slow
@pytest.mark.render
@pytest.mark.skipif(os.environ.get(NESTED_ENV) == "1", reason="already the second-target run")
def test_goldens_hold_on_a_second_cpu_target(tmp_path, golden):
    """The same golden tests, in a child process compiled and dispatched for another CPU. The child
    shows which target it compiled for, and its images are compared with this process's own."""
    target = second_target()
    if target is None:
        pytest.skip("no second x86-64 target this host can run")
    env = emulation_env(target)
    env[NESTED_ENV] = "1"
    env[DUMP_ENV] = str(tmp_path)
    env.pop("PYTEST_XDIST_WORKER", None)
    cmd = [
        sys.executable,
        "-m",
        "pytest",
        "-q",
        "-p",
        "no:cacheprovider",
        "-p",
        "no:xdist",
        str(ROOT / "tests" / "test_golden.py"),
        "-m",
        "golden",
    ]
    proc = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, f"golden tests fail on emulated {target}:\n{proc.stdout[-6000:]}{proc.stderr[-2000:]}"
    summary = proc.stdout.strip().splitlines()[-1]
    assert " passed" in summary and "skipped" not in summary and "deselected" in summary, summary

    child = json.loads((tmp_path / "target.json").read_text())
    assert child["vector_width"] == EMULATED_TARGETS[target]["width"] != host_vector_width(), child
    # the parent's own run of a case against the child's: the stage inputs within the tolerance,
    # the reads on the stored input identical
    case, config, overrides = CAPTURE_CASES[0]
    mine = conftest.Golden.as_stored(run_capture_case(config, overrides, stored=golden.stored_inputs(case)).images)
    with np.load(tmp_path / f"{case}.npz") as data:
        theirs = {k: data[k] for k in data.files}
    assert sorted(mine) == sorted(theirs)
    for name, img in theirs.items():
        why = within(compare(img, mine[name]), tolerance(case, name, mine[name], golden.measured(case, name)), img)
        assert why is None, f"{case} {name}: the emulated {target} child and this process differ: {why}"


# --------------------------------------------------------------------------- the checker itself


def test_golden_check_fails_on_a_changed_image_and_writes_the_evidence(tmp_path, monkeypatch):
    monkeypatch.setattr(conftest, "GOLDEN_DIR", tmp_path / "golden")
    monkeypatch.setattr(conftest, "FAILURE_DIR", tmp_path / "failures")
    img = np.random.default_rng(0).random((6, 8, 3))
    with pytest.raises(pytest.fail.Exception, match="rewrote"):
        conftest.Golden(regen=True).pin("case", {"img": img})
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


def test_regenerating_never_writes_a_perturbed_image(tmp_path, monkeypatch):
    """With --regen-golden, only the golden tests' pin() writes; the checks that show a change is
    caught (check()) fail as usual and leave the golden as it was."""
    monkeypatch.setattr(conftest, "GOLDEN_DIR", tmp_path / "golden")
    monkeypatch.setattr(conftest, "FAILURE_DIR", tmp_path / "failures")
    img = np.random.default_rng(1).random((6, 8, 3))
    regen = conftest.Golden(regen=True)
    with pytest.raises(pytest.fail.Exception, match="rewrote"):
        regen.pin("case", {"img": img})
    before = (tmp_path / "golden" / "case.npz").read_bytes()
    with pytest.raises(AssertionError, match="relative L2 error"):
        regen.check("case", {"img": img * 1.01})
    assert (tmp_path / "golden" / "case.npz").read_bytes() == before
    assert regen.stored_inputs("case") is None  # a regenerating run renders afresh, replays nothing


@pytest.fixture(scope="module")
def photon_efficient_run():
    case, config, overrides = CAPTURE_CASES[0]
    return run_capture_case(config, overrides, stored=conftest.Golden(regen=False).stored_inputs(case))


@pytest.mark.render
def test_goldens_catch_a_one_percent_radiance_change(golden, photon_efficient_run):
    """1 % more light (quantum efficiency x 1.01): the sensor's input and the HDR radiance move."""
    case, config, overrides = CAPTURE_CASES[0]
    qe = np.array(photon_efficient_run.result.config.sensor.quantum_efficiency) * 1.01
    run = run_capture_case(
        config, overrides, [f"sensor.quantum_efficiency={qe.tolist()}"], stored=golden.stored_inputs(case)
    )
    with pytest.raises(AssertionError) as err:
        golden.check(case, run.images)
    for name in ("sensor0_in", "radiance"):
        assert f"{name}: relative L2" in str(err.value)


@pytest.mark.render
def test_goldens_catch_a_swapped_bucket(golden, photon_efficient_run):
    case = CAPTURE_CASES[0][0]
    images = dict(photon_efficient_run.images)
    golden.check(case, images)  # unchanged: passes
    images["sensor0_in"] = images["sensor0_in"][[1, 0, 2, 3]]
    with pytest.raises(AssertionError, match="sensor0_in: relative L2"):
        golden.check(case, images)


@pytest.mark.render
def test_counts_allow_a_one_count_flip_that_the_inputs_explain_and_nothing_more(golden, photon_efficient_run):
    """The situation of an Intel AVX-512 host running the emulated haswell child: its renders differ
    from the golden's in the last bits, and one read moves by one count in one sample. That is
    accepted; a 2-count change in one sample, or one-count flips that the inputs do not explain, are not."""
    case = CAPTURE_CASES[0][0]
    expected, _ = conftest.read_golden(conftest.GOLDEN_DIR / f"{case}.npz")
    g_in, g_dn = expected["sensor0_in"], expected["sensor0_dn"].astype(np.float64)
    reads, gain = photon_efficient_run.reads[0], photon_efficient_run.gain_dn_per_e
    # another CPU: expected electrons off by the largest relative difference measured between targets
    rel = golden.measured(case, "sensor0_in")["max_abs"] / np.abs(g_in).max()
    other_in = g_in * (1 + rel * np.random.default_rng(3).uniform(-1, 1, g_in.shape))
    flipped = g_dn.copy()
    flipped[0, 5, 7, 1] += 1
    assert count_differences(flipped, g_dn, other_in, g_in, reads, gain) == []
    two = g_dn.copy()
    two[0, 5, 7, 1] += 2
    assert "more than their inputs allow" in count_differences(two, g_dn, other_in, g_in, reads, gain)[0]
    # the same flip with inputs equal to the golden's: nothing explains it
    assert "at most 0 DN" in count_differences(flipped, g_dn, g_in, g_in, reads, gain)[0]
    # many one-count flips exceed what the inputs' differences make likely
    many = g_dn.copy()
    many[0, :, :, 1] += 1
    assert "allowed" in count_differences(many, g_dn, other_in, g_in, reads, gain)[0]


@pytest.mark.render
def test_an_inf_turned_nan_fails(golden, photon_efficient_run):
    """sigma is inf where every read saturated: a NaN there is another answer, not a rounding."""
    case = CAPTURE_CASES[0][0]
    images = dict(photon_efficient_run.images)
    sigma = np.array(images["sigma_temporal"], copy=True)
    assert np.isinf(sigma).any(), "the lamp saturates every read somewhere"
    sigma[tuple(np.argwhere(np.isinf(sigma))[0])] = np.nan
    with pytest.raises(AssertionError, match="sigma_temporal: 1 non-finite samples changed kind"):
        golden.check(case, {k: v for k, v in images.items() if k != "sigma"} | {"sigma_temporal": sigma})


@pytest.mark.parametrize("change", ["numpy_poisson", "read_noise_x1.5", "no_transfer_loss"])
def test_goldens_catch_a_changed_noise_model(golden, monkeypatch, change):
    """The sensor golden pins the noise draws, not only their statistics."""
    import golden_cases

    import mbcapture.sensor.readout as readout

    if change == "numpy_poisson":  # the same law, drawn by numpy's rejection sampler
        monkeypatch.setattr(
            readout,
            "poisson_quantile_memo",
            lambda u, lam, u_key=None: np.random.default_rng(0).poisson(lam).astype(np.float64),
        )
    else:
        base = golden_cases.sensor_config()
        update = (
            {"read_noise_e": base.read_noise_e * 1.5} if change == "read_noise_x1.5" else {"transfer_inefficiency": 0.0}
        )
        monkeypatch.setattr(golden_cases, "sensor_config", lambda: base.model_copy(update=update))
    with pytest.raises(AssertionError, match="reads_dn"):
        golden.check("sensor_reads", sensor_images())
