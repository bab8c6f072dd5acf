"""What a capture needs of the machine, planned before any work: peak memory, the disk its outputs
take, and what its renders add to the render cache; and the check that stops a run which cannot
fit, with one line saying what it needs, what is free and what to change.

The model counts the arrays the pipeline holds, per sample of the film (row x column x channel):

* memory: a fixed part (the interpreter, numpy/scipy, Mitsuba and Dr.Jit's LLVM backend with its
  kernels: ``BASE_MEMORY_MB``, plus ``PER_THREAD_MB`` per render thread beyond two and what an
  application's own libraries add, ``App.libraries_mb``), and the working set: ``FLOAT64_PER_BUCKET_SAMPLE`` float64 values per
  sample of each bucket (the exposures, their two halves and the per-group exposures held from
  the render stage, the sensor stage's noise fields and counts; the Poisson and binomial
  inversions work in chunks of bounded size), times ``App.memory_scale`` for an application that
  simulates comparison captures of its own. A video holds every frame's results.
* outputs: the float32 EXRs (buckets, expected and simulated reads, the application's
  ``App.output_channels``) and the PNG previews, each at the compression ZIP and PNG reach on such
  images (``EXR_RATIO_*``, ``PNG_RATIO``).
* render cache: one float32 (group, row, column, RGB) array per render (two halves per stratum,
  and the pilot's), when the cache is on; an upper bound, since a large film's pilot and adaptive
  sampling's renders (cached too) hold only some of the film's pixels.

Tiles (``render.tiles``, :func:`choose_tiles`): render, accumulation and the sensor stage go
through the film a tile of rows at a time, so their working set scales with the largest tile
while the whole-film results stay: ``HELD_PER_BUCKET_SAMPLE`` float64 values per sample of each
bucket (the exposures and their half-sample and temporal differences, the reads and their
truths, and what the reconstruction, the noise report and the writing of the outputs make of
them), plus one per emitter group for an application that asks for per-group exposures, plus
``APP_CHANNEL_HELD`` per pixel and channel of the application's images (its reconstruction).
An application's comparison captures (``App.memory_scale`` above 1) are simulated whole.

The constants were fitted to the peak resident memory and the bytes written of the shipped
configs at 320x256 and 640x512 (``python scripts/resources.py`` measures them again and prints the
model's error per config; docs/resources.md has the table): within 20 % of the measured peak memory; the
outputs at most 20 % over the plan and down to 0.6 of it (ZIP and PNG compression follow the content: measured
0.63 to 1.16 of the plan over the shipped configs).
"""

from __future__ import annotations

import resource
import shutil
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from ..application import App
from ..config import CaptureConfig
from ..errors import ResourceProblem
from .filmstore import default_scratch_dir
from .plan import Plan
from ..render.bands import film_bands, group_bands
from ..sensor.sampling import usable_cores
from ..timing.timeline import Timeline

MB = 1 << 20
GB = 1 << 30

#: Resident memory before the first array: Python, numpy/scipy, Mitsuba, Dr.Jit's LLVM and kernels.
#: About a third of it is the libraries' file pages, and how many of those are resident depends on the
#: page cache: a freshly installed environment (every library just written) maps 60 MB more than one
#: installed long ago, the same code and packages, the same anonymous memory (measured at 320x256:
#: RssFile 216 against 156 MB, RssAnon 223 MB both). 310 sits between the two.
BASE_MEMORY_MB = 310.0
#: Resident memory per render thread beyond the 2 of the machines ``BASE_MEMORY_MB`` was fitted on (their
#: stacks, malloc arenas and Dr.Jit's per-thread state): on a 16-core Xeon (2026-11-27, the default
#: capture at 320x256 under ``taskset``) the anonymous memory was 264, 256, 271 and 298 MiB with 2, 4, 8
#: and 16 threads; least squares, 2.8 MiB a thread. Dr.Jit starts a thread per core this process may use.
PER_THREAD_MB = 2.8
FITTED_THREADS = 2
#: Peak float64 values per sample of each bucket (fitted: the reads add nothing measurable).
FLOAT64_PER_BUCKET_SAMPLE = 15.8
#: Of those, the float64 values per bucket sample a tiled capture holds for the whole film, and the
#: float64 values per pixel and output channel its application's reconstruction holds and makes (fitted,
#: minimax, to the peak memory of metronome_hdr, multi_flash and flash_matting at 640x512 and 1280x1024
#: in tiles of 64 rows: scripts/resources.py --band-rows 64 --tiles 16, within 0.87-1.15; the two
#: error estimates are float32, half a value each: mbcapture.exposure.integrate.DIFF_DTYPE).
HELD_PER_BUCKET_SAMPLE = 5.5
APP_CHANNEL_HELD = 2.75
#: Compressed / raw size of float32 EXR layers (ZIP): noise-free floats to about 3/4, integer DN to under half.
EXR_RATIO_EXPECTED = 0.75
EXR_RATIO_DN = 0.45
EXR_RATIO_APP = 0.65
#: Compressed / raw size of an 8-bit RGB PNG preview of a rendered scene.
PNG_RATIO = 0.5
#: report.html, report.json, config.yaml and the two report plots, whatever the film.
REPORT_BYTES = 120_000
#: The render pilot (render.spp null): PILOT_TIMES strata x two sample counts x two renders.
PILOT_RENDERS = 12
#: A run is refused when its estimate exceeds what is free by more than the estimate's error.
MARGIN = 1.2


@dataclass(frozen=True)
class Resources:
    """Bytes a capture needs: peak resident memory, its outputs in --out, new render-cache entries."""

    memory_bytes: int
    output_bytes: int
    cache_bytes: int
    #: tiles of rows the film goes through (render, accumulate, sensor), and the film's render bands
    tiles: int = 1
    bands: int = 1
    #: the whole-film results kept in scratch files on disk (render.spill, :mod:`mbcapture.exposure.filmstore`)
    spill_bytes: int = 0

    def summary(self) -> dict:
        return {
            "peak_memory_gb": round(self.memory_bytes / GB, 3),
            "outputs_mb": round(self.output_bytes / MB, 2),
            "render_cache_mb": round(self.cache_bytes / MB, 2),
            "tiles": self.tiles,
            "render_bands": self.bands,
            "spill_gb": round(self.spill_bytes / GB, 3),
        }

    def line(self) -> str:
        tiles = f" in {self.tiles} tiles of rows" if self.tiles > 1 else ""
        spill = f" and {_size(self.spill_bytes)} of scratch files on disk (render.spill)" if self.spill_bytes else ""
        return (
            f"needs about {_size(self.memory_bytes)} of memory{tiles}{spill}, {_size(self.output_bytes)} for its "
            "outputs" + (f" and {_size(self.cache_bytes)} of new render-cache entries" if self.cache_bytes else "")
        )


def _size(n: float) -> str:
    return f"{n / GB:.3g} GB" if n >= GB else f"{n / MB:.3g} MB"


def bands_of(cfg: CaptureConfig) -> tuple[tuple[int, int], ...]:
    """The render bands of the film of ``cfg`` (:func:`mbcapture.render.bands.film_bands`, as its renderer makes them)."""
    whole = bool(cfg.camera.distortion) or bool(cfg.camera.diffraction)
    return film_bands(cfg.render.width, cfg.render.height, cfg.render.band_rows, whole)


def tile_rows(cfg: CaptureConfig, tiles: int) -> tuple[tuple[int, int], ...]:
    """The rows (first, end) of each of ``tiles`` tiles of the film of ``cfg`` (runs of whole bands)."""
    return group_bands(bands_of(cfg), tiles)


def accumulated_channels(timeline: Timeline) -> int:
    """The per-pixel channels a capture accumulates: its buckets, or a coded capture's sub-frames and
    the buckets they are routed to."""
    return timeline.n_channels + (timeline.n_buckets if timeline.code is not None else 0)


def spilled_per_bucket_sample(timeline: Timeline, plan: Plan, app: App) -> float:
    """Float64 values per bucket sample (of the accumulated channels) that ``render.spill`` keeps on disk:
    the exposures (1), their two float32 error estimates (1), the per-group exposures of an application
    that asks for them (one per group), and per read its DN, its expected electrons and its saturation
    flags (2 + 1/8)."""
    groups = len(plan.groups) if app.per_group else 0
    return 2.0 + groups + len(timeline.reads) * (2.0 + 1.0 / 8.0) / accumulated_channels(timeline)


def fixed_memory_bytes() -> float:
    """Resident memory before any array of a capture, on this machine: ``BASE_MEMORY_MB``, plus
    ``PER_THREAD_MB`` for each render thread beyond ``FITTED_THREADS``."""
    return (BASE_MEMORY_MB + PER_THREAD_MB * max(usable_cores() - FITTED_THREADS, 0)) * MB


def estimate(
    cfg: CaptureConfig, timeline: Timeline, plan: Plan, app: App, tiles: int = 1, spill: bool = False
) -> Resources:
    """The resources of the capture ``cfg`` with its ``timeline``, render ``plan`` and application,
    going through its film in ``tiles`` tiles of rows (at most one per render band); ``spill``: with the
    whole-film results of a tiled run in scratch files (:func:`spilled_per_bucket_sample`), whose
    pages the kernel may drop, so they count as disk, not memory."""
    px = cfg.render.width * cfg.render.height
    samples = px * 3
    K, R = timeline.n_buckets, len(timeline.reads)
    frames = cfg.capture.frames
    # accumulated per channel; a coded capture holds its sub-frames and its routed buckets
    acc = accumulated_channels(timeline)
    rows = tile_rows(cfg, tiles)
    per_sample = FLOAT64_PER_BUCKET_SAMPLE * app.memory_scale
    if len(rows) > 1:  # the working set follows the largest tile; comparison captures stay whole
        share = max(b - a for a, b in rows) / cfg.render.height
        groups = len(plan.groups) if app.per_group else 0  # the per-group exposures stay whole too
        images = APP_CHANNEL_HELD * app.output_channels / (3.0 * acc)  # the reconstruction, per bucket sample
        per_sample = (
            HELD_PER_BUCKET_SAMPLE
            + groups
            + images
            + (FLOAT64_PER_BUCKET_SAMPLE - HELD_PER_BUCKET_SAMPLE) * share
            + FLOAT64_PER_BUCKET_SAMPLE * (app.memory_scale - 1.0)
        )
    spill_values = spilled_per_bucket_sample(timeline, plan, app) if spill and len(rows) > 1 and frames == 1 else 0.0
    per_sample -= spill_values
    per_frame = 8.0 * samples * per_sample * acc
    # a finished frame's arrays: exposures (float64) and their half-sample differences (float32), reads and truths
    held = 8.0 * samples * (1.5 * K + 2 * R) + 4.0 * px * app.output_channels
    memory = fixed_memory_bytes() + app.libraries_mb * MB + per_frame + (frames - 1) * held

    exr = (
        4.0
        * px
        * (3 * (K + R) * EXR_RATIO_EXPECTED + 3 * R * EXR_RATIO_DN + frames * app.output_channels * EXR_RATIO_APP)
    )
    pngs = app.previews + 2 * R + 3  # the application's, each read on two scales, three maps
    dng = 2.0 * 3 * px * R if cfg.output.dng else 0.0  # uncompressed 16-bit R, G, B per read
    outputs = exr + 3.0 * px * PNG_RATIO * pngs + dng + REPORT_BYTES

    cache = 0.0
    if cfg.render.cache != "off":
        renders = frames * (2 * plan.passes + (PILOT_RENDERS if cfg.render.spp is None else 0))
        cache = min(renders * 4.0 * px * 3 * max(len(plan.groups), 1), cfg.render.cache_max_gb * GB)
    return Resources(
        int(memory),
        int(outputs),
        int(cache),
        tiles=len(rows),
        bands=len(bands_of(cfg)),
        spill_bytes=int(8.0 * samples * acc * spill_values),
    )


def choose_layout(cfg: CaptureConfig, timeline: Timeline, plan: Plan, app: App) -> tuple[int, bool]:
    """(tiles, spill). Tiles: ``render.tiles`` when set (at most one per band); otherwise the fewest
    whose estimate, with :data:`MARGIN`, fits in ``render.max_memory_gb`` and in the free memory (one
    per band when none does: :func:`check` then says so). Spill (``render.spill``; only with more than
    one tile, and not for a video's frames): true or false as set; null, only when tiles alone do not
    fit, and then the fewest tiles that fit with it. Any choice gives the same images."""
    n_bands = len(bands_of(cfg))
    setting = cfg.render.spill
    can_spill = cfg.capture.frames == 1 and setting is not False
    limit = free_memory()[0] / MARGIN
    if cfg.render.max_memory_gb is not None:
        limit = min(limit, cfg.render.max_memory_gb * GB)

    def fits(n: int, spill: bool) -> bool:
        return estimate(cfg, timeline, plan, app, n, spill).memory_bytes <= limit

    if cfg.render.tiles is not None:
        n = min(int(cfg.render.tiles), n_bands)
        return n, n > 1 and can_spill and (setting is True or not fits(n, False))
    spilled = [(n, True) for n in range(2, n_bands + 1)] if can_spill else []
    # true: spill whenever tiles are needed; null: only when tiles alone are not enough
    options = [(1, False), *spilled] if setting is True else [*((n, False) for n in range(1, n_bands + 1)), *spilled]
    for n, spill in options:
        if fits(n, spill):
            return n, spill
    return n_bands, n_bands > 1 and can_spill


def choose_tiles(cfg: CaptureConfig, timeline: Timeline, plan: Plan, app: App) -> int:
    """The tiles of :func:`choose_layout`."""
    return choose_layout(cfg, timeline, plan, app)[0]


def plan_resources(cfg: CaptureConfig, timeline: Timeline, plan: Plan, app: App) -> Resources:
    """:func:`estimate` with the tiles and spill :func:`choose_layout` takes: what a run of ``cfg`` will need."""
    return estimate(cfg, timeline, plan, app, *choose_layout(cfg, timeline, plan, app))


# ----------------------------------------------------------------------------- what is free
def _proc_kb(path: str, field: str) -> int | None:
    """The value in kB of ``field`` in a /proc file of 'Name:   123 kB' lines, or None."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _status_kb(field: str) -> int:
    """``field`` of this process's /proc/self/status, kB (0 where unknown)."""
    return _proc_kb("/proc/self/status", field) or 0


def _cgroup_headroom(root: Path = Path("/sys/fs/cgroup"), own: Path = Path("/proc/self/cgroup")) -> int | None:
    """Bytes this process's memory cgroup still allows it, or None without a limit: cgroup v2
    (memory.max, memory.current), else v1 (the memory controller's memory.limit_in_bytes and
    memory.usage_in_bytes of the group ``own`` names; at the controller's root in a container, which
    sees its own group there). ``root``, ``own``: where they are read (tests)."""
    try:
        limit = (root / "memory.max").read_text().strip()
        used = int((root / "memory.current").read_text())
        return None if limit == "max" else int(limit) - used
    except (OSError, ValueError):
        pass
    try:
        group = next(
            line.split(":", 2)[2].strip()
            for line in own.read_text().splitlines()
            if "memory" in line.split(":", 2)[1].split(",")
        )
        folder = root / "memory" / group.lstrip("/")
        if not folder.is_dir():
            folder = root / "memory"
        limit_v1 = int((folder / "memory.limit_in_bytes").read_text())
        used = int((folder / "memory.usage_in_bytes").read_text())
    except (OSError, ValueError, StopIteration, IndexError):
        return None
    return None if limit_v1 >= 1 << 60 else limit_v1 - used  # v1 writes "no limit" as a huge page-aligned number


def free_memory() -> tuple[int, str]:
    """(bytes, where from) this process can still hold resident, counting what it holds now: the
    smallest of the kernel's MemAvailable, the cgroup's limit and the address-space limit (ulimit -v)."""
    rss = rss_bytes()
    options: list[tuple[int, str]] = []
    avail = _proc_kb("/proc/meminfo", "MemAvailable")
    if avail is not None:
        options.append((avail * 1024 + rss, "available memory"))
    cg = _cgroup_headroom()
    if cg is not None:
        options.append((cg + rss, "the cgroup's memory limit"))
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        options.append((soft - _status_kb("VmSize") * 1024 + rss, "the address-space limit (ulimit -v)"))
    if not options:
        return (1 << 62, "unknown")
    return min(options)


def free_disk(path: Path) -> int:
    """Free bytes on the file system of ``path`` (or of its nearest existing parent)."""
    p = Path(path).absolute()
    while not p.exists():
        p = p.parent
    return shutil.disk_usage(p).free


def check(need: Resources, cfg: CaptureConfig, out_dir: Path | None, cache_root: Path | None) -> None:
    """ResourceProblem (one line, exit 2) when the run cannot fit: its memory (with MARGIN, the
    estimate's error) above what is free or above ``render.max_memory_gb``; its outputs above the
    free disk of ``out_dir``; its new render-cache entries above the free disk of ``cache_root``."""
    film = f"film {cfg.render.width}x{cfg.render.height}" + (f" in {need.tiles} tiles" if need.tiles > 1 else "")
    fewer = (
        "smaller render bands (render.band_rows) or fewer outputs"
        if need.tiles >= need.bands
        else f"more tiles (render.tiles, up to one per render band: {need.bands})"
    )
    cap = cfg.render.max_memory_gb
    if cap is not None and need.memory_bytes > cap * GB:
        raise ResourceProblem(
            f"render.max_memory_gb: this run needs about {_size(need.memory_bytes)} of memory "
            f"({film}), above the cap of {cap:g} GB; use a smaller film (render.width, "
            f"render.height), {fewer}, or raise the cap"
        )
    free, source = free_memory()
    if need.memory_bytes * MARGIN > free:
        raise ResourceProblem(
            f"render.width/height: this run needs about {_size(need.memory_bytes)} of memory "
            f"({film}) but {_size(free)} is free ({source}); use a smaller film or {fewer}"
        )
    if out_dir is not None:
        disk = free_disk(out_dir)
        if need.output_bytes * MARGIN > disk:
            raise ResourceProblem(
                f"--out {out_dir}: the outputs need about {_size(need.output_bytes)} but "
                f"{_size(disk)} is free on that disk; free some space, choose another --out "
                "or a smaller film"
            )
    if need.spill_bytes:
        folder = spill_folder(cfg)
        disk = free_disk(folder)
        if need.spill_bytes * MARGIN > disk:
            raise ResourceProblem(
                f"render.spill_dir {folder}: the film's arrays need about {_size(need.spill_bytes)} "
                f"of scratch files there but {_size(disk)} is free; free some space, choose another "
                "folder (render.spill_dir) or a smaller film"
            )
    if cache_root is not None and need.cache_bytes:
        disk = free_disk(cache_root)
        if need.cache_bytes * MARGIN > disk:
            raise ResourceProblem(
                f"render.cache: the renders need about {_size(need.cache_bytes)} in {cache_root} "
                f"but {_size(disk)} is free there; set render.cache: off, another folder, or "
                "free some space"
            )


def spill_folder(cfg: CaptureConfig) -> Path:
    """Where ``render.spill`` makes its scratch files: ``render.spill_dir``, else :func:`mbcapture.exposure.filmstore.default_scratch_dir`."""
    return Path(cfg.render.spill_dir).expanduser() if cfg.render.spill_dir else default_scratch_dir()


def anon_bytes() -> int:
    """This process's anonymous resident memory now (RssAnon: what the kernel cannot drop or write back
    to a file; a spilled film's mapped pages are not in it), 0 where unknown."""
    return _status_kb("RssAnon") * 1024


def rss_bytes() -> int:
    """This process's resident memory now: VmRSS of /proc/self/status (0 where unknown)."""
    return _status_kb("VmRSS") * 1024


def peak_rss_bytes() -> int:
    """This process's peak resident memory so far: VmHWM of /proc/self/status (getrusage's ru_maxrss
    is no measure of it in a child process: Linux carries the high-water mark of the memory a
    process was started from across exec, the parent's own where it forks by vfork)."""
    return _status_kb("VmHWM") * 1024


__all__ = [
    "Resources",
    "accumulated_channels",
    "anon_bytes",
    "bands_of",
    "check",
    "choose_layout",
    "choose_tiles",
    "estimate",
    "fixed_memory_bytes",
    "free_disk",
    "free_memory",
    "peak_rss_bytes",
    "plan_resources",
    "rss_bytes",
    "spill_folder",
    "spilled_per_bucket_sample",
    "tile_rows",
]


#: :func:`one_blas_thread`'s state: how many blocks are open (in any thread), and the limit the first set.
_BLAS_LOCK = threading.Lock()
_BLAS_OPEN = 0
_BLAS_LIMIT: Any = None


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS (OpenBLAS, as numpy and scipy ship it) on one thread inside the block; as it was once the
    last open block ends.

    mbcapture's BLAS calls are thin products, pixels x a few channels (``integrate.accumulate``'s
    exposures, colour matrices), bound by memory, not arithmetic. On more threads they gain nothing,
    and OpenBLAS's workers spin for a while after each call, waiting for the next: a render that
    starts then shares the cores with them. Measured at 640x512, 14 half-stratum renders with an
    accumulation after each (``scripts/benchmark.py`` [2]'s capture, 2 cores): the renders took
    5.31-5.43 s with two BLAS threads, 4.96-5.15 s with one, 4.90-5.03 s with no BLAS between them;
    the accumulations 0.08-0.18 s and 0.033 s. Through threadpoolctl, which finds the BLAS libraries
    loaded in the process.

    The limit is the process's, so blocks are counted: the first to open sets it and the last to close
    restores it, whatever the threads they run in (a sweep's points run side by side) and however they
    nest; each block alone would restore what it found, which another thread may have set. threadpoolctl
    (3.8) lets only the thread that first set OpenBLAS's limit change it again, and ignores the others
    silently; the last block may close in another thread than the first opened, so each change here
    frees that control before and after it (:func:`_free_blas_control`)."""
    global _BLAS_OPEN, _BLAS_LIMIT
    with _BLAS_LOCK:
        if _BLAS_OPEN == 0:
            from threadpoolctl import threadpool_limits

            _free_blas_control()
            _BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")
            _free_blas_control()
        _BLAS_OPEN += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_OPEN -= 1
            if _BLAS_OPEN == 0:
                _free_blas_control()
                _BLAS_LIMIT.restore_original_limits()
                _free_blas_control()
                _BLAS_LIMIT = None


def _free_blas_control() -> None:
    """Let any thread set OpenBLAS's limit next (threadpoolctl >= 3.8 gives it to the first thread that
    set it; earlier versions have no such control, and nothing to free)."""
    import threadpoolctl

    clear = getattr(getattr(threadpoolctl, "OpenBLASController", None), "clear_controlling_thread", None)
    if clear is not None:
        clear(force=True)
