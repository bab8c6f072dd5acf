"""Per-pixel gate codes: each pixel chooses its own bucket for every sub-frame (coded two-bucket
sensors, Wei et al., ECCV 2018).

A global gate schedule sends every pixel's charge to the same bucket in a slot. A coded sensor
keeps a small memory per pixel that selects the active bucket, loaded with a new binary 2D
pattern for each sub-frame: the schedule's slots then name *sub-frames* (0 .. S-1), and the code
says, for every pixel, which bucket (or the drain) collects each sub-frame. No light is blocked:
every sub-frame lands in some bucket of every pixel unless the code drains it.

A :class:`GateCode` is an (S, h, w) tile of 0-based buckets (``DRAIN`` = -1) repeated over the
film; pixel (y, x) follows tile position (y mod h, x mod w). A random code is one tile as large
as the film. The families (:data:`FAMILIES`):

``global``   every pixel follows the schedule's own bucket for each sub-frame (sub-frame s to
             bucket s): today's global gates, written as a code.
``one_hot``  tile position f sends sub-frame f mod S to bucket 1 and every other sub-frame to
             bucket 2 (a near-square tile of at least S positions).
``hadamard`` tile position f sends sub-frame s to bucket 1 where entry (f + 1, s + 1) of the
             Sylvester Hadamard matrix of order n (the smallest power of two > S) is +1, to
             bucket 2 where it is -1: bucket 1 - bucket 2 measures rows of a Hadamard matrix,
             bucket 1 + bucket 2 the sum, so the S sub-frames are recoverable from a tile of n - 1
             positions. Its first row and column (all +1) are left out: no position sends every
             sub-frame to one bucket, and no sub-frame always goes to the same bucket (the S-matrix
             construction of Harwit and Sloane).
``random``   each pixel and sub-frame independently to bucket 1 or 2 with probability 1/2,
             from a seed (one tile the size of the film).
``file``     an array file (.npy, shape (S, h, w), 1-based buckets, 0 = drain), tiled.

Routing (:meth:`GateCode.route`) turns the exposures the renderer accumulated per sub-frame into
per-bucket exposures, pixel by pixel. It is linear and exact in the charge: every sub-frame's
light goes to exactly one store, so the buckets (and the drain) sum to the photodiode's light.
Written by hand: no library models per-pixel gating.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from math import ceil
from pathlib import Path

import numpy as np

from ..errors import ConfigError

DRAIN = -1
FAMILIES = ("global", "one_hot", "hadamard", "random", "file")


@dataclass(frozen=True, eq=False)
class GateCode:
    """``tile`` (S, h, w) int8: the 0-based bucket (or DRAIN) of sub-frame s at tile position (y, x);
    ``n_buckets`` the sensor's buckets; ``family`` how it was made."""

    family: str
    tile: np.ndarray
    n_buckets: int

    def __post_init__(self):
        t = np.asarray(self.tile)
        if t.ndim != 3 or min(t.shape) < 1:
            raise ValueError(f"a gate code's tile is (sub-frames, height, width), got shape {t.shape}")
        if t.min() < DRAIN or t.max() >= self.n_buckets:
            raise ValueError(
                f"a gate code names buckets 0..{self.n_buckets - 1} or the drain, got {t.min()}..{t.max()}"
            )
        t = t.astype(np.int8)
        t.setflags(write=False)
        object.__setattr__(self, "tile", t)

    @property
    def n_subframes(self) -> int:
        return int(self.tile.shape[0])

    @property
    def tile_shape(self) -> tuple[int, int]:
        return int(self.tile.shape[1]), int(self.tile.shape[2])

    @property
    def uniform(self) -> bool:
        """Every pixel follows the same bucket in every sub-frame (a global schedule)."""
        flat = self.tile.reshape(self.n_subframes, -1)
        return bool((flat == flat[:, :1]).all())

    @property
    def identity(self) -> bool:
        """Sub-frame s goes to bucket s in every pixel: the schedule's own global gates."""
        return self.uniform and bool((self.tile[:, 0, 0] == np.arange(self.n_subframes)).all())

    def vectors(self) -> tuple[np.ndarray, np.ndarray]:
        """The distinct per-pixel codes (V, S) and the share of tile positions holding each (V,)."""
        flat = self.tile.reshape(self.n_subframes, -1).T
        vec, counts = np.unique(flat, axis=0, return_counts=True)
        return vec, counts / flat.shape[0]

    def shares(self) -> list[list[Fraction]]:
        """[s][k]: the exact fraction of tile positions that send sub-frame s to bucket k."""
        n = self.tile.shape[1] * self.tile.shape[2]
        return [
            [Fraction(int((self.tile[s] == k).sum()), n) for k in range(self.n_buckets)]
            for s in range(self.n_subframes)
        ]

    def full(self, height: int, width: int) -> np.ndarray:
        """(S, H, W) int8: every pixel's bucket per sub-frame."""
        h, w = self.tile_shape
        reps = (1, -(-height // h), -(-width // w))
        return np.tile(self.tile, reps)[:, :height, :width]

    def route(self, x: np.ndarray | None) -> np.ndarray | None:
        """Per-sub-frame arrays (S, H, W, ...) -> per-bucket arrays (K, H, W, ...): bucket k of pixel
        p sums the sub-frames whose code sends them to k in p, in sub-frame order. Linear (exposures,
        signed Monte Carlo differences, per-group exposures alike); the global identity code returns
        the same numbers, bit for bit."""
        if x is None:
            return None
        x = np.asarray(x)
        if x.shape[0] != self.n_subframes:
            raise ValueError(f"route: {x.shape[0]} sub-frame arrays for a code of {self.n_subframes} sub-frames")
        if self.uniform:  # one bucket per sub-frame everywhere: plain copies and sums, no masks
            out = np.zeros((self.n_buckets,) + x.shape[1:], dtype=x.dtype)
            for k in range(self.n_buckets):
                src = [s for s in range(self.n_subframes) if self.tile[s, 0, 0] == k]
                if len(src) == 1:
                    out[k] = x[src[0]]
                elif src:
                    out[k] = x[src].sum(axis=0)
            return out
        H, W = x.shape[1], x.shape[2]
        code = self.full(H, W).reshape((self.n_subframes, H, W) + (1,) * (x.ndim - 3))
        out = np.zeros((self.n_buckets,) + x.shape[1:], dtype=x.dtype)
        for s in range(self.n_subframes):
            for k in range(self.n_buckets):
                out[k] += np.where(code[s] == k, x[s], 0)
        return out

    def measurement(self, read_sets: list[tuple[int, ...]], height: int, width: int) -> np.ndarray:
        """(R, S, H, W) float64: 1 where read r of pixel p holds sub-frame s (its code sends s to one
        of the read's buckets). A read is then A(p) @ x(p) for the sub-frame images x."""
        code = self.full(height, width)
        return np.stack([np.isin(code, list(r)) for r in read_sets]).astype(np.float64)


def default_tile(positions: int) -> tuple[int, int]:
    """A tile (h, w) for ``positions`` codes: an exact h x w with w <= 2h when there is one (8: 2x4),
    else the near-square tile with room for them (5: 2x3; the extra positions repeat codes)."""
    exact = [
        (h, positions // h) for h in range(1, positions + 1) if positions % h == 0 and h <= positions // h <= 2 * h
    ]
    if exact:
        return exact[-1]
    h = max(1, round(positions**0.5))
    return h, ceil(positions / h)


def _sylvester(n: int) -> np.ndarray:
    h = np.ones((1, 1), dtype=np.int64)
    while h.shape[0] < n:
        h = np.block([[h, h], [h, -h]])
    return h


def _fill(rows: np.ndarray, tile: tuple[int, int]) -> np.ndarray:
    """(F, S) codes per position -> (S, h, w), cycling the rows over the tile's positions."""
    h, w = tile
    idx = np.arange(h * w) % rows.shape[0]
    return rows[idx].T.reshape(rows.shape[1], h, w)


def make_code(
    family: str,
    subframes: int,
    n_buckets: int,
    *,
    width: int,
    height: int,
    tile: tuple[int, int] | None = None,
    seed: int = 0,
    array: np.ndarray | None = None,
) -> GateCode:
    """The gate code of ``family`` for ``subframes`` sub-frames and ``n_buckets`` buckets.
    ConfigError names ``capture.gate_code.<key>`` when it cannot be made."""
    S, K = subframes, n_buckets
    if family == "global":
        if S > K:
            raise ConfigError(
                f"capture.gate_code.family: 'global' sends sub-frame s to bucket s, but the schedule has "
                f"{S} sub-frames and sensor.bucket_count is {K}"
            )
        return GateCode(family, np.arange(S, dtype=np.int8)[:, None, None], K)
    if family == "file":
        if array is None:
            raise ConfigError("capture.gate_code.file: the 'file' family needs an array file")
        a = np.asarray(array)
        if a.ndim != 3 or a.shape[0] != S:
            raise ConfigError(
                f"capture.gate_code.file: expected an array of shape (sub-frames={S}, height, width), got {a.shape}"
            )
        if not np.issubdtype(a.dtype, np.integer) or a.min() < 0 or a.max() > K:
            raise ConfigError(f"capture.gate_code.file: entries must be 1-based buckets 1..{K} or 0 (drain)")
        return GateCode(family, (a - 1).astype(np.int8), K)
    if K < 2:
        raise ConfigError(
            f"capture.gate_code.family: {family!r} sends sub-frames to buckets 1 and 2; sensor.bucket_count is {K}"
        )
    if family == "one_hot":
        rows = np.ones((S, S), dtype=np.int8)  # bucket 2 (index 1) ...
        np.fill_diagonal(rows, 0)  # ... except sub-frame f at position f: bucket 1
        shape = tile or default_tile(S)
        return GateCode(family, _fill(rows, _check_tile(shape, S)), K)
    if family == "hadamard":
        n = 1 << S.bit_length()  # the smallest power of two > S
        rows = np.where(_sylvester(n)[1:, 1 : S + 1] > 0, 0, 1).astype(np.int8)
        shape = tile or default_tile(n - 1)
        return GateCode(family, _fill(rows, _check_tile(shape, n - 1)), K)
    if family == "random":
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0xC2B]))
        return GateCode(family, rng.integers(0, 2, size=(S, height, width), dtype=np.int8), K)
    raise ConfigError(f"capture.gate_code.family: unknown family {family!r}; expected one of {list(FAMILIES)}")


def _check_tile(tile: tuple[int, int], needed: int) -> tuple[int, int]:
    h, w = tile
    if h * w < needed:
        raise ConfigError(f"capture.gate_code.tile: {h}x{w} holds {h * w} positions; this family needs {needed}")
    return h, w


def load_array(path: str | Path) -> np.ndarray:
    """A code array from a .npy file; ConfigError naming capture.gate_code.file when unreadable."""
    p = Path(path)
    try:
        return np.load(p, allow_pickle=False)
    except FileNotFoundError:
        raise ConfigError(f"capture.gate_code.file: {p} does not exist") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"capture.gate_code.file: {p} is not a .npy array ({exc})") from None
