"""Where a capture's whole-film arrays live: in memory, or memory-mapped from scratch files on disk.

A tiled capture (``render.tiles``) renders, accumulates and senses its film a tile of rows at a
time, but its results are whole-film arrays: the exposures and their two error estimates (and the
per-group exposures of an application that asks for them), the reads, their truths and their
saturation. At 24 megapixels those alone are about 9 GB (an HDR capture of four buckets). With ``render.spill`` they are made in
files of a scratch folder and mapped into memory (``mmap``): the kernel keeps their pages in the
page cache while memory is free and writes them back and drops them when it is not, so the memory
a run must hold is its working set, not its film. The values are the same bit for bit (the same
float64, float32 and bool arrays, only their storage differs).

Written here because numpy's ``np.memmap`` keeps a named file (and a subclass whose arithmetic
results stay memmaps): a scratch file here is reserved in full first (``posix_fallocate``, so a
full disk is an error before any work, not a SIGBUS while writing), mapped, and unlinked at
once, so nothing is left in the folder after the run, even a killed one; the array is a plain
ndarray over the mapping, which the kernel frees with the last reference.
"""

from __future__ import annotations

import math
import mmap
import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import ResourceProblem


class FilmStore:
    """Makes whole-film arrays: in memory (``folder`` None) or mapped from scratch files in ``folder``.
    ``spilled_bytes``: what it has mapped so far."""

    def __init__(self, folder: Path | str | None = None):
        self.folder = None if folder is None else Path(folder)
        self.spilled_bytes = 0

    @property
    def spills(self) -> bool:
        return self.folder is not None

    def empty(self, shape, dtype) -> np.ndarray:
        """An uninitialised array of ``shape`` and ``dtype`` (as ``np.empty``)."""
        shape = tuple(int(n) for n in (shape if isinstance(shape, (tuple, list)) else (shape,)))
        dtype = np.dtype(dtype)
        nbytes = math.prod(shape) * dtype.itemsize
        if self.folder is None or nbytes == 0:
            return np.empty(shape, dtype)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            fd, path = tempfile.mkstemp(prefix="film-", suffix=".scratch", dir=self.folder)
        except OSError as exc:
            raise ResourceProblem(
                f"render.spill_dir {self.folder}: cannot make a scratch file there ({exc.strerror}); "
                "choose another folder or set render.spill: false"
            ) from None
        try:
            os.unlink(path)  # the open descriptor and then the mapping keep it; no name is left behind
            try:
                os.posix_fallocate(fd, 0, nbytes)
            except OSError as exc:
                raise ResourceProblem(
                    f"render.spill_dir {self.folder}: the film's arrays need "
                    f"{nbytes / (1 << 30):.2f} GB more there ({exc.strerror}); free some space, "
                    "choose another folder or a smaller film"
                ) from None
            buffer = mmap.mmap(fd, nbytes)
        finally:
            os.close(fd)
        self.spilled_bytes += nbytes
        return np.frombuffer(buffer, dtype=dtype).reshape(shape)


#: Arrays in memory: what a capture uses unless it spills.
IN_MEMORY = FilmStore(None)

#: Overrides the default scratch folder (as $MBCAPTURE_CACHE_DIR does the render cache's).
ENV_DIR = "MBCAPTURE_SCRATCH_DIR"


def default_scratch_dir() -> Path:
    """``$MBCAPTURE_SCRATCH_DIR``, else the platform's user cache folder for mbcapture, ``scratch``
    (beside the render cache's ``renders``: a disk, where a system's temporary folder may be memory)."""
    env = os.environ.get(ENV_DIR)
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("mbcapture", appauthor=False)) / "scratch"


__all__ = ["ENV_DIR", "FilmStore", "IN_MEMORY", "default_scratch_dir"]
