"""Emulate another x86-64 CPU in a child process, to check that results do not depend on it.

Floating-point results differ in their last bits between machines because several libraries
choose their code by the CPU they run on:

* Dr.Jit compiles the renderer's kernels for the host (instruction set, vector width 4/8/16,
  FMA or not): ``MBCAPTURE_LLVM_TARGET`` (:mod:`mbcapture.render.llvm`);
* numpy dispatches its loops to AVX-512 / AVX2 / SSE variants: ``NPY_DISABLE_CPU_FEATURES``;
* OpenBLAS (numpy's and scipy's linear algebra) picks a kernel per CPU: ``OPENBLAS_CORETYPE``;
* numba (pymatting) compiles for the host: ``NUMBA_CPU_NAME``;
* OpenCV dispatches to AVX-512 / AVX2 code: ``OPENCV_CPU_DISABLE``.

:func:`emulation_env` sets all of them for one named target. The variables are read when each
library loads, so they only take effect in a new process. An emulated target must be one the
host can run (an AVX2 target on an AVX-512 host, not the reverse); :func:`second_target`
chooses one that differs from the host in vector width. Targets without FMA cannot be emulated:
Dr.Jit's LLVM backend aborts on them (see :mod:`mbcapture.render.llvm`).
"""

from __future__ import annotations

import os

__all__ = ["EMULATED_TARGETS", "emulation_env", "host_vector_width", "runnable_targets", "second_target"]

# OpenCV 5 names its dispatch levels SSE4.1 ... AVX2, AVX512-SKX (cv2.getCPUFeaturesLine(); a '?'
# after a name there marks it disabled)
_OPENCV_AVX512 = "AVX512-SKX"

#: Named targets: Dr.Jit vector width and the environment of each library.
EMULATED_TARGETS: dict[str, dict] = {
    "haswell": {  # AVX2 + FMA, vector width 8 (most x86-64 machines of 2013-2020, AMD Zen 1-3)
        "width": 8,
        "env": {
            "MBCAPTURE_LLVM_TARGET": "haswell",
            "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
            "OPENBLAS_CORETYPE": "Haswell",
            "NUMBA_CPU_NAME": "haswell",
            "OPENCV_CPU_DISABLE": _OPENCV_AVX512,
        },
    },
    "haswell-w4": {  # the same instructions on 4-wide vectors: another width on any AVX2 host
        "width": 4,
        "env": {
            "MBCAPTURE_LLVM_TARGET": "haswell-w4",
            "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
            "OPENBLAS_CORETYPE": "Haswell",
            "NUMBA_CPU_NAME": "haswell",
            "OPENCV_CPU_DISABLE": _OPENCV_AVX512,
        },
    },
    "skylake-avx512": {  # AVX-512, vector width 16 (Intel Xeon since 2017)
        "width": 16,
        "needs_avx512": True,
        "env": {
            "MBCAPTURE_LLVM_TARGET": "skylake-avx512",
            "NPY_DISABLE_CPU_FEATURES": "AVX512_ICL AVX512_SPR",
            "OPENBLAS_CORETYPE": "SkylakeX",
            "NUMBA_CPU_NAME": "skylake-avx512",
            "OPENCV_CPU_DISABLE": "",  # OpenCV's top dispatch level is AVX512-SKX itself
        },
    },
}


def _host_flags() -> set[str]:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def host_vector_width() -> int:
    """Dr.Jit's vector width on this host, from the CPU flags: 16 (AVX-512), 8 (AVX2), else 4."""
    flags = _host_flags()
    if {"avx512f", "avx512vl", "avx512bw", "avx512dq"} <= flags:
        return 16
    if {"avx2", "fma"} <= flags:
        return 8
    return 4


def runnable_targets() -> list[str]:
    """The emulated targets this host can execute."""
    flags, width = _host_flags(), host_vector_width()
    out = []
    for name, t in EMULATED_TARGETS.items():
        if t.get("needs_avx512") and width < 16:
            continue
        if not {"avx2", "fma"} <= flags:  # Dr.Jit's LLVM kernels need FMA
            continue
        out.append(name)
    return out


def second_target() -> str | None:
    """A runnable target whose vector width differs from the host's (haswell on an AVX-512 host,
    haswell-w4 on an AVX2 one), or None when there is none (a host without AVX2 and FMA)."""
    width = host_vector_width()
    for name in ("haswell", "haswell-w4"):
        if name in runnable_targets() and EMULATED_TARGETS[name]["width"] != width:
            return name
    return None


def emulation_env(target: str, base: dict[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: ``os.environ``) with every library set to compile or
    dispatch for ``target``."""
    if target not in EMULATED_TARGETS:
        raise ValueError(f"emulated target {target!r}: expected one of {sorted(EMULATED_TARGETS)}")
    env = dict(os.environ if base is None else base)
    env.update(EMULATED_TARGETS[target]["env"])
    return env
