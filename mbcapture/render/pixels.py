"""Renders of listed pixels (:class:`PixelRendering`, part of :class:`mbcapture.render.Renderer`): adaptive
sampling's refinement and a large film's pilot render only the pixels they need, each with its own sample count and
pattern offset, through Mitsuba's independent sampler (which takes any count) and the shared pattern."""

from __future__ import annotations

import hashlib
from typing import Any

from typing import Sequence

import numpy as np

from .bands import band_seed
from .integrator import aov_layout, CAMERA_DIM
from .pattern import pair as pattern_pair, pixel_key


def aligned(a: np.ndarray) -> np.ndarray:
    """``a``'s values in memory aligned to 64 bytes. Dr.Jit reads a numpy array where it lies, and its kernel
    declares the loads aligned or not by the address: an array from wherever numpy put it compiled the same
    render again (0.19 s at 640x512) whenever its alignment differed from the last's (Dr.Jit's kernel log)."""
    a = np.ascontiguousarray(a)
    buf = np.empty(a.nbytes + 64, np.uint8)
    start = (-buf.ctypes.data) % 64
    out = buf[start : start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


class PixelRendering:
    """The listed-pixel renders of a :class:`~mbcapture.render.Renderer`, which this class is a part of (a mixin:
    its methods use the renderer's scenes, integrator, lens and cache, set up by ``Renderer.__init__``)."""

    @property
    def renders_pixels_alone(self) -> bool:
        """Whether :meth:`render_pixels` renders the listed pixels alone, at a cost in proportion to them: a lens
        acting pixel by pixel. A lens that mixes neighbours (camera.distortion, camera.diffraction) makes it render
        the whole film, the listed pixels' neighbourhoods at their samples and the rest at one."""
        return not self.lens.mixes_pixels

    def render_pixels(
        self,
        t_s: float,
        spp: "int | np.ndarray",
        seed: int,
        groups: Sequence[str],
        pixels: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None" = None,
        cached: bool = False,
    ) -> np.ndarray:
        """Radiance of each requested group at the film pixels ``pixels`` (flat indices y * W + x) only,
        ``spp`` samples each: float32 (len(groups), len(pixels), 3), the same estimator as :meth:`render`
        (box filter: the mean over each pixel's area; the lens and a mono mixture applied), at a
        cost in proportion to the pixels where the lens acts pixel by pixel (:attr:`renders_pixels_alone`).
        Written here because Mitsuba renders whole films
        (or crop rectangles): the camera rays of the listed pixels are generated as ``mi.render`` does
        (the sampler seeded over pixels x spp lanes, spp consecutive lanes per pixel, so its
        stratification is per pixel) and each lane's per-group AOVs (spectral: the film's channels of the
        sample, one pass a group) are summed into its pixel. A lens that mixes neighbours (distortion,
        diffraction) reads pinhole pixels around each listed one: the whole pinhole film is rendered, each
        pixel with the listed pixels' samples in proportion to its weight in them and the rest with one
        (:meth:`_lens_samples`), and put through the lens as a film is, so the value is unbiased and costs
        about one sample of the whole film more.
        ``pattern`` (key, offset): the samples drawn from the shared pattern as :meth:`render` draws them,
        so that a pixel's value is the one a whole-film render with that pattern gives it. With a pattern,
        ``spp`` and the offset may be one per pixel (arrays of the pixels' length): pixel i takes the pattern's
        samples offset[i] .. offset[i] + spp[i] - 1, all pixels in one render (adaptive sampling's tiers).
        ``cached``: kept in the render cache under the pixels' digest, as :meth:`render` keeps a film (the
        pilot's blocks and adaptive sampling's passes, which a run on a warm cache with the same choice of
        pixels reuses)."""
        req = list(groups)
        pix = np.ascontiguousarray(np.asarray(pixels, dtype=np.uint32).ravel())
        counts = np.broadcast_to(np.asarray(spp, np.int64), pix.shape)
        if pattern is None:
            if counts.size and counts.min() != counts.max():
                raise ValueError(
                    "render_pixels: samples per pixel that vary need a pattern (the sampler's "
                    "sequences are spp consecutive lanes a pixel)"
                )
            n = self.sample_count(int(counts.flat[0]) if counts.size else 1)
            counts, offsets = np.full(pix.shape, n, np.int64), None
        else:
            offsets = np.broadcast_to(np.asarray(pattern[1], np.int64), pix.shape)
            if counts.size and (counts.min() < 1 or offsets.min() < 0 or (offsets + counts).max() > 2**32):
                raise ValueError("render_pixels: expected samples >= 1 a pixel and pattern samples within 0 .. 2^32")

        basis = self.basis_of(req)

        def rendered(at: np.ndarray, n: np.ndarray, first: np.ndarray | None, s: int) -> np.ndarray:
            """``_render_pixels`` of pixels ``at`` (the pinhole's, before the lens), kept in the cache if asked;
            phase groups combined after it (:meth:`basis_of`)."""
            pat = None if pattern is None else (pattern[0], first)
            if not cached:
                return self.combined(self._render_pixels(t_s, n, s, basis, at, pat, first), basis, req)
            params = {
                **self._cache_params(n, s, basis, pat),
                "pixels": hashlib.sha256(at.tobytes()).hexdigest(),
                "n_pixels": int(at.size),
            }
            img = self.cached("pixels", t_s, params, lambda: self._render_pixels(t_s, n, s, basis, at, pat, first))
            return self.combined(img, basis, req)

        if self.renders_pixels_alone:
            out = rendered(pix, counts, offsets, seed)
            if self.lens.falloff is not None:
                out = out * self.lens.falloff.reshape(-1)[pix][None, :, None]
            return self._mono_mixed(out)
        # a lens that mixes neighbours: the whole pinhole film, each pixel with the samples that what reads it asks for
        # (its share of them), the rest with one, through the lens as :meth:`render`'s films are
        film = np.arange(self.width * self.height, dtype=np.uint32)
        asked, first = self.lens.samples(pix, counts, offsets)
        if pattern is not None:  # one render: a pixel nothing asks for takes one sample at a place of its own
            start = int(np.random.default_rng(int(seed) & 0xFFFFFFFF).integers(0, 2**31))
            img = rendered(film, np.maximum(asked, 1), np.where(asked > 0, first, start), seed)
        else:  # the sampler's sequences take one count a render: the reached pixels at it, the rest at one
            reached = asked > 0
            img = np.zeros((len(req), film.size, 3), np.float32)
            img[:, reached] = rendered(film[reached], np.full(int(reached.sum()), int(counts.flat[0])), None, seed)
            img[:, ~reached] = rendered(
                film[~reached], np.ones(int((~reached).sum()), np.int64), None, band_seed(seed, 0x5A)
            )
        img = self.lens.apply(img.reshape(len(req), self.height, self.width, 3), 0, self.height)
        return self._mono_mixed(img.reshape(len(req), -1, 3)[:, pix])

    def _render_pixels(
        self,
        t_s: float,
        counts: np.ndarray,
        seed: int,
        req: list[str],
        pix: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None",
        offsets: np.ndarray | None,
    ) -> np.ndarray:
        """:meth:`render_pixels` before the lens's falloff and a mono mixture: ``counts`` samples at each of
        ``pix``, from the pattern's samples ``offsets`` on (with a pattern) or the sampler's (equal counts).
        RGB: every group in one pass (its AOVs); spectral: one pass a group, in the scene whose film samples
        the group's wavelengths (as :meth:`_render`)."""
        out = np.zeros((len(req), pix.size, 3), np.float32)
        self._ensure_loaded()  # the emitters of each group are known once the scene is loaded
        lit, waves, slots = aov_layout(req, self._group_emitters)
        if not lit or pix.size == 0:
            return out
        self.set_time(t_s)
        passes = [[g] for g in lit] if self.spectral else [lit]
        for groups in passes:
            scene, params, emitters = (
                self._scene_of(groups[0])
                if self.spectral
                else (self._scene, self._params, [self._group_emitters[g] for g in groups])
            )
            self._set_rows(params, (0, self.height))  # the rays below address the whole film
            self._integrator.set_groups(groups, emitters, None if self.spectral else waves)
            sums = self._pixel_sums(scene, groups[0] if self.spectral else None, counts, seed, pix, pattern, offsets)
            if self.spectral:
                out[req.index(groups[0])] = sums[:, 0]
                continue
            for name, i in slots.items():
                if name in req:
                    out[req.index(name)] = sums[:, i]
        return out

    def _scene_of(self, group: str) -> tuple[Any, Any, list[list[Any]]]:
        """A spectral group's (scene, its parameters, [its emitters]): its own scene where its emitters share
        one spectral shape (:meth:`~.scene_dicts.SceneDicts.group_spectral_shape`), else the main one."""
        if group in self._group_scenes:
            scene, params, emitters = self._group_scenes[group]
            return scene, params, [emitters]
        return self._scene, self._params, [self._group_emitters[group]]

    def _pixel_sums(
        self,
        scene: Any,
        group: str | None,
        counts: np.ndarray,
        seed: int,
        pix: np.ndarray,
        pattern: "tuple[int, int | np.ndarray] | None",
        offsets: np.ndarray | None,
    ) -> np.ndarray:
        """One pass of :meth:`_render_pixels` in ``scene`` (the integrator's groups set): float64 (pixels,
        groups, 3), each pixel's mean over its samples. ``group``: the spectral group rendered (its scene's film
        curves weigh the wavelengths), None in RGB."""
        mi, dr = self._mi, self._dr
        lanes = int(counts.sum())
        sensor = scene.sensors()[self._sensor_index(pattern)]
        sampler = sensor.sampler().clone()
        key = index = None
        if pattern is None:  # the sampler's sequences: n consecutive lanes a pixel
            n = int(counts[0])
            sampler.set_sample_count(n)
            # the clone would keep the last mi.render's count, and the quasi-Monte Carlo samplers would then
            # stratify over the wrong sequences
            sampler.set_samples_per_wavefront(n)
            self._integrator.use_pattern(None)
            per_pixel = mi.UInt32(n)
            dr.make_opaque(per_pixel)  # a literal would compile a kernel for every count
            slot = dr.arange(mi.UInt32, lanes) // per_pixel
            pixel = dr.gather(mi.UInt32, mi.UInt32(aligned(pix)), slot)
        else:  # the pattern draws every dimension: each lane is told its pixel and its sample of the pattern
            slots = np.repeat(np.arange(pix.size, dtype=np.uint32), counts)
            starts = np.cumsum(counts) - counts
            lane_index = (np.arange(lanes, dtype=np.int64) - np.repeat(starts - offsets, counts)).astype(np.uint32)
            slot, pixel, index = (
                mi.UInt32(aligned(slots)),
                mi.UInt32(aligned(pix[slots])),
                mi.UInt32(aligned(lane_index)),
            )
            self._integrator.use_pattern(int(pattern[0]) & 0xFFFFFFFF, 0, 0, lanes=(pixel, index))
            key = mi.UInt32(int(pattern[0]) & 0xFFFFFFFF)
            dr.make_opaque(key)
        sampler.seed(int(seed) & 0xFFFFFFFF, lanes)
        y = pixel // self.width
        x = pixel - y * self.width
        if self.spectral and pattern is not None:
            # mi.render's spectral camera ray is its sampler's (the integrator cannot redraw its wavelengths and
            # their weight); these lanes have no sampler sequence of their own, so the ray's point in the pixel,
            # the aperture and the wavelengths are the pattern's: the same estimator, stratified across the strata
            draw = lambda d: pattern_pair(dr, mi, index, pixel_key(pixel, key), mi.UInt32(CAMERA_DIM + d))  # noqa: E731
            in_pixel, aperture = draw(0), (draw(1) if sensor.needs_aperture_sample() else mi.Point2f(0.5))
            wavelength = draw(2).x
        else:  # mi.render's order: the point in the pixel, the aperture, the wavelengths (spectral)
            in_pixel = sampler.next_2d()
            aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
            wavelength = sampler.next_1d() if self.spectral else mi.Float(0.0)
        pos = (mi.Point2f(mi.Float(x), mi.Float(y)) + in_pixel) * mi.ScalarVector2f(1.0 / self.width, 1.0 / self.height)
        ray, weight = sensor.sample_ray_differential(sensor.shutter_open(), wavelength, pos, aperture)
        spec, _, aovs = self._integrator.sample(scene, sampler, ray, None, mi.Bool(True))
        if self.spectral:
            values = self._film_values(sensor.film(), group, ray.wavelengths, weight * spec)
        else:
            values = [value * weight[0] for value in aovs]
        C = len(values)
        # the sums' array at a power of two of the pixels (at least 1024): a scatter's kernel holds its target's
        # size as a literal, so a size of its own for every choice of pixels compiled the render anew each call
        acc = dr.zeros(mi.Float, (1 << max(10, int(np.ceil(np.log2(pix.size))))) * C)
        for c, value in enumerate(values):
            dr.scatter_reduce(dr.ReduceOp.Add, acc, value, slot * C + c)
        dr.eval(acc)
        return np.asarray(acc, dtype=np.float64)[: pix.size * C].reshape(pix.size, C // 3, 3) / counts[:, None, None]

    def _film_values(self, film: Any, group: str, wavelengths: Any, spec: Any) -> list[Any]:
        """What ``specfilm`` stores of one sample (its channels), written here because Mitsuba 3.9.1's Python
        binding of ``Film.prepare_sample`` corrupts memory (measured: a segmentation fault). As the film
        does: the sample's value at each wavelength (``spec``, the ray's weight included) over the sum of the
        film's curves there (its wavelength-sampling density; 1 where that is 0), times each channel's
        curve, averaged over the wavelengths. The curves are the film's own (the scene's film description)."""
        mi, dr = self._mi, self._dr
        key = group if group in self._dicts else None  # the groups of the main scene share its film
        if key not in self._film_curves:
            film_dict = self._dicts[key]["sensor"]["film"]
            self._film_curves[key] = [mi.load_dict(film_dict[c]) for c in self.channels]
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wavelengths = wavelengths
        total = film.sensor_response_function().eval(si)
        scaled = spec * dr.select(total != 0.0, dr.rcp(total), 1.0)
        n = dr.size_v(mi.Spectrum)
        out = []
        for curve in self._film_curves[key]:
            weights = curve.eval(si)
            out.append(sum(weights[i] * scaled[i] for i in range(n)) * (1.0 / n))
        return out

    def _sensor_index(self, pattern: tuple[int, int] | None) -> int:
        """The scene's sensor a render uses: :data:`~.scene_dicts.EXACT_SENSOR` (1) where it draws from the shared pattern in
        an RGB variant, else the user's sampler's (0)."""
        return 1 if pattern is not None and not self.spectral else 0
