"""Emulating another CPU (mbcapture.portability, MBCAPTURE_LLVM_TARGET): parsing and choice of targets.
The emulation itself is exercised by tests/test_golden.py::test_goldens_hold_on_a_second_cpu_target."""

from __future__ import annotations

import pytest

from mbcapture.errors import EnvironmentProblem
from mbcapture.portability import (
    EMULATED_TARGETS,
    emulation_env,
    host_vector_width,
    runnable_targets,
    second_target,
)
from mbcapture.render.llvm import CPU_TARGETS, TARGET_ENV_VAR, parse_target


def test_named_and_explicit_targets_parse():
    assert parse_target("haswell") == CPU_TARGETS["haswell"]
    assert parse_target(" skylake-avx512 ")[2] == 16
    assert parse_target("haswell:+avx,+avx2,+fma:8") == ("haswell", "+avx,+avx2,+fma", 8)


@pytest.mark.parametrize("bad", ["pentium", "haswell:+avx2", "haswell:+avx2:7", "haswell::x", ":+fma:8"])
def test_malformed_targets_are_refused_naming_the_variable(bad):
    with pytest.raises(EnvironmentProblem, match=TARGET_ENV_VAR):
        parse_target(bad)


def test_every_emulated_target_sets_every_library_and_names_a_dr_jit_target():
    for name, t in EMULATED_TARGETS.items():
        env = emulation_env(name, base={"KEEP": "1"})
        assert env["KEEP"] == "1"
        assert {
            "MBCAPTURE_LLVM_TARGET",
            "NPY_DISABLE_CPU_FEATURES",
            "OPENBLAS_CORETYPE",
            "NUMBA_CPU_NAME",
            "OPENCV_CPU_DISABLE",
        } <= set(env)
        assert parse_target(env["MBCAPTURE_LLVM_TARGET"])[2] == t["width"]
        assert "+fma" in parse_target(env["MBCAPTURE_LLVM_TARGET"])[1], "Dr.Jit's kernels need FMA"
    with pytest.raises(ValueError, match="emulated target"):
        emulation_env("pentium")


def test_the_second_target_differs_from_the_host_in_vector_width():
    target = second_target()
    if host_vector_width() >= 8:
        assert target in runnable_targets()
        assert EMULATED_TARGETS[target]["width"] != host_vector_width()
