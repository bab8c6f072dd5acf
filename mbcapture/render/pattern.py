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
  every point uniform on [0, 1)^2 (the first step adds a uniform random integer mod 2^32, the
  rest are bijections), so every estimate stays unbiased.

The nested scrambles are hash-based, in the bit-reversed domain, where "depends only on the bits
above" becomes "on the bits below": additions, multiplications by odd numbers and ``x ^= x * even``
all have that property. They are far less random than a full Owen scramble, which draws a
random bit per node of the binary tree; the tests check what the renderer relies on (uniform
marginals, nets in aligned blocks, no correlation between pairs).
"""

from __future__ import annotations

from typing import Any

#: The 32 direction numbers of Sobol's second dimension (primitive polynomial x + 1): column b of
#: the upper-triangular Pascal matrix mod 2, v_0 = 2^31, v_b = v_{b-1} ^ (v_{b-1} >> 1).
_V = [0x80000000]
for _b in range(1, 32):
    _V.append(_V[-1] ^ (_V[-1] >> 1))
SOBOL_DIM1 = tuple(_V)
del _b, _V

#: Even multipliers of the nested scramble: numpy.random.default_rng(20261127).integers(0, 2**32, 4)
#: with the lowest bit cleared, kept literal so that the sequence does not depend on numpy.
_EVEN = (0xCAEDFD64, 0x5E80D61A, 0x51F0DA98, 0x28FD4F3E)
#: The multipliers of a published 32-bit integer mix (C. Wellons' "lowbias32").
_ODD = (0x7FEB352D, 0x846CA68B)


def hash_u32(dr: Any, x: Any) -> Any:
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
    y = dr.brev(x)
    y = y + seed
    y = y * (hash_u32(dr, seed) | 1)
    for c in _EVEN:
        y = y ^ (y * c)
    return dr.brev(y)


def sobol_pair(dr: Any, mi: Any, i: Any) -> tuple[Any, Any]:
    """The point ``i`` (UInt32) of the unscrambled (0,2)-sequence, as two UInt32 fractions."""
    x = dr.brev(i)
    y = mi.UInt32(0)
    for b, v in enumerate(SOBOL_DIM1):
        y = y ^ dr.select(((i >> b) & 1) != 0, mi.UInt32(v), mi.UInt32(0))
    return x, y


def to_unit(dr: Any, mi: Any, u: Any) -> Any:
    """A UInt32 fraction as a float in [0, 1): its 24 leading bits (exact in single precision)."""
    return mi.Float(u >> 8) * (1.0 / (1 << 24))


def pair(dr: Any, mi: Any, g: Any, key: Any, dim: Any) -> Any:
    """The 2D sample ``g`` (UInt32 global index) of the sequence keyed ``key`` (UInt32: pattern and
    pixel) for the pair of dimensions ``dim`` (UInt32): a ``Point2f`` in [0, 1)^2."""
    k = hash_u32(dr, key ^ hash_u32(dr, dim + 0x9E3779B9))
    k1 = hash_u32(dr, k + 1)
    k2 = hash_u32(dr, k + 2)
    k3 = hash_u32(dr, k + 3)
    x, y = sobol_pair(dr, mi, nested_scramble(dr, g, k1))
    return mi.Point2f(to_unit(dr, mi, nested_scramble(dr, x, k2)), to_unit(dr, mi, nested_scramble(dr, y, k3)))
