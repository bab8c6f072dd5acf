"""Multi-bucket pixel physics, from expected electrons to digital reads.

Order of the physics (one capture):

1. Fixed pattern: a per-pixel relative sensitivity (PRNU) multiplies the expected
   photo-electrons of every bucket (the buckets share one photodiode and microlens).
   It and the per-pixel DSNU offset come from ``sensor.fpn_seed`` only, so they are the
   same in every read and every capture of this sensor.
2. Parasitic light (optional): a bucket also collects ``parasitic_light`` times the
   photo-electrons generated while the *other* buckets of the pixel were gated.
3. Dark current: ``dark_current_e_per_s * storage_s[k]`` electrons of mean in bucket k.
4. Shot noise: ONE Poisson draw per bucket on its total expectation. The charge a bucket
   collects is a sum of independent Poisson increments (one per gate slot), and a sum of
   independent Poisson variables is Poisson with the summed mean, so one draw is exact. It
   is drawn by inversion of a per-bucket, per-pixel uniform fixed by the seed
   (:mod:`.sampling`): the same seed on another CPU, whose renderer differs in the last bits,
   gives the same counts except where a step of the Poisson CDF falls between the two means.
5. Bucket full well: charge above ``full_well_e`` is drained by the anti-blooming gate and
   lost (it does not spill into other buckets or pixels); every read that includes such a
   bucket is flagged saturated.
6. Transfer to the floating diffusion (FD): each electron is left behind with probability
   ``transfer_inefficiency`` (binomial thinning, one draw per bucket by inversion of its own
   uniform field: a bucket is moved onto the FD once, and a non-destructive cumulative read
   keeps it there for later reads).
7. A read sums its buckets' transferred charge on the FD, noiselessly (the paper's
   in-pixel addition, section 4.1). The sum clips at ``fd_full_well_e`` (flagged).
8. Readout chain, ONCE PER READ: DSNU offset (pixel, row and column components), Gaussian read
   noise ``read_noise_e`` (the paper's R, figure 11b; a normal field of its own) and, optionally,
   temporal row noise ``read_noise_row_e`` (one offset per row and read), conversion gain, black
   level, rounding to integer codes, ADC clipping to [0, 2^bits - 1] (the top code is flagged
   saturated; the bottom one is not, as it only happens for black levels below the read noise).

Non-destructive cumulative reads (J1 = B4, J2 = B4 + B3, ...) therefore share the same
photons and are correlated, Cov(J_i, J_j) = lambda * min(t_i, t_j) for i != j, while each
read has its own independent read noise.

A film may be sensed in row bands (``band``, a tiled capture): every noise field and fixed-pattern
map is then the whole film's, cut to the band's rows (:class:`~.sampling.BandedField`), so the
bands joined (:func:`join_rows`) are the whole film's reads bit for bit; a colour filter array's
mosaic is demosaiced once the bands are joined (:func:`develop_reads`), since demosaicing reaches
across rows.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import astuple, dataclass, replace
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from .cfa import LOG_DEMOSAIC_FLOOR_E, demosaic_hdr, spread_to_footprint, to_mosaic
from .config import SensorConfig
from .sampling import FIELD_MEMO, BandedField, NoiseStreams, binomial_quantile, poisson_quantile_memo

__all__ = [
    "FixedPattern",
    "SensorReads",
    "develop_reads",
    "dn_to_electrons",
    "fixed_pattern",
    "join_rows",
    "sensor_stage_hook",
    "simulate_reads",
]


@dataclass(frozen=True)
class FixedPattern:
    """Per-pixel fixed-pattern noise maps of one sensor, each (H, W, C) float64.

    ``prnu_gain``: relative sensitivity, mean 1, dimensionless (clipped at 0).
    ``dsnu_offset_e``: offset added to every read, electrons (mean 0).
    """

    prnu_gain: np.ndarray
    dsnu_offset_e: np.ndarray


@dataclass(frozen=True)
class SensorReads:
    """What the sensor delivers for one capture.

    Axes: K buckets, R reads, H rows, W columns, C channels (R, G, B).

    ``electrons``: (K, H, W, C) float64, the noisy charge of each bucket after shot noise,
        dark current and bucket full-well clipping (integer-valued), in electrons.
    ``reads_dn``: (R, H, W, C) float64 holding integer ADC codes, in DN.
    ``reads_e_expected``: (R, H, W, C) float64, the ideal sensor's response: the sum of the
        *input* expected electrons over the read's buckets, noise-free and unclipped, without
        fixed pattern, dark current, parasitic light or transfer loss. Ground truth.
    ``saturated``: (R, H, W, C) bool, True where a bucket of the read hit its full well,
        the FD sum hit ``fd_full_well_e``, or the ADC hit its top code.
    ``bucket_saturated``: (K, H, W, C) bool, True where the bucket hit its full well.
    ``reads``: the bucket indices summed by each read, as given.

    With a colour filter array (``cfg.cfa`` not 'none', :mod:`.cfa`), ``electrons`` and
    ``bucket_saturated`` are the photosites', (K, H, W, 1); ``reads_dn`` are the demosaiced reads
    (float, no longer integer codes) and ``saturated`` is spread over each demosaiced pixel's
    footprint; ``mosaic_dn`` (R, H, W) holds the integer codes of the photosites (raw files) and
    ``mosaic_saturated`` (R, H, W) their own flags;
    ``reads_e_expected`` stays the ideal R, G, B sensor's (grey for a mono sensor): the truth.
    Both are None without a colour filter array; ``cfa`` names it (``sensor.cfa``).

    ``electrons`` and ``bucket_saturated`` are None where the caller kept the reads only
    (:func:`join_rows` with ``reads_only``: a tiled capture does not hold the buckets' charge).
    """

    electrons: np.ndarray | None
    reads_dn: np.ndarray
    reads_e_expected: np.ndarray
    saturated: np.ndarray
    bucket_saturated: np.ndarray | None
    reads: tuple[tuple[int, ...], ...]
    mosaic_dn: np.ndarray | None = None
    mosaic_saturated: np.ndarray | None = None
    cfa: str = "none"


def fixed_pattern(
    shape: tuple[int, int, int],
    cfg: SensorConfig,
    rows: tuple[int, int] | None = None,
    streams: NoiseStreams | None = None,
) -> FixedPattern:
    """The PRNU / DSNU maps of the sensor identified by ``cfg.fpn_seed``, for (H, W, C) images: a
    pixel component (``prnu``, ``dsnu_e``) plus row and column components (``prnu_row``,
    ``prnu_col``, ``dsnu_row_e``, ``dsnu_col_e``), whose variances add.

    Drawn from their own generator so that they do not depend on (nor consume) the
    capture's random stream: the same sensor gives the same maps in every capture.

    ``rows`` (r0, r1): those rows of the (H, W, C) maps, equal to the whole maps' rows; ``streams``
    keeps the pixel maps' stream position for the next band (:class:`~.sampling.BandedField`).
    Whole maps come read-only from :data:`~.sampling.FIELD_MEMO` when it is on (a sweep).
    """
    if rows is None and FIELD_MEMO.entries:  # the same sensor's maps at every point of a sweep: made once
        key = repr(
            (
                "fpn",
                tuple(int(n) for n in shape),
                cfg.fpn_seed,
                cfg.prnu,
                cfg.dsnu_e,
                cfg.prnu_row,
                cfg.prnu_col,
                cfg.dsnu_row_e,
                cfg.dsnu_col_e,
            )
        ).encode()
        maps = FIELD_MEMO.fetch(key, lambda: np.stack(astuple(_fixed_pattern(shape, cfg))))
        return FixedPattern(prnu_gain=maps[0], dsnu_offset_e=maps[1])
    return _fixed_pattern(shape, cfg, rows, streams)


def _fixed_pattern(
    shape: tuple[int, int, int],
    cfg: SensorConfig,
    rows: tuple[int, int] | None = None,
    streams: NoiseStreams | None = None,
) -> FixedPattern:
    """:func:`fixed_pattern`, drawn."""
    seed = np.random.SeedSequence(cfg.fpn_seed)
    if rows is None:
        rng = np.random.default_rng(seed)
        prnu_pixel = cfg.prnu * rng.standard_normal(shape)
        dsnu_offset_e = cfg.dsnu_e * rng.standard_normal(shape)
    else:  # the pixel maps are the first 2 x H x W x C normals of their generator: PRNU's, then DSNU's
        full = (2, *shape)
        field = (
            BandedField(seed, full, "normal")
            if streams is None
            else streams.banded(("fpn", cfg.fpn_seed), seed, full, "normal")
        )
        pixel = field.rows(*rows)
        prnu_pixel, dsnu_offset_e = cfg.prnu * pixel[0], cfg.dsnu_e * pixel[1]
    # row and column components (EMVA 1288 R4.0 reports DSNU and PRNU split so), from a generator of
    # their own so that the pixel maps stay those of the same fpn_seed; shared by a row's (a
    # column's) pixels and channels: one row driver, one column amplifier. Variances add.
    lines = np.random.default_rng(np.random.SeedSequence(cfg.fpn_seed, spawn_key=(1,)))
    H, W = shape[:2]
    prnu_lines = cfg.prnu_row * lines.standard_normal((H, 1, 1)) + cfg.prnu_col * lines.standard_normal((1, W, 1))
    dsnu_lines = cfg.dsnu_row_e * lines.standard_normal((H, 1, 1)) + cfg.dsnu_col_e * lines.standard_normal((1, W, 1))
    if rows is not None:  # (H, 1, 1) + (1, W, 1): drawn whole (a line each), cut to the band
        prnu_lines, dsnu_lines = prnu_lines[rows[0] : rows[1]], dsnu_lines[rows[0] : rows[1]]
    prnu_gain = np.maximum(1.0 + prnu_pixel + prnu_lines, 0.0)
    return FixedPattern(prnu_gain=prnu_gain, dsnu_offset_e=dsnu_offset_e + dsnu_lines)


def _validate_reads(reads: Sequence[Sequence[int]], bucket_count: int) -> tuple[tuple[int, ...], ...]:
    if len(reads) == 0:
        raise ValueError("reads: at least one read is needed")
    out = []
    for r, read in enumerate(reads):
        idx = tuple(int(b) for b in read)
        if not idx:
            raise ValueError(f"reads[{r}]: a read must sum at least one bucket")
        if len(set(idx)) != len(idx):
            raise ValueError(f"reads[{r}]: bucket listed twice in {idx}")
        if min(idx) < 0 or max(idx) >= bucket_count:
            raise ValueError(f"reads[{r}]: bucket indices {idx} outside 0..{bucket_count - 1}")
        out.append(idx)
    return tuple(out)


def simulate_reads(
    expected_bucket_e: np.ndarray,
    reads: Sequence[Sequence[int]],
    cfg: SensorConfig,
    noise: NoiseStreams | np.random.SeedSequence | np.random.Generator | int,
    *,
    storage_s: np.ndarray | Sequence[float] | None = None,
    shared_photodiode: bool = True,
    band: tuple[int, int] | None = None,
    develop: bool = True,
) -> SensorReads:
    """Simulate the noisy buckets and their reads.

    Parameters
    ----------
    expected_bucket_e:
        (K, H, W, C) float64, expected photo-electrons per bucket (noise-free), >= 0.
    reads:
        R reads, each the tuple of 0-based bucket indices summed on the floating diffusion
        for that read (``(3,)``, ``(3, 2)``, ... for cumulative non-destructive reads; one
        index per read for direct reads).
    cfg:
        The sensor.
    noise:
        Source of the capture's shot, transfer and read noise: :class:`~.sampling.NoiseStreams`
        or what it is made from (a SeedSequence, an int, a Generator). Each noise source has
        its own stream (the fixed pattern has its own seed, ``cfg.fpn_seed``).
    storage_s:
        (K,) seconds each bucket holds charge before its read (integration plus waiting),
        for dark current. ``None``: no dark current is added.
    shared_photodiode:
        True (a multi-bucket pixel): the K buckets share one photodiode, so parasitic light
        couples them and K may not exceed ``cfg.bucket_count``. False: the K "buckets" are
        separate frames of a conventional sequential capture; no parasitic coupling.
    band:
        (first row, film height): ``expected_bucket_e`` holds rows first row .. first row + H' of a
        film of that height, and every noise field is the film's, cut to those rows (pass the same
        :class:`~.sampling.NoiseStreams` for every band). None: the whole film.
    develop:
        False: a colour filter array's photosites are returned undeveloped (``reads_dn`` (R, H, W, 1),
        ``reads_e_expected`` already the R, G, B truth), for :func:`develop_reads` once the bands of
        a film are joined. No effect without a colour filter array.

    Returns
    -------
    SensorReads
    """
    expected = np.asarray(expected_bucket_e, dtype=np.float64)
    if expected.ndim != 4:
        raise ValueError(f"expected_bucket_e: expected shape (K, H, W, C), got {expected.shape}")
    if not np.all(np.isfinite(expected)) or np.any(expected < 0):
        raise ValueError("expected_bucket_e: values must be finite and >= 0")
    k_buckets = expected.shape[0]
    if shared_photodiode and k_buckets > cfg.bucket_count:
        raise ValueError(f"expected_bucket_e: {k_buckets} buckets but sensor.bucket_count is {cfg.bucket_count}")
    read_sets = _validate_reads(reads, k_buckets)
    storage = None if storage_s is None else np.asarray(storage_s, dtype=np.float64)
    if storage is not None:
        if storage.shape != (k_buckets,) or np.any(storage < 0):
            raise ValueError(f"storage_s: expected {k_buckets} non-negative seconds, got {storage!r}")

    streams = noise if isinstance(noise, NoiseStreams) else NoiseStreams(noise)
    film = None
    if band is not None:
        r0, height = (int(x) for x in band)
        if not 0 <= r0 <= height - expected.shape[1]:
            raise ValueError(f"band: rows {r0}..{r0 + expected.shape[1]} outside a film of {height} rows")
        if r0 % 2 and cfg.cfa not in ("none", "mono"):
            raise ValueError(f"band: a {cfg.cfa} colour filter array's band must start on an even row, got {r0}")
        film = _Film(r0, height)

    def simulate(e: np.ndarray) -> SensorReads:
        """This call's sensor (its noise fields, storage times and reads) on the input ``e``."""
        e = np.asarray(e, dtype=np.float64)
        if e is not expected and (e.shape != expected.shape or not np.all(np.isfinite(e)) or np.any(e < 0)):
            raise ValueError(f"sensor stage input: expected finite electrons >= 0 of shape {expected.shape}")
        photosites = _photosites(e, read_sets, cfg, streams, storage, shared_photodiode, film)
        return develop_reads(photosites, cfg) if develop else photosites

    hook = _STAGE_HOOK.get()
    return simulate(expected) if hook is None else hook(expected, simulate)


#: The sensor-stage seam (:func:`sensor_stage_hook`); None outside such a context.
_STAGE_HOOK: ContextVar[Callable[[np.ndarray, Callable[[np.ndarray], SensorReads]], SensorReads] | None] = ContextVar(
    "mbcapture_sensor_stage_hook", default=None
)


@contextmanager
def sensor_stage_hook(hook: Callable[[np.ndarray, Callable[[np.ndarray], SensorReads]], SensorReads]) -> Iterator[None]:
    """Within this context, every :func:`simulate_reads` call (every sensor stage of a capture, an
    application's comparison captures included) calls ``hook(expected_e, simulate)`` and returns
    what it returns; ``simulate(e)`` is that call's sensor applied to the input ``e``, with the
    same noise fields, storage times and reads (callable more than once, always the same answer
    for the same ``e``).

    This is the seam of the stage goldens (tests/golden_cases.py): they record each stage's
    input, and replay the golden's stored input so that every count downstream is pinned on
    its own stored input, whatever the renderer's last bits on this CPU."""
    token = _STAGE_HOOK.set(hook)
    try:
        yield
    finally:
        _STAGE_HOOK.reset(token)


@dataclass(frozen=True)
class _Film:
    """Where a band lies: its first row and the film's height."""

    r0: int
    height: int

    def field(self, shape: tuple[int, ...]) -> tuple[tuple[int, ...], tuple[int, int]]:
        """The film's field shape of a band array's ``shape`` (axis 1: rows), and the band's rows."""
        return (shape[0], self.height, *shape[2:]), (self.r0, self.r0 + shape[1])


def _photosites(
    expected: np.ndarray,
    read_sets: tuple[tuple[int, ...], ...],
    cfg: SensorConfig,
    streams: NoiseStreams,
    storage: np.ndarray | None,
    shared_photodiode: bool,
    film: _Film | None,
) -> SensorReads:
    """:func:`simulate_reads` on validated arguments, up to the photosites behind the colour filter
    array (:mod:`.cfa`); :func:`develop_reads` turns them into R, G, B reads."""
    if cfg.cfa == "none":
        return _simulate_photosites(expected, read_sets, cfg, streams, storage, shared_photodiode, film)
    if cfg.cfa == "mono":
        # one photosite per pixel; its input is the same in every channel (the renderer's mono mixture),
        # the channels' mean where a caller gives them different
        return _simulate_photosites(
            expected.mean(axis=-1, keepdims=True), read_sets, cfg, streams, storage, shared_photodiode, film
        )
    out = _simulate_photosites(to_mosaic(expected, cfg.cfa), read_sets, cfg, streams, storage, shared_photodiode, film)
    full = np.stack([expected[list(r)].sum(axis=0) for r in read_sets])  # the ideal RGB sensor: the truth
    return replace(out, reads_e_expected=full)


def develop_reads(photosites: SensorReads, cfg: SensorConfig) -> SensorReads:
    """The reads of :func:`simulate_reads` (``develop=False``: photosites, a band's or a joined film's)
    as the camera delivers them: a Bayer mosaic demosaiced (``sensor.demosaic``) and its saturation
    spread over each pixel's footprint, a mono sensor's one value in every channel; as they are
    without a colour filter array."""
    out = photosites
    if cfg.cfa == "none":
        return out
    if cfg.cfa == "mono":
        mono = np.repeat(out.reads_e_expected, 3, axis=-1)
        return replace(
            out,
            reads_dn=np.repeat(out.reads_dn, 3, axis=-1),
            reads_e_expected=mono,
            saturated=np.repeat(out.saturated, 3, axis=-1),
            mosaic_dn=out.reads_dn[..., 0],
            mosaic_saturated=out.saturated[..., 0],
            cfa="mono",
        )
    # demosaic the signal above black in a logarithmic domain (demosaic_hdr: a read spans its ADC's range,
    # thousands to one), linear below LOG_DEMOSAIC_FLOOR_E; not rounded again: the reads are the ISP's output
    floor = LOG_DEMOSAIC_FLOOR_E * cfg.gain_dn_per_e
    signal = demosaic_hdr(out.reads_dn[..., 0] - cfg.black_level_dn, cfg.cfa, cfg.demosaic, floor) + cfg.black_level_dn
    return replace(
        out,
        reads_dn=signal,
        saturated=spread_to_footprint(out.saturated, cfg.demosaic),
        mosaic_dn=out.reads_dn[..., 0],
        mosaic_saturated=out.saturated[..., 0],
        cfa=cfg.cfa,
    )


def join_rows(
    bands: "Iterable[SensorReads]",
    height: int,
    reads_only: bool = False,
    empty: "Callable[[tuple, np.dtype], np.ndarray]" = np.empty,
) -> SensorReads:
    """The reads of a film of ``height`` rows from its row bands (in order, each from
    :func:`simulate_reads` with ``band``); ``reads_only``: without the buckets' charge
    (``electrons``, ``bucket_saturated`` None), which a tiled capture does not keep. ``bands`` may be
    a generator: each band is copied into the film's arrays as it comes and let go, so the bands are
    never all held at once. ``empty(shape, dtype)`` makes the film's arrays (``np.empty``, or
    :meth:`mbcapture.exposure.filmstore.FilmStore.empty` for arrays on disk)."""
    names = ("reads_dn", "reads_e_expected", "saturated", "mosaic_dn", "mosaic_saturated") + (
        () if reads_only else ("electrons", "bucket_saturated")
    )
    first: SensorReads | None = None
    film: dict[str, np.ndarray | None] = {}
    row = 0
    for b in bands:
        first = b if first is None else first
        h = b.reads_dn.shape[1]
        for name in names:
            value = getattr(b, name)
            if value is None:
                film[name] = None
                continue
            if name not in film:  # rows on axis 1 of every array
                film[name] = empty((value.shape[0], height, *value.shape[2:]), value.dtype)
            film[name][:, row : row + h] = value
        row += h
    if first is None:
        raise ValueError("join_rows: no bands")
    if row != height:
        raise ValueError(f"join_rows: the bands hold {row} rows, not the film's {height}")
    if reads_only:
        film.update(electrons=None, bucket_saturated=None)
    return replace(first, **film)


def _simulate_photosites(
    expected: np.ndarray,
    read_sets: tuple[tuple[int, ...], ...],
    cfg: SensorConfig,
    streams: NoiseStreams,
    storage: np.ndarray | None,
    shared_photodiode: bool,
    film: _Film | None = None,
) -> SensorReads:
    """The photosites (one per pixel and channel of ``expected``): fixed pattern, shot noise, wells, reads.
    ``film``: where a band lies in its film (every field cut to its rows); None: the whole film."""

    def field(kind: str, stage: str, shape: tuple[int, ...]) -> np.ndarray:
        draw = streams.uniform if kind == "uniform" else streams.normal
        return draw(stage, shape) if film is None else draw(stage, *film.field(shape))

    def normal_runs(stage: str, shape: tuple[int, ...]) -> Iterator[np.ndarray]:  # field("normal", ...)[i], in turn
        return streams.normal_runs(stage, shape) if film is None else streams.normal_runs(stage, *film.field(shape))

    fpn = (
        fixed_pattern(expected.shape[1:], cfg)
        if film is None
        else fixed_pattern((film.height, *expected.shape[2:]), cfg, (film.r0, film.r0 + expected.shape[1]), streams)
    )
    # arrays of the film's size are made once and then worked in place: a fresh array costs its page
    # faults, more than the arithmetic (numpy asks the kernel for huge pages, which it may compact for)
    mean_e = expected * fpn.prnu_gain
    if shared_photodiode and cfg.parasitic_light > 0.0:
        others_e = mean_e.sum(axis=0, keepdims=True) - mean_e
        others_e *= cfg.parasitic_light
        mean_e += others_e
        del others_e
    if storage is not None:
        mean_e += (cfg.dark_current_e_per_s * storage)[:, None, None, None]

    # remembered: a sweep's points that differ only after this draw (read noise, full wells, ADC) reuse it
    electrons = poisson_quantile_memo(
        field("uniform", "shot", mean_e.shape),
        mean_e,
        streams.field_key("shot", mean_e.shape, "uniform") if film is None else None,
    )
    del mean_e
    bucket_saturated = electrons >= cfg.full_well_e
    np.minimum(electrons, cfg.full_well_e, out=electrons)

    if cfg.transfer_inefficiency > 0.0:
        lost = binomial_quantile(field("uniform", "transfer", electrons.shape), electrons, cfg.transfer_inefficiency)
        transferred = electrons - lost
        del lost
    else:
        transferred = electrons

    n_reads = len(read_sets)
    shape = (n_reads, *expected.shape[1:])
    reads_dn = np.empty(shape, dtype=np.float64)
    reads_e_expected = np.empty(shape, dtype=np.float64)
    saturated = np.empty(shape, dtype=bool)
    adc_max = float(cfg.adc_max_dn)
    read_noise = normal_runs("read", shape)
    # temporal row noise: one offset per row and read, shared by the row's pixels and channels
    row_noise = (
        cfg.read_noise_row_e * field("normal", "row", (n_reads, shape[1], 1, 1)) if cfg.read_noise_row_e > 0.0 else None
    )
    signal_e, scratch = np.empty(shape[1:]), np.empty(shape[1:])
    for r, buckets in enumerate(read_sets):
        idx = list(buckets)
        _reduce_buckets(np.add, transferred, idx, out=signal_e)  # the floating diffusion's charge
        sat = saturated[r]
        _reduce_buckets(np.logical_or, bucket_saturated, idx, out=sat)
        sat |= signal_e >= cfg.fd_full_well_e
        np.minimum(signal_e, cfg.fd_full_well_e, out=signal_e)
        signal_e += fpn.dsnu_offset_e
        np.multiply(next(read_noise), cfg.read_noise_e, out=scratch)
        signal_e += scratch
        if row_noise is not None:
            signal_e += row_noise[r]
        dn = signal_e  # in DN from here
        dn *= cfg.gain_dn_per_e
        dn += cfg.black_level_dn
        np.rint(dn, out=dn)
        sat |= dn >= adc_max
        np.clip(dn, 0.0, adc_max, out=reads_dn[r])
        _reduce_buckets(np.add, expected, idx, out=reads_e_expected[r])

    return SensorReads(
        electrons=electrons,
        reads_dn=reads_dn,
        reads_e_expected=reads_e_expected,
        saturated=saturated,
        bucket_saturated=bucket_saturated,
        reads=read_sets,
    )


def _reduce_buckets(op: np.ufunc, a: np.ndarray, idx: list[int], out: np.ndarray) -> np.ndarray:
    """``op.reduce(a[idx], axis=0)`` into ``out`` (np.add: the buckets' sum, np.logical_or: any),
    bucket after bucket (the order numpy reduces a leading axis in, so the same bits), without the
    copy ``a[idx]``."""
    np.copyto(out, a[idx[0]])
    for i in idx[1:]:
        op(out, a[i], out=out)
    return out


def dn_to_electrons(reads_dn: np.ndarray, cfg: SensorConfig) -> np.ndarray:
    """Undo black level and gain: (DN - black_level_dn) / gain_dn_per_e, in electrons.

    Any shape; float64. The result can be negative (read noise around zero light).
    """
    return (np.asarray(reads_dn, dtype=np.float64) - cfg.black_level_dn) / cfg.gain_dn_per_e
