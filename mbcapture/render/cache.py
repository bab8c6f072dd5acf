"""A persistent cache of renders: nothing downstream of a render ever pays for it twice.

A render is a pure function of what the renderer was given (the Mitsuba scene description
with its files' contents, the moving parts' poses at the render time, the film, variant,
integrator settings, samples per pixel, seed, the emitter groups requested) and of the code
and libraries that turn that into pixels (mbcapture's renderer modules, Mitsuba, Dr.Jit, and
the CPU target its kernels were compiled for, which changes the last bits). The
:class:`~mbcapture.render.Renderer` hashes all of it into a key (SHA-256); this module stores
one float32 array per key.

Layout: ``<root>/<key[:2]>/<key>.npy.entry``, one file per render: a JSON header line (shape,
dtype, SHA-256 of the data, seconds the render took, what it was) followed by the raw array.
Writes go to a temporary file in the same folder and are moved into place with
``os.replace``, so a reader sees a whole entry or none; a damaged entry (a truncated file, a
wrong checksum, an unreadable header) is deleted and reported as a miss, so it is rendered again
and never used. Two processes rendering the same key both write the same bytes; the last
rename wins. Reads touch the entry's modification time; when the cache grows beyond its size
cap, the least recently used entries are removed (under an advisory lock, so two evictions do
not race; a reader whose entry vanishes sees a miss). The cache's size is not measured on every
write: a walk of the folder costs a ``stat`` per entry, and a run writes an entry per render, so a
large cache made every render pay for all the others. A ``RenderCache`` walks the folder on its
first write and then every ``RESCAN_EVERY`` writes (to see other processes' entries), adds its own
writes' bytes in between, and evicts as soon as that count passes the cap.

Where: ``render.cache`` ("on": the platform's user cache folder from platformdirs, e.g.
``~/.cache/mbcapture/renders`` on Linux, or ``$MBCAPTURE_CACHE_DIR`` when set; "off"; or a
folder path), capped at ``render.cache_max_gb``. ``mbcapture cache info | clear``.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["CacheStats", "RenderCache", "default_cache_dir", "open_cache"]

ENV_DIR = "MBCAPTURE_CACHE_DIR"
SUFFIX = ".npy.entry"
FORMAT = 1
#: Writes between two walks of the folder that measure the cache's size (see the module doc).
RESCAN_EVERY = 64


def default_cache_dir() -> Path:
    """``$MBCAPTURE_CACHE_DIR``, else the platform's user cache folder for mbcapture, ``renders``."""
    env = os.environ.get(ENV_DIR)
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_cache_dir("mbcapture", appauthor=False)) / "renders"


@dataclass
class CacheStats:
    """What one run got from the cache: renders read (hits), rendered and stored (misses),
    damaged entries found and replaced, and the render seconds the hits saved."""

    hits: int = 0
    misses: int = 0
    corrupt: int = 0
    saved_s: float = 0.0
    kinds: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {
            "hits": self.hits,
            "rendered": self.misses,
            "corrupt_replaced": self.corrupt,
            "render_seconds_saved": round(self.saved_s, 3),
            "by_kind": self.kinds,
        }


class RenderCache:
    """Arrays by key in a folder, with checksums, atomic writes and least-recently-used eviction."""

    def __init__(self, root: str | os.PathLike, max_bytes: int):
        self.root = Path(root).expanduser()
        self.max_bytes = int(max_bytes)
        self.stats = CacheStats()
        self._known_bytes: int | None = None  # the size at the last walk, plus this object's writes since
        self._writes_since_walk = 0

    # -- paths ------------------------------------------------------------------------------
    def _path(self, key: str) -> Path:
        if len(key) < 8 or not all(c in "0123456789abcdef" for c in key):
            raise ValueError(f"cache key must be a hex digest, got {key!r}")
        return self.root / key[:2] / f"{key}{SUFFIX}"

    def entries(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return [p for p in self.root.glob(f"??/*{SUFFIX}") if p.is_file()]

    # -- read / write -----------------------------------------------------------------------
    def get(self, key: str, kind: str = "render") -> tuple[np.ndarray, dict] | None:
        """(array, header) for ``key``, or None (absent or damaged: a damaged entry is removed)."""
        path = self._path(key)
        try:
            with open(path, "rb") as f:
                header = json.loads(f.readline().decode("utf-8"))
                data = f.read()
        except FileNotFoundError:
            self._count(kind, hit=False)
            return None
        except (OSError, ValueError, UnicodeDecodeError):
            return self._damaged(path, kind)
        try:
            if header.get("format") != FORMAT or header.get("key") != key:
                raise ValueError("header")
            if hashlib.sha256(data).hexdigest() != header["sha256"]:
                raise ValueError("checksum")
            arr = np.frombuffer(data, dtype=np.dtype(header["dtype"])).reshape(header["shape"]).copy()
        except (KeyError, TypeError, ValueError):
            return self._damaged(path, kind)
        with contextlib.suppress(OSError):
            os.utime(path)  # least recently *used*
        self.stats.hits += 1
        self.stats.saved_s += float(header.get("seconds", 0.0))
        self._count(kind, hit=True)
        return arr, header

    def put(self, key: str, array: np.ndarray, *, seconds: float = 0.0, about: dict | None = None) -> None:
        """Store ``array`` under ``key`` atomically, then evict beyond the size cap. Failing to
        write (a full disk, a read-only folder) is not an error: the render is simply not kept."""
        arr = np.ascontiguousarray(array)
        data = arr.tobytes()
        header = {
            "format": FORMAT,
            "key": key,
            "shape": list(arr.shape),
            "dtype": arr.dtype.str,
            "sha256": hashlib.sha256(data).hexdigest(),
            "seconds": float(seconds),
            "about": about or {},
        }
        path = self._path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=path.parent)
            try:
                head = json.dumps(header, sort_keys=True).encode("utf-8") + b"\n"
                with os.fdopen(fd, "wb") as f:
                    f.write(head)
                    f.write(data)
                os.replace(tmp, path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        except OSError:
            return
        self._count_written(len(head) + len(data))

    def _count_written(self, nbytes: int) -> None:
        """Keep the size count up to date after a write of ``nbytes``; evict when it passes the cap."""
        if self._known_bytes is None or self._writes_since_walk >= RESCAN_EVERY:
            self._known_bytes, self._writes_since_walk = self.size_bytes(), 0
        else:
            self._known_bytes += nbytes  # an overwritten key counts twice: it errs towards a walk
            self._writes_since_walk += 1
        if self._known_bytes > self.max_bytes:
            self.evict()

    def _damaged(self, path: Path, kind: str) -> None:
        with contextlib.suppress(OSError):
            path.unlink()
        self.stats.corrupt += 1
        self._count(kind, hit=False)
        return None

    def _count(self, kind: str, hit: bool) -> None:
        if not hit:
            self.stats.misses += 1
        k = self.stats.kinds.setdefault(kind, {"hits": 0, "rendered": 0})
        k["hits" if hit else "rendered"] += 1

    # -- size -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def _lock(self):
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / ".lock", "a+b") as f:
            fcntl.flock(f, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def size_bytes(self) -> int:
        total = 0
        for p in self.entries():
            with contextlib.suppress(OSError):
                total += p.stat().st_size
        return total

    def evict(self) -> int:
        """Remove least recently used entries until the cache is within its cap; returns how many."""
        removed = 0
        with self._lock():
            files = []
            for p in self.entries():
                with contextlib.suppress(OSError):
                    st = p.stat()
                    files.append((st.st_mtime, st.st_size, p))
            total = sum(s for _, s, _ in files)
            for _, size, p in sorted(files, key=lambda x: x[0]):
                if total <= self.max_bytes:
                    break
                with contextlib.suppress(OSError):
                    p.unlink()
                    total -= size
                    removed += 1
        self._known_bytes, self._writes_since_walk = total, 0
        return removed

    def clear(self) -> int:
        """Remove every entry (and stray temporary files); returns how many entries."""
        n = 0
        with self._lock():
            for p in self.entries():
                with contextlib.suppress(OSError):
                    p.unlink()
                    n += 1
            for p in self.root.glob("??/.tmp-*"):
                with contextlib.suppress(OSError):
                    p.unlink()
        return n

    def info(self) -> dict:
        files = self.entries()
        return {
            "folder": str(self.root),
            "entries": len(files),
            "size_bytes": self.size_bytes(),
            "max_bytes": self.max_bytes,
        }


def open_cache(setting: str, max_gb: float) -> RenderCache | None:
    """The cache a ``render.cache`` setting names: "on" (the default folder), "off" (None), or a folder."""
    if setting == "off":
        return None
    root = default_cache_dir() if setting == "on" else Path(setting).expanduser()
    return RenderCache(root, int(max_gb * 1e9))


def digest(obj) -> str:
    """SHA-256 of a canonical JSON form of ``obj`` (dicts sorted, floats as repr)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), default=repr).encode()).hexdigest()


@lru_cache(maxsize=None)
def _file_sha256(path: str, mtime_ns: int, size: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's content (memoized by path, modification time and size)."""
    st = Path(path).stat()
    return _file_sha256(str(Path(path).resolve()), st.st_mtime_ns, st.st_size)


def canonical(obj: Any, mi: Any) -> Any:
    """A Mitsuba scene dict as plain JSON data for hashing: transforms as matrices, files by content."""
    if isinstance(obj, dict):
        return {
            str(k): ({"file": Path(v).name, "sha256": file_digest(v)} if k == "filename" else canonical(v, mi))
            for k, v in obj.items()
        }
    if isinstance(obj, (list, tuple)):
        return [canonical(v, mi) for v in obj]
    if isinstance(obj, (bool, int, str)) or obj is None:
        return obj
    if isinstance(obj, float):
        return repr(obj)
    if isinstance(obj, mi.ScalarTransform4f):
        return [[repr(float(x)) for x in row] for row in np.asarray(obj.matrix, dtype=np.float64)]
    if isinstance(obj, mi.Bitmap):  # e.g. a projector's pattern: by content
        data = np.ascontiguousarray(np.asarray(obj))
        return {
            "bitmap": hashlib.sha256(data.tobytes()).hexdigest(),
            "shape": list(data.shape),
            "dtype": data.dtype.str,
        }
    if isinstance(obj, np.ndarray):
        return {"array": hashlib.sha256(np.ascontiguousarray(obj).tobytes()).hexdigest(), "shape": list(obj.shape)}
    # anything else would be hashed by its repr, which need not show its content: refuse, so that
    # two different scenes can never share a cache key
    raise TypeError(f"render cache key: cannot hash a {type(obj).__name__} in the scene description")
