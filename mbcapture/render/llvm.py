"""Find a usable system libLLVM (>= 16) for Dr.Jit's LLVM backend, before Dr.Jit loads one.

With LLVM 15 the first render aborts the whole process inside LLVM ("Cannot select:
fminimum"): a crash, not a Python exception. So the library is chosen and checked here, and
:func:`ensure_llvm` must run before ``drjit`` or ``mitsuba`` is imported.

Rules
-----
* ``DRJIT_LIBLLVM_PATH`` set: its version is parsed from the file name (following symlinks
  when the name carries none); below 16, or unknown, is refused.
* unset: the newest ``libLLVM-*.so*`` / ``libLLVM.so.N*`` >= 16 found in :data:`SEARCH_DIRS`
  or in ``ldconfig -p`` is put into ``DRJIT_LIBLLVM_PATH``.
* after import, ``drjit.detail.llvm_version()`` is checked too (Dr.Jit may have been imported
  by someone else first).

Every refusal is an :class:`~mbcapture.errors.EnvironmentProblem` with one line naming the fix.

CPU target
----------
Dr.Jit compiles its LLVM kernels for the host CPU (instruction set and vector width), so the
same render differs in the last bits between machines. ``MBCAPTURE_LLVM_TARGET`` makes it
compile for another x86-64 target instead, to reproduce another machine's renders (the golden
tests use it to prove that they pass on other CPUs): a name from :data:`CPU_TARGETS`, or
``cpu:features:width`` in LLVM's terms (``haswell:+avx,+avx2,+fma:8``; FMA is required). It must be set before
the process renders anything; the target must run on the host (an AVX2 target on an AVX-512
host, not the reverse). :func:`llvm_target` reports what kernels are compiled for.
"""

from __future__ import annotations

import glob
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Iterable, Sequence

from ..errors import EnvironmentProblem

#: Environment variable naming the CPU target Dr.Jit compiles for (see the module doc).
TARGET_ENV_VAR = "MBCAPTURE_LLVM_TARGET"
#: Named x86-64 targets: (LLVM cpu name, LLVM feature string, Dr.Jit vector width).
_BASE = "+64bit,+cmov,+cx8,+cx16,+fxsr,+mmx,+sse,+sse2,+sse3,+ssse3,+sse4.1,+sse4.2,+popcnt,+xsave"
_AVX2 = _BASE + ",+avx,+avx2,+fma,+f16c,+bmi,+bmi2,+lzcnt,+movbe"
# LLVM >= 18 also wants +evex512 for 512-bit vectors (without it: "Do not know how to split")
_AVX512 = _AVX2 + ",+avx512f,+avx512dq,+avx512bw,+avx512vl,+avx512cd,+evex512"
CPU_TARGETS: dict[str, tuple[str, str, int]] = {
    "haswell": ("haswell", _AVX2, 8),
    # AVX2 instructions on 4-wide vectors: not Dr.Jit's choice on any machine, but another
    # vector width that every AVX2 host can run (its second target when it is not AVX-512)
    "haswell-w4": ("haswell", _AVX2, 4),
    "skylake-avx512": ("skylake-avx512", _AVX512, 16),
}
# Targets without FMA (x86-64-v2, sandybridge) cannot be used: LLVM lowers Dr.Jit's fma intrinsic
# to a library call there and Dr.Jit aborts ("a global offset table was generated").
# Dr.Jit's C++ entry points (drjit-core 1.x, not bound in Python): mangled names
_SYM_SET_TARGET = "_Z19jit_llvm_set_targetPKcS0_j"
_SYM_CPU = "_Z19jit_llvm_target_cpuv"
_SYM_FEATURES = "_Z24jit_llvm_target_featuresv"
_SYM_WIDTH = "_Z21jit_llvm_vector_widthv"

#: Oldest LLVM major version that renders without crashing.
MIN_LLVM_MAJOR = 16
ENV_VAR = "DRJIT_LIBLLVM_PATH"
FIX = f"install a newer LLVM ('apt-get install libllvm19') or set {ENV_VAR} to a libLLVM >= {MIN_LLVM_MAJOR}"
#: Directories searched (glob patterns allowed), in addition to ``ldconfig -p``.
SEARCH_DIRS: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu",
    "/lib/x86_64-linux-gnu",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/local/lib",
)

# libLLVM-19.so, libLLVM-14.0.6.so.1, libLLVM-15.so.1, libLLVM.so.19.1, libLLVM.so.1 (not a
# major version: the SONAME suffix of some builds is the LLVM major, of others not; accept
# only >= 2-digit or dotted forms after 'libLLVM.so.').
_NAME_DASH = re.compile(r"^libLLVM-(\d+)(?:\.\d+)*(?:git)?\.so(?:\.\d+)*$")
_NAME_DOT = re.compile(r"^libLLVM\.so\.(\d+)(?:\.\d+)+$|^libLLVM\.so\.(\d{2,})$")


def version_from_name(name: str) -> int | None:
    """LLVM major version encoded in a library file name, or None (e.g. ``libLLVM.so``)."""
    m = _NAME_DASH.match(name)
    if m:
        return int(m.group(1))
    m = _NAME_DOT.match(name)
    if m:
        return int(m.group(1) or m.group(2))
    return None


def library_version(path: str | os.PathLike) -> int | None:
    """Major version of a libLLVM file: from its name, else from the names along its symlinks."""
    p = Path(path)
    for _ in range(16):  # follow a symlink chain one hop at a time (names carry the version)
        v = version_from_name(p.name)
        if v is not None:
            return v
        if not p.is_symlink():
            return None
        target = Path(os.readlink(p))
        p = target if target.is_absolute() else p.parent / target
    return None


def _ldconfig_paths() -> list[str]:
    try:
        out = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=10, check=False).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.split("=>", 1)[1].strip() for line in out.splitlines() if "libLLVM" in line and "=>" in line]


def candidates(dirs: Iterable[str] = SEARCH_DIRS, use_ldconfig: bool = True) -> list[tuple[int, str]]:
    """All (major version, path) of existing libLLVM shared libraries found, newest first."""
    found: dict[str, int] = {}
    paths: list[str] = []
    for pattern in dirs:
        for d in sorted(glob.glob(pattern)):
            paths += glob.glob(os.path.join(d, "libLLVM*.so*"))
    if use_ldconfig:
        paths += _ldconfig_paths()
    for p in paths:
        if not os.path.isfile(p):  # also drops dangling symlinks
            continue
        v = library_version(p)
        if v is not None:
            found.setdefault(p, v)
    return sorted(((v, p) for p, v in found.items()), key=lambda vp: (-vp[0], vp[1]))


def find_llvm(dirs: Sequence[str] = SEARCH_DIRS, use_ldconfig: bool = True) -> tuple[int, str]:
    """Newest libLLVM >= :data:`MIN_LLVM_MAJOR`: (major, path). Raises EnvironmentProblem."""
    cands = candidates(dirs, use_ldconfig)
    good = [vp for vp in cands if vp[0] >= MIN_LLVM_MAJOR]
    if good:
        return good[0]
    if cands:
        have = ", ".join(sorted({str(v) for v, _ in cands}))
        raise EnvironmentProblem(f"only libLLVM {have} found (crashes Mitsuba); {FIX}")
    raise EnvironmentProblem(f"no libLLVM found; {FIX}")


def select_llvm(
    environ: dict | None = None, dirs: Sequence[str] = SEARCH_DIRS, use_ldconfig: bool = True
) -> tuple[int, str]:
    """Choose the library and write it into ``environ[DRJIT_LIBLLVM_PATH]`` (default os.environ).

    Pure file-system logic (no Dr.Jit import), so it can be tested with fake directories.
    """
    env = os.environ if environ is None else environ
    preset = env.get(ENV_VAR)
    if preset:
        if not os.path.isfile(preset):
            raise EnvironmentProblem(f"{ENV_VAR}={preset} does not exist; {FIX}")
        v = library_version(preset)
        if v is None:
            raise EnvironmentProblem(
                f"{ENV_VAR}={preset}: cannot tell its LLVM version from the name; "
                f"point it at a versioned file such as libLLVM-19.so"
            )
        if v < MIN_LLVM_MAJOR:
            raise EnvironmentProblem(f"{ENV_VAR}={preset} is LLVM {v} (crashes Mitsuba); {FIX}")
        return v, preset
    v, path = find_llvm(dirs, use_ldconfig)
    env[ENV_VAR] = path
    return v, path


def ensure_llvm() -> tuple[int, int, int]:
    """Make sure Dr.Jit uses a libLLVM >= 16; returns the loaded version (major, minor, patch).

    Call before the first ``import drjit`` / ``import mitsuba``. If Dr.Jit was already
    imported, only the post-import check applies (the loaded library cannot be changed).
    """
    if "drjit" not in sys.modules:
        select_llvm()
    import drjit as dr  # noqa: PLC0415  (deliberately late: after the env var is set)

    try:
        version = tuple(int(x) for x in dr.detail.llvm_version())
    except Exception as exc:  # Dr.Jit raises when it could not load any libLLVM
        raise EnvironmentProblem(f"Dr.Jit could not load libLLVM ({exc}); {FIX}") from exc
    if version[0] < MIN_LLVM_MAJOR:
        raise EnvironmentProblem(f"Dr.Jit loaded LLVM {'.'.join(map(str, version))} (crashes Mitsuba); {FIX}")
    return version  # type: ignore[return-value]


def parse_target(spec: str) -> tuple[str, str, int]:
    """A :data:`TARGET_ENV_VAR` value as (cpu, features, vector width); EnvironmentProblem if malformed."""
    spec = spec.strip()
    if spec in CPU_TARGETS:
        return CPU_TARGETS[spec]
    parts = spec.split(":")
    if len(parts) != 3 or not parts[0] or not parts[2].isdigit() or int(parts[2]) not in (1, 4, 8, 16):
        raise EnvironmentProblem(
            f"{TARGET_ENV_VAR}={spec!r}: expected one of {sorted(CPU_TARGETS)} or cpu:features:width "
            "with width 1, 4, 8 or 16 (e.g. haswell:+avx,+avx2,+fma:8)"
        )
    return parts[0], parts[1], int(parts[2])


def _core_lib():
    import ctypes

    import drjit as dr

    return ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))


def llvm_target() -> dict:
    """What Dr.Jit's LLVM backend compiles for: {"cpu", "features", "vector_width"}."""
    import ctypes

    lib = _core_lib()
    try:
        cpu, features, width = getattr(lib, _SYM_CPU), getattr(lib, _SYM_FEATURES), getattr(lib, _SYM_WIDTH)
    except AttributeError:
        return {"cpu": None, "features": None, "vector_width": None}
    cpu.restype = features.restype = ctypes.c_char_p
    width.restype = ctypes.c_uint32
    return {"cpu": (cpu() or b"").decode(), "features": (features() or b"").decode(), "vector_width": int(width())}


_applied_target: tuple[str, str, int] | None = None


def apply_target_from_env() -> tuple[str, str, int] | None:
    """Compile for :data:`TARGET_ENV_VAR`'s target, if set (once per process, before the first
    kernel: call it right after ``mi.set_variant`` of an llvm variant). Returns the target or None."""
    global _applied_target
    spec = os.environ.get(TARGET_ENV_VAR)
    if not spec:
        return None
    target = parse_target(spec)
    if _applied_target is not None:
        if _applied_target != target:
            raise EnvironmentProblem(
                f"{TARGET_ENV_VAR} changed within one process ({_applied_target[0]} -> {target[0]})"
            )
        return target
    import ctypes

    try:
        fn = getattr(_core_lib(), _SYM_SET_TARGET)
    except AttributeError:
        raise EnvironmentProblem(f"{TARGET_ENV_VAR}: this Dr.Jit has no jit_llvm_set_target (drjit 1.5 has)") from None
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    fn.restype = None
    fn(target[0].encode(), target[1].encode(), target[2])
    _applied_target = target
    return target


def set_render_threads(variant: str, threads: int | None) -> None:
    """Render on ``threads`` of this process's cores (None: Dr.Jit's default, every core). For an LLVM
    ``variant`` the libLLVM is picked first (:func:`ensure_llvm`), as it must be before Mitsuba loads."""
    if not variant.startswith("llvm"):
        return
    ensure_llvm()
    if threads:
        import drjit as dr

        if dr.thread_count() != threads:
            dr.set_thread_count(threads)
