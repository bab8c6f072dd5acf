"""Row bands of a film: the unit in which a film is rendered, and tiles made of them.

Why bands: a capture too large for memory is processed in tiles of rows (render, accumulate,
sensor), and a tiled run must equal the untiled one. Mitsuba seeds its sampler per lane of the
wavefront it renders (lane = pixel of the rendered window x sample), so a window of rows does
not reproduce those rows of a whole-film render, except a window that starts at row 0 (its
lanes are the whole film's first lanes: measured bit-identical on llvm_ad_rgb, Mitsuba 3.9.1).
So every film is rendered as the same fixed bands whatever the memory, each band a crop window
with a seed of its own, and a tile is a run of whole bands: then the tiles of any size hold the
same pixels. Band 0 keeps the render's own seed, so a film of one band (at most
:data:`BAND_PIXELS` pixels by default: 640x512 and every test size) renders as it always has.
"""

from __future__ import annotations

import numpy as np

#: Pixels of a render band at most when ``render.band_rows`` is null: about one megapixel, small
#: enough that a band's renders and accumulators stay ~100 MB, large enough that the ~1.2 s of
#: kernel compilation per band and group set is small against its render.
BAND_PIXELS = 1 << 20


def film_bands(
    width: int, height: int, band_rows: int | None = None, whole: bool = False
) -> tuple[tuple[int, int], ...]:
    """The bands (first row, end row) of a ``width`` x ``height`` film: ``band_rows`` rows each (the
    last may be shorter), or, with None, the largest even number of rows within :data:`BAND_PIXELS`
    (even, so that a Bayer mosaic's pattern starts every band in the same phase). ``whole``: one
    band, the film (a lens that mixes neighbouring pixels: distortion, diffraction)."""
    if width < 1 or height < 1:
        raise ValueError(f"film_bands: the film must have positive size, got {width}x{height}")
    if whole:
        return ((0, int(height)),)
    rows = int(band_rows) if band_rows is not None else max(2, (BAND_PIXELS // int(width)) // 2 * 2)
    if rows < 1:
        raise ValueError(f"band rows: expected >= 1, got {band_rows}")
    return tuple((r, min(r + rows, int(height))) for r in range(0, int(height), rows))


def band_seed(seed: int, band: int) -> int:
    """The 32-bit sampler seed of band ``band`` of a render with ``seed``: the seed itself for band
    0, else a SeedSequence hash of (seed, band) (Mitsuba hashes the seed with each lane's index
    (TEA), so distinct seeds give independent lanes)."""
    s = int(seed) & 0xFFFFFFFF
    return s if band == 0 else int(np.random.SeedSequence([s, int(band)]).generate_state(1)[0])


def group_bands(bands: tuple[tuple[int, int], ...], tiles: int) -> tuple[tuple[int, int], ...]:
    """``bands`` gathered into ``tiles`` runs of consecutive bands, as equal in bands as they can be
    (at most one tile per band): the rows (first, end) of each tile."""
    n = max(1, min(int(tiles), len(bands)))
    edges = np.linspace(0, len(bands), n + 1).round().astype(int)
    return tuple((bands[a][0], bands[b - 1][1]) for a, b in zip(edges[:-1], edges[1:]))


__all__ = ["BAND_PIXELS", "band_seed", "film_bands", "group_bands"]
