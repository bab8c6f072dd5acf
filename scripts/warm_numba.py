"""Compile pymatting's numba functions once, for this CPU and for the test suite's second CPU
target, before the tests run (``make test`` calls it).

Why: pymatting compiles about 30 numba functions when it is imported (explicit signatures,
``cache=True``), 45 s of CPU with an empty cache. The cache lives in the virtual environment, so
a fresh clone starts empty, and every test process that imports pymatting first compiles it
again: both pytest-xdist workers at once, and the golden tests' run under the emulated second
CPU for its own CPU name (numba keys its cache by CPU). Compiling both here, in parallel, does
each once. With a warm cache each import takes about a second.

    .venv/bin/python scripts/warm_numba.py
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mbcapture.portability import emulation_env, second_target  # noqa: E402


def main() -> int:
    envs = {"this CPU": None}
    target = second_target()
    if target is not None:
        envs[f"emulated {target}"] = emulation_env(target)
    t0 = time.perf_counter()
    procs = {name: subprocess.Popen([sys.executable, "-c", "import pymatting"], env=env) for name, env in envs.items()}
    failed = [name for name, p in procs.items() if p.wait() != 0]
    print(f"warm_numba: pymatting compiled for {', '.join(envs)} in {time.perf_counter() - t0:.1f} s")
    if failed:
        print(f"warm_numba: importing pymatting failed for {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
