"""Random draws that move little when their parameters move little.

Why: ``numpy.random.Generator.poisson`` is a rejection sampler. How many uniforms it consumes
depends on the mean, so a last-bit change of one expected value (another CPU renders the scene
with another vector width) shifts every later draw, and two machines with the same seed give
images that differ everywhere. Here every random quantity of the sensor is a deterministic
function of its parameters and of a uniform (or normal) *field* fixed by the seed and the
stage alone (:class:`NoiseStreams`): one value per bucket, pixel and channel, drawn up front in
a fixed order. Discrete laws are sampled by **inversion**, k = F^-1(u) = min{k : F(k) >= u}: a
change of the mean moves k only where u lies within that change of a step of F, so the same
seed on two machines gives reads that differ only where, and about as much as, the expected
electrons differ. Inversion is exact: k has exactly the law F for u uniform.

Inversion for large means (:func:`invert_discrete`), written here because neither numpy nor
scipy has a fast vectorized one (``scipy.stats.poisson.ppf`` took 13 s for 3.9 M draws on this
2-core VM; it root-finds a continuous quantile per element): start from a Cornish-Fisher
guess k0 (the normal quantile corrected for skewness and kurtosis, within one or two of the
answer wherever the mean exceeds a few), evaluate the exact CDF once at k0 with scipy's
regularized incomplete gamma / beta functions (the lower tail P(X <= k0) when u <= 1/2, the
upper tail P(X > k0) against 1 - u, which is exact in float64, when u > 1/2, so neither tail
loses digits), and step k up or down by the pmf recurrence (pmf(k+1) = pmf(k) * ratio) until
k is the smallest count with F(k) >= u. Each lane needs one CDF and one pmf evaluation; the start
is the answer in all but about one lane in a thousand (the default capture's: 4595 of 3.9 M), and
only those walk. Measured on the default capture's 3.9 M bucket samples at 640x512 (means up to
1.4e7, median 1.6e3; AMD EPYC, 2 cores): 0.62 s on one core, about 0.43 s of it scipy's incomplete
gamma (the tails, ~100 ns a lane), 0.31 s on the two threads; numpy's rejection sampler takes 0.10 s.
Each tail is evaluated on its own lanes, gathered by index: the ufuncs' ``where=`` masks cost a sixth
more per lane (132 against 112 ms per million lanes; on another machine of the same kind the masks
had been the faster, so measure again before changing it back). The Cornish-Fisher start has a
Poisson form (:func:`_poisson_start`) with a third of the general one's arithmetic; together with the
gathered tails these took the inversion from 0.75 to 0.62 s on one core, with the same counts. A
walk compiled with numba was no faster than this one, and its compiler (llvmlite's LLVM, beside
Dr.Jit's) added 120 MB to every process.

Streams: :class:`NoiseStreams` spawns one child seed per named stage (``shot``,
``transfer``, ``read``) from the capture's sensor seed, so turning one noise source on or off
(or changing its parameter) leaves the draws of the others unchanged: a sweep over read noise
sees the same photons in every point.

Row bands (a film sensed in tiles, :mod:`mbcapture.capture.pipeline`): :class:`BandedField` gives rows
r0:r1 of a field exactly as the whole field has them, without drawing the whole field at once.
numpy's ``Generator`` draws a double from one 64-bit output and a ziggurat normal from one or
more, one value after another with nothing buffered, so a stream cut anywhere and resumed from
its saved bit-generator state continues bit for bit (tests/test_tiles.py checks it). The field
is C-ordered (leading axis, row, ...), so each leading index's band is one contiguous run of the
stream; the state at the end of each run is kept, and the next band resumes there: sensing a
film band after band draws each field about once.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
from scipy import special

__all__ = [
    "FIELD_MEMO",
    "POISSON_MEMO",
    "ArrayMemo",
    "BandedField",
    "DiscreteLaw",
    "NoiseStreams",
    "binomial_quantile",
    "invert_discrete",
    "keep_sensor_work",
    "poisson_pmf",
    "poisson_quantile",
    "poisson_quantile_memo",
    "uniform_open",
]

#: Above this mean a Poisson count is no longer an exact float64 integer: the draw is the rounded
#: Cornish-Fisher quantile (relative skewness 1/sqrt(mean) < 3e-8, below float64 use downstream).
POISSON_EXACT_MAX = 2.0**50

#: Stages with their own child seed, in spawn order (the order never changes: adding a stage
#: appends to it, so existing stages keep their draws).
STAGES = ("shot", "transfer", "read")
#: Streams added later, each derived from a stage's seed (stage, child key) without spawning: the
#: streams above stay what they were for the same seed.
DERIVED = {"row": ("read", 1)}


def uniform_open(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Uniform float64 in (0, 1): ``rng.random`` with its value 0 (probability 2^-53) moved to
    2^-54, so that inverse CDFs never see u = 0."""
    u = rng.random(shape)
    u[u == 0.0] = 2.0**-54
    return u


#: Values skipped at a time when a banded field moves its stream forward (bounded memory).
_SKIP_CHUNK = 1 << 20


class BandedField:
    """Row bands of the random field of ``shape`` (leading axis, rows, ...) that
    ``default_rng(seed)`` draws in C order, ``kind`` 'uniform' (:func:`uniform_open`) or 'normal'
    (``standard_normal``): :meth:`rows` (r0, r1) equals ``whole[:, r0:r1]`` bit for bit, at the cost
    of the band plus the stream skipped to reach it (nothing when bands come in order)."""

    def __init__(self, seed: np.random.SeedSequence, shape: tuple[int, ...], kind: str):
        if kind not in ("uniform", "normal"):
            raise ValueError(f"BandedField kind: expected 'uniform' or 'normal', got {kind!r}")
        if len(shape) < 2:
            raise ValueError(f"BandedField shape: expected (leading, rows, ...), got {shape}")
        self.shape, self.kind = tuple(int(n) for n in shape), kind
        self._marks: dict[int, dict] = {0: np.random.PCG64(seed).state}  # stream offset -> bit-generator state

    def _draw(self, g: np.random.Generator, n: int) -> np.ndarray:
        return uniform_open(g, (n,)) if self.kind == "uniform" else g.standard_normal(n)

    def _at(self, offset: int) -> np.random.Generator:
        """A generator whose next value is the stream's value number ``offset``."""
        start = max(o for o in self._marks if o <= offset)
        g = np.random.Generator(np.random.PCG64())
        g.bit_generator.state = self._marks[start]
        if self.kind == "uniform":  # one 64-bit output per double: jump
            g.bit_generator.advance(offset - start)
        else:  # a normal takes one or more outputs: draw through
            for a in range(start, offset, _SKIP_CHUNK):
                self._draw(g, min(_SKIP_CHUNK, offset - a))
        return g

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """float64 (leading, r1 - r0, ...): rows r0:r1 of the field."""
        if not 0 <= r0 < r1 <= self.shape[1]:
            raise ValueError(f"BandedField rows: expected 0 <= r0 < r1 <= {self.shape[1]}, got {r0}, {r1}")
        out = np.empty((self.shape[0], r1 - r0, *self.shape[2:]))
        for a in range(self.shape[0]):
            self.run(a, r0, r1, out[a])
        return out

    def run(self, a: int, r0: int, r1: int, out: np.ndarray) -> np.ndarray:
        """``out`` (r1 - r0, ...) filled with rows r0:r1 of leading index ``a`` of the field (``rows(r0, r1)[a]``)."""
        lead, H = self.shape[:2]
        if not 0 <= r0 < r1 <= H or not 0 <= a < lead:
            raise ValueError(
                f"BandedField run: expected 0 <= a < {lead} and rows 0 <= r0 < r1 <= {H}, got {a}, {r0}, {r1}"
            )
        row = int(np.prod(self.shape[2:], dtype=np.int64))
        start, n = (a * H + r0) * row, (r1 - r0) * row
        g = self._at(start)
        out[...] = self._draw(g, n).reshape(out.shape)
        self._marks[start + n] = g.bit_generator.state
        return out


class NoiseStreams:
    """Per-stage random fields of one capture's sensor, fixed by one seed.

    ``seed``: a :class:`numpy.random.SeedSequence`, an int, or a Generator (tests): a Generator
    gives up a fixed number of its draws to seed the stages, whatever the signal.

    ``rows`` (r0, r1) asks for those rows (axis 1) of the field of ``shape``: the same values as
    the whole field's rows, for a film sensed band by band (:class:`BandedField`, kept per field
    so that consecutive bands continue the stream).
    """

    def __init__(self, seed: np.random.SeedSequence | np.random.Generator | int):
        if isinstance(seed, np.random.Generator):
            seed = np.random.SeedSequence(seed.integers(0, 2**63, size=4).tolist())
        elif not isinstance(seed, np.random.SeedSequence):
            seed = np.random.SeedSequence(int(seed))
        self._seeds = dict(zip(STAGES, seed.spawn(len(STAGES))))
        self._bands: dict[tuple, BandedField] = {}

    def _seed(self, stage: str) -> np.random.SeedSequence:
        if stage in DERIVED:  # a child of another stage's seed, made without spawning from it
            base, key = DERIVED[stage]
            s = self._seeds[base]
            return np.random.SeedSequence(s.entropy, spawn_key=(*s.spawn_key, key))
        if stage not in self._seeds:
            raise ValueError(f"noise stage {stage!r}: expected one of {[*self._seeds, *DERIVED]}")
        return self._seeds[stage]

    def _rng(self, stage: str) -> np.random.Generator:
        return np.random.default_rng(self._seed(stage))

    def banded(self, key: tuple, seed: np.random.SeedSequence, shape: tuple[int, ...], kind: str) -> BandedField:
        """The :class:`BandedField` of ``seed``, ``shape`` and ``kind``, kept under ``key`` for later bands."""
        k = (key, tuple(shape), kind)
        if k not in self._bands:
            self._bands[k] = BandedField(seed, shape, kind)
        return self._bands[k]

    def field_key(self, stage: str, shape: tuple[int, ...], kind: str) -> bytes:
        """What identifies the whole field of ``stage``, ``shape`` and ``kind`` ('uniform' or 'normal'):
        its seed and shape (the field is a function of them alone)."""
        s = self._seed(stage)
        return repr(("field", kind, s.entropy, tuple(s.spawn_key), tuple(int(n) for n in shape))).encode()

    def uniform(self, stage: str, shape: tuple[int, ...], rows: tuple[int, int] | None = None) -> np.ndarray:
        """The stage's uniform field in (0, 1), float64 of ``shape`` (the same on every call), or its ``rows``.
        Read-only when it comes from :data:`FIELD_MEMO` (on in a sweep)."""
        if rows is None:
            return FIELD_MEMO.fetch(
                self.field_key(stage, shape, "uniform"), lambda: uniform_open(self._rng(stage), shape)
            )
        return self.banded(("stage", stage), self._seed(stage), shape, "uniform").rows(*rows)

    def normal(self, stage: str, shape: tuple[int, ...], rows: tuple[int, int] | None = None) -> np.ndarray:
        """The stage's standard normal field, float64 of ``shape`` (the same on every call), or its ``rows``.
        Read-only when it comes from :data:`FIELD_MEMO` (on in a sweep)."""
        if rows is None:
            return FIELD_MEMO.fetch(
                self.field_key(stage, shape, "normal"), lambda: self._rng(stage).standard_normal(shape)
            )
        return self.banded(("stage", stage), self._seed(stage), shape, "normal").rows(*rows)

    def normal_runs(
        self, stage: str, shape: tuple[int, ...], rows: tuple[int, int] | None = None
    ) -> Iterator[np.ndarray]:
        """:meth:`normal`'s field one leading index at a time, ``normal(stage, shape, rows)[i]`` for i in
        order, each drawn into the same array (valid until the next): the field's values without the
        whole field's memory, which is new memory the system must map and zero first (a 640x512
        capture's read noise: 31 MB, which took longer than the draw)."""
        if rows is None and FIELD_MEMO.entries:  # the whole field, drawn once for the points of a sweep
            yield from self.normal(stage, shape)
            return
        out = np.empty(shape[1:] if rows is None else (rows[1] - rows[0], *shape[2:]))
        if rows is None:  # a normal is one or more 64-bit outputs, nothing buffered: draws continue the stream
            g = self._rng(stage)
            for _ in range(shape[0]):
                g.standard_normal(out=out)
                yield out
            return
        field = self.banded(("stage", stage), self._seed(stage), shape, "normal")
        for a in range(shape[0]):
            yield field.run(a, *rows, out)


def _cornish_fisher(
    z: np.ndarray, mean: np.ndarray, var: np.ndarray, skew: np.ndarray, exkurt: np.ndarray
) -> np.ndarray:
    """Continuous quantile mean + sd * (z + skew (z^2-1)/6 + exkurt (z^3-3z)/24 - skew^2 (2z^3-5z)/36)."""
    z2 = z * z
    w = z + skew * (z2 - 1.0) / 6.0 + z * (exkurt * (z2 - 3.0) / 24.0 - skew * skew * (2.0 * z2 - 5.0) / 36.0)
    return mean + np.sqrt(var) * w


#: Below this variance the expansion in 1/sd diverges; the plain normal quantile starts the walk.
_CF_MIN_VAR = 8.0


def _start(z: np.ndarray, mean: np.ndarray, var: np.ndarray, skew: np.ndarray, exkurt: np.ndarray) -> np.ndarray:
    """Integer starting point of the walk: the continuity-corrected Cornish-Fisher quantile where
    the variance is large enough for it, the normal quantile elsewhere."""
    x = _cornish_fisher(z, mean, var, skew, exkurt)
    small = np.flatnonzero(var < _CF_MIN_VAR)
    x[small] = mean[small] + np.sqrt(var[small]) * z[small]
    return np.maximum(np.ceil(x - 0.5), 0.0)


def _poisson_start(z: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """:func:`_start` for Poisson(lam) (skewness 1/sd, excess kurtosis 1/lam), where the expansion
    reduces to lam + sd z + (z^2 - 1)/6 + z (1 - z^2) / (72 sd): the same starts for half the time,
    evaluated in place."""
    sd = np.sqrt(lam)
    z2 = z * z
    x = 1.0 - z2
    x *= z
    x /= 72.0 * sd
    x += (z2 - 1.0) / 6.0
    x[lam < _CF_MIN_VAR] = 0.0  # the plain normal quantile there, as in _start
    x += sd * z
    x += lam
    x -= 0.5
    np.ceil(x, out=x)
    return np.maximum(x, 0.0, out=x)


#: Above this variance n p (1 - p) the binomial's tails come from the regularized incomplete beta function
#: (scipy's ``betainc``, Boost's) instead of ``bdtr``/``bdtrc`` (cephes), whose error grows with the
#: parameters: measured against ``betainc`` near the mean, 1e-7 of the pmf at a variance of 1e3, 1e-4 at 1e5,
#: 2.4 pmfs at 1e6 (there the walks never settled: a full well of 1e7 electrons and 30 % transfer loss
#: raised "walks do not settle"). ``betainc`` is 1.5x slower at small n and 4.5x at 1.4e7 trials.
_BDTR_MAX_VAR = 1e3


def _binomial_tail(k: np.ndarray, n: np.ndarray, p: float, upper: bool) -> np.ndarray:
    """P(X <= k) (``upper`` False) or P(X > k) of X ~ Binomial(n, p), lane by lane, n float64 integer-valued:
    I_{1-p}(n - k, k + 1) and I_p(k + 1, n - k), by ``bdtr``/``bdtrc`` up to :data:`_BDTR_MAX_VAR`, by
    ``betainc`` above it."""
    out = np.empty(k.size)
    wide = n * p * (1.0 - p) > _BDTR_MAX_VAR
    narrow = np.flatnonzero(~wide)
    if narrow.size:  # scipy's binomial tails take integer trials
        out[narrow] = (special.bdtrc if upper else special.bdtr)(k[narrow], n[narrow].astype(np.int64), p)
    wide = np.flatnonzero(wide)
    if wide.size:
        kw, nw = k[wide], n[wide]
        out[wide] = special.betainc(kw + 1.0, nw - kw, p) if upper else special.betainc(nw - kw, kw + 1.0, 1.0 - p)
    return out


@dataclass(frozen=True)
class DiscreteLaw:
    """The law of each lane of :func:`invert_discrete`: Poisson(``param``) (``p`` unused) or
    Binomial(``param``, ``p``), ``param`` 1-D (one mean or number of trials per lane).

    Its exact tails and pmf are scipy's and :func:`poisson_pmf` (evaluated at the walks' starts
    only); the walk between them steps the pmf by its recurrence pmf(k+1) = pmf(k) * ratio(k), with
    ratio(k) = mean / (k + 1), or max(n - k, 0) / (k + 1) * p / (1 - p) bounded by k <= n. Each method
    takes the lanes it works on: an index array, or ``slice(None)`` for all of them (no copies)."""

    kind: str
    param: np.ndarray
    p: float = 0.0

    def __post_init__(self):
        if self.kind not in ("poisson", "binomial"):
            raise ValueError(f"DiscreteLaw kind: expected 'poisson' or 'binomial', got {self.kind!r}")

    @property
    def binomial(self) -> bool:
        return self.kind == "binomial"

    def tail_gap(self, k: np.ndarray, u: np.ndarray, lanes: np.ndarray | slice) -> np.ndarray:
        """t(k) at ``lanes``: P(X <= k) - u where u <= 1/2, (1 - u) - P(X > k) elsewhere (exact in
        float64 for u > 1/2, so neither tail loses digits). Both rise with k by pmf(k + 1); the
        quantile is the smallest k with t(k) >= 0."""
        a = self.param[lanes]
        lo = u <= 0.5
        # each tail on its own lanes, gathered: a ufunc masked by ``where=`` took a sixth longer per lane
        low, high = np.flatnonzero(lo), np.flatnonzero(~lo)
        t = np.empty(u.size)
        if self.binomial:
            t[low] = _binomial_tail(k[low], a[low], self.p, upper=False) - u[low]
            t[high] = (1.0 - u[high]) - _binomial_tail(k[high], a[high], self.p, upper=True)
        else:
            t[low] = special.pdtr(k[low], a[low]) - u[low]
            t[high] = (1.0 - u[high]) - special.pdtrc(k[high], a[high])
        return t

    def upper(self, lanes: np.ndarray | slice) -> np.ndarray | None:
        """The largest count at ``lanes``: the binomial's n; None (unbounded) for Poisson."""
        return self.param[lanes] if self.binomial else None

    def ratio_up(self, k: np.ndarray, lanes: np.ndarray | slice) -> np.ndarray:
        """pmf(k + 1) / pmf(k) at ``lanes``."""
        if self.binomial:
            return np.maximum(self.param[lanes] - k, 0.0) / (k + 1.0) * (self.p / (1.0 - self.p))
        return self.param[lanes] / (k + 1.0)

    def pmf(self, k: np.ndarray, lanes: np.ndarray | slice) -> np.ndarray:
        """P(X = k) at ``lanes``."""
        if self.binomial:
            # here, not at the top: scipy.stats takes 1.1 s to import, a third of the command line's start
            # (`mbcapture --help`), and only this pmf needs it
            from scipy import stats

            return stats.binom.pmf(k, self.param[lanes], self.p)
        return poisson_pmf(k, self.param[lanes])


def invert_discrete(u: np.ndarray, k0: np.ndarray, law: DiscreteLaw, max_steps: int = 100_000) -> np.ndarray:
    """min{k in [0, upper] : F(k) >= u} for every lane, walking from the integer start ``k0``
    (upper: the binomial's n; unbounded for Poisson).

    ``u`` (in (0, 1)) and ``k0`` are 1-D of the law's length. The tail is evaluated exactly at the
    start (:meth:`DiscreteLaw.tail_gap`) and the walk adds or removes pmf terms from there. A walk
    of more than one step adds pmf terms of very different size (a poor start in a far tail), so
    its lanes are walked again from where they stopped, with the tail evaluated afresh, until no
    lane moves more than one step: the final decision always rests on an exact tail value and at
    most one pmf term. Returns float64 integer counts.
    """
    k = _walk(u, k0, law, slice(None), max_steps)
    moved = np.flatnonzero(np.abs(k - k0) > 1.0)
    for _ in range(64):
        if moved.size == 0:
            return k
        again = _walk(u[moved], k[moved], law, moved, max_steps)
        still = np.abs(again - k[moved]) > 1.0
        k[moved] = again
        moved = moved[still]
    raise RuntimeError("invert_discrete: walks do not settle")


def _walk(u: np.ndarray, k0: np.ndarray, law: DiscreteLaw, lanes: np.ndarray | slice, max_steps: int) -> np.ndarray:
    """One walk of :func:`invert_discrete` from ``k0`` at the law's ``lanes``, with the tail evaluated
    exactly at k0 only. The samplers' starts are the answer in all but about one lane in a thousand,
    so the walks below run on those few: the whole-array work is the tail, the pmf and one comparison."""
    upper = law.upper(lanes)
    k = np.maximum(k0, 0.0) if upper is None else np.clip(k0, 0.0, upper)
    t = law.tail_gap(k, u, lanes)  # rises with k by pmf(k + 1); the answer is the smallest k with t(k) >= 0
    p = law.pmf(k, lanes)
    at = (lambda i: i) if isinstance(lanes, slice) else (lambda i: lanes[i])  # noqa: E731  (law lanes of walk lanes)
    # walking down: t(k-1) = t(k) - pmf(k); walking up: t(k+1) = t(k) + pmf(k+1)
    t_below = t - p
    down = np.flatnonzero((t_below >= 0.0) & (k > 0.0))  # t(k - 1) >= 0 as well: k is not the smallest
    kk, tt, pp = k[down], t_below[down], p[down]
    for _ in range(max_steps):  # here tt = t(kk - 1) >= 0: step down while it is
        if down.size == 0:
            break
        kk = kk - 1.0
        k[down] = kk
        pp = pp / law.ratio_up(kk, at(down))  # pmf(kk) from pmf(kk + 1)
        more = kk > 0.0
        down, kk, tt, pp = down[more], kk[more], tt[more] - pp[more], pp[more]
        go = tt >= 0.0
        down, kk, tt, pp = down[go], kk[go], tt[go], pp[go]
    else:
        raise RuntimeError("invert_discrete: no convergence walking down")
    up = np.flatnonzero(t < 0.0)
    kk, tt, pp = k[up], t[up], p[up]
    for _ in range(max_steps):  # here tt = t(kk) < 0: step up until it is >= 0
        if up.size == 0:
            break
        pp = pp * law.ratio_up(kk, at(up))
        kk, tt = kk + 1.0, tt + pp
        met = (tt >= 0.0) | (pp == 0.0)  # pp == 0: the pmf underflowed, the tail is exhausted
        if upper is not None:
            met |= kk >= upper[up]
        k[up[met]] = kk[met]
        keep = ~met
        up, kk, tt, pp = up[keep], kk[keep], tt[keep], pp[keep]
    else:
        raise RuntimeError("invert_discrete: no convergence walking up")
    return k


def poisson_pmf(k: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """P(X = k) for X ~ Poisson(mean), float64, accurate where both are large.

    Catherine Loader's saddle-point form (2000): pmf = exp(-stirlerr(k) - bd0(k, mean)) /
    sqrt(2 pi k), with stirlerr(k) = log k! - ((k + 1/2) log k - k + log(2 pi)/2) (Stirling's
    series from k = 16 on) and bd0(k, m) = k log(k/m) + m - k = k log1p((k - m)/m) - (k - m),
    whose absolute error is ~1e-16 |k - m|. Measured against 40-digit mpmath: relative error
    below 1e-12 for means 0.1 .. 1e7 within 8 sd (scipy.stats.poisson.pmf: 1.6e-9 at 1e6).
    ``k`` >= 0 integer-valued and ``mean`` > 0 broadcast together; returns a 1-D array.
    """
    k, m = (a.ravel() for a in np.broadcast_arrays(np.asarray(k, np.float64), np.asarray(mean, np.float64)))
    kc = np.maximum(k, 1.0)
    inv2 = 1.0 / (kc * kc)
    stirlerr = (1.0 / 12.0 - (1.0 / 360.0 - (1.0 / 1260.0 - inv2 / 1680.0) * inv2) * inv2) / kc
    few = np.flatnonzero(k < 16.0)  # the series needs k >= 16; below, log k! directly
    kf = kc[few]
    stirlerr[few] = special.gammaln(kf + 1.0) - ((kf + 0.5) * np.log(kf) - kf + _HALF_LOG_2PI)
    d = k - m
    with np.errstate(invalid="ignore", divide="ignore"):  # k = 0 lanes: 0 * log(0), replaced below
        out = np.exp(-stirlerr - (k * np.log1p(d / m) - d)) / np.sqrt(2.0 * np.pi * kc)
    zero = np.flatnonzero(k == 0.0)
    out[zero] = np.exp(-m[zero])
    return out


_HALF_LOG_2PI = 0.5 * np.log(2.0 * np.pi)


#: Lanes inverted at a time. The inversion is per lane (each count depends on its own u and mean
#: only), so inverting in chunks gives the same counts while its dozen temporaries stay near
#: 12 x 8 MB whatever the film: the sensor stage's memory no longer grows with them.
CHUNK_LANES = 1 << 20


#: Threads the inversions may use; None: every core this process may run on. A process that shares
#: its host with others (a Dask worker beside its siblings) sets its share (:func:`set_threads`).
_THREADS: int | None = None


def set_threads(n: int | None) -> None:
    """The threads the Poisson and binomial inversions use in this process (None: every usable core)."""
    global _THREADS
    _THREADS = None if n is None else max(1, int(n))


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _inversion_threads() -> int:
    return usable_cores() if _THREADS is None else _THREADS


def _chunked(fn: Callable[..., np.ndarray], u: np.ndarray, *per_lane: np.ndarray) -> np.ndarray:
    """``fn(u, *per_lane)`` over 1-D lanes, CHUNK_LANES at a time, the chunks on as many threads as
    this process has cores (numpy's and scipy's ufuncs release the GIL), each thread's chunk
    CHUNK_LANES / threads so that the temporaries stay those of one chunk. Per lane, so the counts
    are those of one pass, whatever the threads."""
    if u.size <= CHUNK_LANES:
        return fn(u, *per_lane)
    threads = min(_inversion_threads(), -(-u.size // CHUNK_LANES))
    step = max(CHUNK_LANES // threads, 1)
    out = np.empty(u.size)

    def run(a: int) -> None:
        b = min(a + step, u.size)
        out[a:b] = fn(u[a:b], *(x[a:b] for x in per_lane))

    if threads == 1:
        for a in range(0, u.size, step):
            run(a)
        return out
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="mbcapture-inversion") as pool:
        list(pool.map(run, range(0, u.size, step)))
    return out


def poisson_quantile(u: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Poisson counts by exact inversion: the smallest k with P(X <= k; mean) >= u.

    ``u`` in (0, 1) and ``mean`` >= 0, broadcast together; float64 integer counts of their
    broadcast shape. Means above :data:`POISSON_EXACT_MAX` get the rounded Cornish-Fisher quantile.
    """
    u, lam = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(mean, np.float64))
    return _chunked(_poisson_lanes, u.ravel(), lam.ravel()).reshape(u.shape)


def _poisson_lanes(u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """:func:`poisson_quantile` on 1-D lanes."""
    z = special.ndtri(u)
    big = lam > POISSON_EXACT_MAX
    live = (lam > 0.0) & ~big
    if live.all():  # the usual film: every lane inverted, with no copies of u, z and the means
        return invert_discrete(u, _poisson_start(z, lam), DiscreteLaw("poisson", lam))
    out = np.zeros(u.size)
    if big.any():
        lb = lam[big]
        out[big] = np.rint(_cornish_fisher(z[big], lb, lb, 1.0 / np.sqrt(lb), 1.0 / lb))
    sel = np.flatnonzero(live)
    if sel.size:
        lm = lam[sel]
        out[sel] = invert_discrete(u[sel], _poisson_start(z[sel], lm), DiscreteLaw("poisson", lm))
    return out


def binomial_quantile(u: np.ndarray, n: np.ndarray, p: float) -> np.ndarray:
    """Binomial(n, p) counts by exact inversion: the smallest k with P(X <= k) >= u.

    ``u`` in (0, 1), ``n`` >= 0 integer-valued (float64 or int), ``p`` in [0, 1]; float64
    integer counts of the broadcast shape.
    """
    u, n = np.broadcast_arrays(np.asarray(u, np.float64), np.asarray(n, np.float64))
    if p <= 0.0:
        return np.zeros(u.shape)
    if p >= 1.0:
        return n.copy()
    return _chunked(lambda uu, nn: _binomial_lanes(uu, nn, p), u.ravel(), n.ravel()).reshape(u.shape)


def _binomial_lanes(u: np.ndarray, n: np.ndarray, p: float) -> np.ndarray:
    """:func:`binomial_quantile` on 1-D lanes, 0 < p < 1."""
    out = np.zeros(u.size)
    # P(X != 0) <= n p and P(X != n) <= n (1 - p): below 2^-60 no u in (0, 1) reaches them (u's grid is
    # 2^-53; also keeps scipy's beta functions away from subnormal p, where they overflow)
    out[n * (1.0 - p) < 2.0**-60] = n[n * (1.0 - p) < 2.0**-60]
    sel = np.flatnonzero((n > 0) & (n * p >= 2.0**-60) & (n * (1.0 - p) >= 2.0**-60))
    if sel.size:
        nn, uu = n[sel], u[sel]
        var = nn * p * (1.0 - p)
        sd = np.sqrt(var)
        guess = _start(special.ndtri(uu), nn * p, var, (1.0 - 2.0 * p) / sd, (1.0 - 6.0 * p * (1.0 - p)) / var)
        out[sel] = invert_discrete(uu, np.minimum(guess, nn), DiscreteLaw("binomial", nn, p))
    return out


class ArrayMemo:
    """The last few arrays this process computed, by key: a sweep's points repeat the same sensor work
    (the same seed's noise fields, the same photons), which they take from here instead. Thread-safe;
    entries beyond ``entries`` or ``max_bytes`` are dropped oldest first. Off (``entries`` 0) unless a
    process that repeats work turns it on (:meth:`keep`): a single capture never draws twice, and would
    only pay the keys and hold the copies. ``copies`` True: an array goes in and comes out as a copy
    (the caller may change it); False: it is kept read-only and handed out as is."""

    def __init__(self, entries: int = 0, max_bytes: int = 1 << 30, *, copies: bool = True):
        self.entries, self.max_bytes, self.copies = entries, max_bytes, copies
        self._arrays: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @staticmethod
    def key(*arrays: np.ndarray, prefix: bytes = b"") -> bytes:
        """SHA-256 of ``prefix`` and the arrays' shapes and float64 bytes (CPUs with SHA extensions
        hash at ~2 GB/s: ~35 ms for a 640x512 capture's four buckets)."""
        h = hashlib.sha256(prefix)
        for a in arrays:
            a = np.ascontiguousarray(a, dtype=np.float64)
            h.update(repr(a.shape).encode())
            h.update(memoryview(a).cast("B"))
        return h.digest()

    def get(self, key: bytes) -> np.ndarray | None:
        with self._lock:
            out = self._arrays.get(key)
            if out is None:
                self.misses += 1
                return None
            self._arrays.move_to_end(key)
            self.hits += 1
        return out.copy() if self.copies else out

    def put(self, key: bytes, array: np.ndarray) -> None:
        if self.entries == 0 or array.nbytes > self.max_bytes:
            return
        kept = array.copy() if self.copies else array
        kept.flags.writeable = False
        with self._lock:
            self._arrays[key] = kept
            while len(self._arrays) > self.entries or sum(d.nbytes for d in self._arrays.values()) > self.max_bytes:
                self._arrays.popitem(last=False)

    def fetch(self, key: bytes, make: Callable[[], np.ndarray]) -> np.ndarray:
        """The array kept under ``key``, else ``make()`` (kept when the memo is on)."""
        if self.entries == 0:
            return make()
        out = self.get(key)
        if out is None:
            out = make()
            self.put(key, out)
        return out

    def keep(self, entries: int) -> None:
        """Remember (at least) the last ``entries`` arrays from now on."""
        with self._lock:
            self.entries = max(self.entries, entries)

    def clear(self) -> None:
        with self._lock:
            self._arrays.clear()
            self.hits = self.misses = 0


#: The process's memo of :func:`poisson_quantile_memo`'s draws (a deterministic function of their uniform
#: field and means; off until :meth:`ArrayMemo.keep`: a sweep's workers turn it on).
POISSON_MEMO = ArrayMemo()
#: The process's memo of whole noise fields (:class:`NoiseStreams`, by seed, stage and shape) and fixed
#: patterns (:func:`mbcapture.sensor.readout.fixed_pattern`), handed out read-only; off until a sweep turns
#: it on: a sweep over read noise, full wells or light draws the same fields at every point.
FIELD_MEMO = ArrayMemo(copies=False)


def keep_sensor_work(entries: int = 4) -> None:
    """Turn both memos on in this process (a sweep's worker, whose points repeat the same sensor work)."""
    POISSON_MEMO.keep(entries)
    FIELD_MEMO.keep(2 * entries)


def poisson_quantile_memo(u: np.ndarray, lam: np.ndarray | float, u_key: bytes | None = None) -> np.ndarray:
    """:func:`poisson_quantile`, remembered: the points of a sweep over read noise, full wells or
    the ADC draw the same photons from the same seed and means, and take them from the memo
    instead of inverting again (a new array each call: the caller may change it). ``u_key``: what
    identifies ``u`` (:meth:`NoiseStreams.field_key`), which then is not hashed."""
    if POISSON_MEMO.entries == 0:
        return poisson_quantile(u, lam)
    u = np.asarray(u, dtype=np.float64)
    lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), u.shape)
    key = POISSON_MEMO.key(lam, prefix=u_key) if u_key is not None else POISSON_MEMO.key(u, lam)
    return POISSON_MEMO.fetch(key, lambda: poisson_quantile(u, lam))
