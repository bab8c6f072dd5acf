"""One sample pattern shared by the strata of a capture: scrambled Sobol' pairs, drawn in Dr.Jit.

A static pixel's read sums its strata, which are separate renders. With a pattern of their own
each (Mitsuba's samplers), the strata's samples are stratified each alone but not together; a
pattern shared by the strata, stratum ``k`` taking the samples ``k N .. (k+1) N - 1`` of one long
sequence per pixel, is stratified over their union too (docs/noise.md, "What the median pays
for"). Mitsuba's samplers cannot do that: multijitter's chunks of one pattern are random subsets
of it, and ldsampler shuffles its index.

The sequence, per pixel and per pair of dimensions (written here: no library draws it in Dr.Jit):

* the sample's global index ``g`` is shuffled by a nested scramble of its bits (each output bit
  depends on the input bits above it only), so aligned blocks of 2^m indices map onto aligned
  blocks, and the pairs are decorrelated from one another;
* the shuffled index gives a point of the base-2 (0,2)-sequence (Sobol's first two dimensions:
  van der Corput, and the Pascal matrix), whose aligned blocks of 2^m points are (0,m,2)-nets;
* each coordinate is scrambled by a nested scramble of its own, which keeps the nets and makes
  every point uniform on [0, 1)^2, so every estimate stays unbiased.

The nested scrambles are hash-based, in the bit-reversed domain, where "depends only on the bits
above" becomes "on the bits below": additions and ``x ^= x * even`` have that property. The key
enters only by the first addition and the rest is one fixed bijection F, so a coordinate is
F(brev(x) + key): over a uniform key, uniform on the 2^32 values whatever x (a key-dependent
multiplier after the addition would break that). They are far less random than a full Owen
scramble, which draws a random bit per node of the binary tree; the tests check what the renderer
relies on (uniform marginals, nets in aligned blocks, no correlation between pairs).
"""

from __future__ import annotations

from typing import Any

#: Masks of the superset transform in :func:`sobol_pair`: the bit positions whose k-th bit is 0.
_SUPERSET_MASKS = (0x55555555, 0x33333333, 0x0F0F0F0F, 0x00FF00FF, 0x0000FFFF)

#: Even multipliers of the nested scramble: numpy.random.default_rng(20261127).integers(0, 2**32, 4)
#: with the lowest bit cleared, kept literal so that the sequence does not depend on numpy.
_EVEN = (0xCAEDFD64, 0x5E80D61A, 0x51F0DA98, 0x28FD4F3E)
#: The multipliers of a published 32-bit integer mix (C. Wellons' "lowbias32").
_ODD = (0x7FEB352D, 0x846CA68B)


def hash_u32(x: Any) -> Any:
    """A 32-bit integer mix (xorshift-multiply rounds) of a ``UInt32`` array."""
    x = x ^ (x >> 16)
    x = x * _ODD[0]
    x = x ^ (x >> 15)
    x = x * _ODD[1]
    return x ^ (x >> 16)


def nested_scramble(dr: Any, x: Any, seed: Any) -> Any:
    """A nested (Owen-type) scramble of the bits of ``x`` (UInt32), keyed by ``seed`` (UInt32).

    Output bit b depends on ``seed`` and the input bits at or above b only, so the image of an
    aligned block of 2^m values is an aligned block; over a uniform random ``seed`` every output is
    uniform on 0 .. 2^32 - 1.
    """
    y = dr.brev(x) + seed
    for c in _EVEN:
        y = y ^ (y * c)
    return dr.brev(y)


def sobol_pair(dr: Any, i: Any) -> tuple[Any, Any]:
    """The point ``i`` (UInt32) of the unscrambled (0,2)-sequence, as two UInt32 fractions.

    The second coordinate's digit r (from the top) is the XOR of the index bits c with C(c, r) odd,
    which by Lucas' theorem are the c whose bits include r's: a superset transform over the 5 bits of
    a position, five shift-and-XOR steps on the whole word instead of 32 masked XORs of the direction
    numbers (v_0 = 2^31, v_b = v_{b-1} ^ (v_{b-1} >> 1); the tests compare the two)."""
    t = i
    for k, mask in enumerate(_SUPERSET_MASKS):
        t = t ^ ((t >> (1 << k)) & mask)
    return dr.brev(i), dr.brev(t)


def to_unit(mi: Any, u: Any) -> Any:
    """A UInt32 fraction as a float in [0, 1): its 24 leading bits (exact in single precision)."""
    return mi.Float(u >> 8) * (1.0 / (1 << 24))


def pixel_key(pixel: Any, seed: Any) -> Any:
    """The key of a pixel's sequences (UInt32) in the pattern keyed ``seed`` (UInt32): :func:`pair`'s ``key``."""
    return hash_u32(pixel) ^ hash_u32(seed)


def pair(dr: Any, mi: Any, g: Any, key: Any, dim: Any) -> Any:
    """The 2D sample ``g`` (UInt32 global index) of the sequence keyed ``key`` (UInt32: pattern and
    pixel) for the pair of dimensions ``dim`` (UInt32): a ``Point2f`` in [0, 1)^2."""
    k = hash_u32(key ^ hash_u32(dim + 0x9E3779B9))
    # three keys from one, each hashed on its own so that the three scrambles are unrelated
    k1, k2, k3 = (hash_u32(k + j) for j in (1, 2, 3))
    x, y = sobol_pair(dr, nested_scramble(dr, g, k1))
    return mi.Point2f(to_unit(mi, nested_scramble(dr, x, k2)), to_unit(mi, nested_scramble(dr, y, k3)))
