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

#: Oldest LLVM major version that renders without crashing.
MIN_LLVM_MAJOR = 16
ENV_VAR = "DRJIT_LIBLLVM_PATH"
FIX = (
    f"install a newer LLVM ('apt-get install libllvm19') or set {ENV_VAR} to a "
    f"libLLVM >= {MIN_LLVM_MAJOR}"
)
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
        out = subprocess.run(
            ["ldconfig", "-p"], capture_output=True, text=True, timeout=10, check=False
        ).stdout
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


def select_llvm(environ: dict | None = None, dirs: Sequence[str] = SEARCH_DIRS,
                use_ldconfig: bool = True) -> tuple[int, str]:
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
        raise EnvironmentProblem(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, version))} (crashes Mitsuba); {FIX}"
        )
    return version  # type: ignore[return-value]
