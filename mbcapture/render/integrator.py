"""One-pass per-emitter-group path tracer (a Python ``mi.SamplingIntegrator``).

Light transport is linear in the emitters, so the image of the whole scene is the sum of the
images lit by each emitter group alone. This integrator renders every *requested* group into
its own three channels in one pass over the same paths:

* a unidirectional path tracer, at most ``max_depth`` segments per path (Mitsuba's
  convention: ``max_depth=1`` sees emitters directly, ``2`` adds direct lighting, ...), no
  Russian roulette;
* at every non-specular vertex, next-event estimation towards *every* emitter of every
  requested group (a Python loop over the few emitters: each one is sampled with probability
  1, so there is no emitter-selection noise and no group starves another of samples);
* BSDF-sampled rays that hit an emitter are attributed to that emitter's group, weighted by
  the power heuristic against that emitter's own ``pdf_direction`` (its selection probability
  is 1). Emitters seen directly from the camera get weight 1.
* in Lambertian scenes the path ends at its last vertex that samples light (segment
  ``max_depth - 1``), whose light is then estimated by next-event estimation alone, with weight 1:
  its BSDF-sampled continuation could only have collected emission, at the cost of one more
  intersection per path, and for a Lambertian BSDF light sampling alone is unbiased and nearly as
  good (measured on the metronome at 320x256, 8 pattern keys: the same per-pixel variance to 0.2 %
  at every quantile, 0.914x the time). Other BSDFs keep that bounce (a mirror needs it).
* where the scene declares guides (spheres around small, brightly lit patches that are not
  emitters, :class:`mbcapture.render.build.Guide`) and ``render.guide_fraction`` > 0, that share of
  every Lambertian bounce goes into the cone towards a guide, weighted by the mixture's density
  (:func:`guided_lambertian`), which the MIS weights above use too.

Emitters of groups that are not requested are never sampled, and their emission is ignored
when a path hits them (they still occlude). Without any group requested the kernel would be
empty; the renderer never asks for that.

Random numbers: from the render's sampler (render.sampler), or, after :meth:`use_pattern`, from the
pattern the strata of a capture share (:mod:`mbcapture.render.pattern`): the paths' dimensions and,
in RGB, the camera ray's position in the pixel and on the lens. Either way through
``next_1d(sampler, dim, active)`` and ``next_2d(...)``, which take the sampler as an argument: Dr.Jit's symbolic loop carries the sampler's
state from one vertex to the next only when the loop body names it (a closure calling
``sampler.next_2d`` would draw the same numbers at every vertex).

Output: the film's RGB is the sum over the requested groups, followed by the AOV channels
``<group>.R, <group>.G, <group>.B`` for each requested group, in the requested order.

Spectral variants (``*_spectral``): the path carries a ``mi.Spectrum`` of sampled wavelengths and
only the film's main output is meaningful. AOVs are plain floats that ``specfilm`` stores
without applying its sensitivity curves, so there are none; the renderer requests one group per
pass and reads the film's channels (see :class:`mbcapture.render.Renderer`).

Cost (metronome, 3 groups with one emitter each, max_depth 4, 2-core VM): 1.38x (640x512,
16 spp; 1.44x before the shadow rays were traced only where a light adds something) to 1.8x
(160x128, 4 spp, where Python tracing overhead weighs more) the time of ``mi.render`` with the
built-in ``path`` integrator at equal spp, against about 3x for separate renders per group; so no
fallback to per-group renders is needed (numbers in :class:`mbcapture.render.Renderer`). Where
the time goes at 640x512: without next-event estimation the kernel takes 0.45x its time; without
the shadow rays alone, 0.61x. Three shadow rays per vertex are the price of sampling every
emitter; 'path' samples one, with 1.27x the variance (mean over lit pixels) and 16.6x at the
median pixel (scripts/benchmark.py [2]).

Every material mbcapture builds is Lambertian (:class:`mbcapture.render.build.Material`). For such
scenes (:func:`is_lambertian`, checked on the loaded scene) a vertex's BSDF is evaluated and sampled
from its albedo (:func:`lambertian_shading`): one virtual call into the scene's BSDFs per vertex
instead of one per emitter to evaluate and one to sample, with the same numbers. Measured at 640x512,
2 groups, 7 renders of 16 spp, three runs alternating: 4.94-4.96 s against 5.13-5.31 s through
Mitsuba's calls ('path': 4.52-4.62 s). Any other BSDF takes Mitsuba's calls (:func:`general_shading`).

Mitsuba's Python classes exist per variant, so the class is created by :func:`integrator_class`
after ``mi.set_variant``.
"""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Any, Sequence

from . import pattern
from ..sensor import demodulation
from .aov import NEAR_CLIP_M

#: Name under which the integrator is registered with ``mi.register_integrator``.
PLUGIN_NAME = "mbcapture_groups"

#: The shared pattern's pairs of dimensions for the camera ray's position in the pixel and on the lens
#: (far from the paths', which count up from 0 by vertex).
CAMERA_DIM = 0x7FFF0000


def aov_layout(
    basis: Sequence[str], group_emitters: dict[str, list[Any]]
) -> tuple[list[str], list[list[float]], dict[str, int]]:
    """What one pass renders for the images named ``basis`` (emitter groups, and phasor channels named by
    :func:`mbcapture.sensor.demodulation.basis_name`): the groups to render (those with emitters), each group's
    wavenumbers, and the index of each rendered name's three AOV channels among :meth:`GroupPath.aov_names`
    (a name missing from it renders black)."""
    groups: list[str] = []
    waves: dict[str, list[float]] = {}
    for name in basis:
        parsed = demodulation.parse_basis(name)
        g = name if parsed is None else parsed[0]
        if not group_emitters.get(g):
            continue
        if g not in groups:
            groups.append(g)
        if parsed is not None and parsed[1] not in waves.setdefault(g, []):
            waves[g].append(parsed[1])
    slots = {g: i for i, g in enumerate(groups)}
    n = len(groups)
    for g in groups:
        for k in waves.get(g, []):
            slots[demodulation.basis_name(g, k, "cos")], slots[demodulation.basis_name(g, k, "sin")] = n, n + 1
            n += 2
    return groups, [waves.get(g, []) for g in groups], slots


def emission_hits(emitters, ptrs, si, ds, em_hit, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active, throughput, result):
    """Per group, (``result`` plus the emission the path segment hits, that emission alone), each term its
    throughput x emission x the MIS weight against next-event estimation from the previous vertex (1 after a
    delta BSDF or from the camera)."""
    import drjit as dr
    import mitsuba as mi

    sums, light = [], []
    for acc, ems, eptrs in zip(result, emitters, ptrs):
        alone = mi.Spectrum(0.0)
        for emitter, ptr in zip(ems, eptrs):
            hit = active & (em_hit == ptr)
            em_pdf = emitter.pdf_direction(prev_si, ds, hit & ~prev_bsdf_delta)
            w = dr.select(prev_bsdf_delta, 1.0, mis_power(prev_bsdf_pdf, em_pdf))
            value = emitter.eval(si, hit & (prev_bsdf_pdf > 0))
            term = dr.select(hit, throughput * value * w, 0.0)
            acc = acc + term
            alone = alone + term
        sums.append(acc)
        light.append(alone)
    return sums, light


def phasor_start(scene, ray, phasors: list[list[float]], n_groups: int):
    """The phasor channels' state before a path's first vertex: (waves: (pair index, group, wavenumber) of every
    cos/sin pair, the waves by group, zero sums of L cos(k l) and L sin(k l) a pair, the camera ray's length so
    far). l is the optical length from the camera's centre of projection (the camera ray starts on the near-clip
    plane, NEAR_CLIP_M / cos from it) through every vertex to the point on the emitter. Outside
    :meth:`GroupPath.sample`, whose ``dr.syntax`` rewrite takes no comprehension over tuples."""
    import drjit as dr
    import mitsuba as mi

    waves = [(g, k) for g in range(n_groups) for k in phasors[g]] if phasors else []
    waves = [(i, g, k) for i, (g, k) in enumerate(waves)]
    by_group: list[list[tuple[int, int, float]]] = [[w for w in waves if w[1] == g] for g in range(n_groups)]
    zero = tuple(mi.Spectrum(0.0) for _ in range(2 * len(waves)))
    if not waves:
        return waves, by_group, zero, mi.Float(0.0)
    forward = dr.normalize(scene.sensors()[0].world_transform() @ mi.Vector3f(0.0, 0.0, 1.0))
    length = mi.Float(NEAR_CLIP_M) / dr.maximum(dr.dot(ray.d, forward), 1e-6)
    return waves, by_group, zero, length


def add_phasors(phasor, waves, light, length):
    """``phasor`` plus ``light[group] cos(k length)`` and ``light[group] sin(k length)`` on the cos/sin pair of each
    (pair index, group, k) of ``waves``; a new tuple (Dr.Jit's += is in place)."""
    import drjit as dr

    out = list(phasor)
    for i, g, k in waves:
        s, c = dr.sincos(length * k)
        out[2 * i] = out[2 * i] + light[g] * c
        out[2 * i + 1] = out[2 * i + 1] + light[g] * s
    return tuple(out)


def mis_power(pdf_a: Any, pdf_b: Any) -> Any:
    """Power heuristic (exponent 2) weight of strategy a; 0 where both pdfs are 0."""
    import drjit as dr

    a2 = dr.square(pdf_a)
    w = a2 / (a2 + dr.square(pdf_b))
    return dr.select(dr.isfinite(w), w, 0.0)


#: Mitsuba's class names of the Lambertian BSDFs (:func:`is_lambertian`).
_LAMBERTIAN = "SmoothDiffuse"
_TWOSIDED = "TwoSidedBRDF"


def is_lambertian(scene: Any) -> bool:
    """Whether every shape of the Mitsuba ``scene`` has a Lambertian BSDF: ``diffuse``, or ``twosided``
    with ``diffuse`` on both sides (what :class:`mbcapture.render.build.Material` makes)."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        name = bsdf.class_name()
        if name == _TWOSIDED:
            nested = re.findall(r"brdf\[\d\] = (\w+)\[", str(bsdf))
            if not nested or any(n != _LAMBERTIAN for n in nested):
                return False
        elif name != _LAMBERTIAN:
            return False
    return True


def general_shading(ctx, bsdf, flags, si, active, guides=()):
    """(eval_pdf(wo, ok) -> (value, pdf), sample(u1, u2, ok) -> (wo, pdf, weight, delta)) of the BSDFs
    at ``si`` through Mitsuba's virtual calls: any BSDF (``flags`` and ``guides`` unused: the renderer
    gives guides to Lambertian scenes only)."""
    import mitsuba as mi

    def eval_pdf(wo, ok):
        return bsdf.eval_pdf(ctx, si, wo, ok)

    def sample(u1, u2, ok):
        bs, weight = bsdf.sample(ctx, si, u1, u2, ok)
        return bs.wo, bs.pdf, weight, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

    return eval_pdf, sample


def lambertian_shading(ctx, bsdf, flags, si, active, guides=()):
    """:func:`general_shading` for Lambertian BSDFs (``diffuse``, and ``twosided`` of it, whose
    ``flags`` hold BackSide), computed from the albedo: one virtual call per vertex instead of one per
    emitter (``eval_pdf``) and one to sample. The same numbers as Mitsuba's, operation for operation
    (diffuse.cpp, twosided.cpp): value albedo / pi cos(wo), pdf cos(wo) / pi, a cosine-weighted sample
    of weight albedo, all 0 where wi or wo is on the side the BSDF does not reflect (a one-sided one's
    back; a two-sided one mirrors its front). Written here because Mitsuba offers no batched
    evaluation of one BSDF at several directions. With ``guides``, the bounce is drawn from
    :func:`guided_lambertian`'s mixture instead."""
    import drjit as dr
    import mitsuba as mi

    albedo = bsdf.eval_diffuse_reflectance(si, active)
    cos_i = mi.Frame3f.cos_theta(si.wi)
    two = mi.has_flag(flags, mi.BSDFFlags.BackSide)
    side = dr.select(cos_i > 0.0, 1.0, dr.select(two & (cos_i < 0.0), -1.0, 0.0))  # 0: reflects nothing

    def eval_pdf(wo, ok):
        cos_o = mi.Frame3f.cos_theta(wo) * side  # on the reflecting side's hemisphere (twosided: mirrored)
        ok = ok & (side != 0.0) & (cos_o > 0.0)
        value = albedo * dr.inv_pi * cos_o
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(mi.Vector3f(wo.x, wo.y, cos_o))
        return dr.select(ok, value, 0.0), dr.select(ok, pdf, 0.0)

    def sample(u1, u2, ok):
        wo = mi.warp.square_to_cosine_hemisphere(u2)
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        weight = dr.select(ok & (side != 0.0) & (pdf > 0.0), albedo, 0.0)
        return mi.Vector3f(wo.x, wo.y, wo.z * side), pdf, weight, mi.Bool(False)

    if not guides:
        return eval_pdf, sample
    return guided_lambertian(si, albedo, side, guides)


def guided_lambertian(si, albedo, side, guides):
    """:func:`lambertian_shading`'s pair for a scene with guides: the bounce drawn from a mixture of the
    cosine lobe and, for each guide (centre, radius, share), the cone of directions towards its sphere
    (uniform in solid angle), chosen by the first coordinate of the bounce's own pair so that each
    strategy's samples stay stratified. Its weight is the value over the mixture's density, so it is
    unbiased, and that density is the one the next-event estimation's MIS weights use.

    A guide gets no share at a vertex inside its sphere, one whose sphere lies wholly below the reflecting
    hemisphere, or one that sees it under less than 0.01 rad (the same rule in sampling and density). The
    cone is drawn and tested by 1 - cos and the sine, not the cosine: near 1 a float32 cosine would put
    some of the cone's own samples outside its test, and weigh them as if the cone had not drawn them.
    Written here: Mitsuba has no mixture of a BSDF and a cone, and its cone warp works with the cosine."""
    import drjit as dr
    import mitsuba as mi

    cones = []  # (axis in the local frame, sin^2 and 1 - cos of the half-angle, share at this vertex)
    total = mi.Float(0.0)
    for centre, radius, share in guides:
        to = si.to_local(mi.Vector3f(*centre) - si.p)
        dist2 = dr.squared_norm(to)
        sin2 = dr.minimum(radius * radius / dr.maximum(dist2, 1e-30), 1.0)
        one_minus = sin2 / (1.0 + dr.safe_sqrt(1.0 - sin2))
        axis = to * dr.rsqrt(dr.maximum(dist2, 1e-30))
        below = axis.z * side < -dr.safe_sqrt(sin2)
        share_here = dr.select((sin2 >= 1.0) | (sin2 < 1e-4) | below | (side == 0.0), 0.0, share)
        cones.append((axis, sin2, one_minus, share_here))
        total = total + share_here

    def density(wo):
        """The mixture's density of local direction ``wo``."""
        cos_o = mi.Frame3f.cos_theta(wo) * side  # on the reflecting side's hemisphere (twosided: mirrored)
        pdf = (1.0 - total) * dr.select(cos_o > 0.0, cos_o * dr.inv_pi, 0.0)
        for axis, sin2, one_minus, eps in cones:
            inside = (dr.dot(wo, axis) > 0.0) & (dr.squared_norm(dr.cross(wo, axis)) <= sin2)
            pdf = pdf + dr.select(inside & (eps > 0.0), eps / (dr.two_pi * one_minus), 0.0)
        return pdf

    def eval_pdf(wo, ok):
        cos_o = mi.Frame3f.cos_theta(wo) * side
        ok = ok & (side != 0.0) & (cos_o > 0.0)
        value = albedo * dr.inv_pi * cos_o
        return dr.select(ok, value, 0.0), dr.select(ok, density(wo), 0.0)

    def sample(u1, u2, ok):
        lo = mi.Float(0.0)
        wo = mi.Vector3f(0.0)
        sin_p, cos_p = dr.sincos(dr.two_pi * u2.y)  # the azimuth about every cone's axis
        for axis, sin2, one_minus, eps in cones:
            pick = (u2.x >= lo) & (u2.x < lo + eps)
            om = (u2.x - lo) / dr.maximum(eps, 1e-30) * one_minus  # 1 - cos, uniform in [0, 1 - cos max)
            sin_t = dr.safe_sqrt(om * (2.0 - om))
            d = mi.Frame3f(axis).to_world(mi.Vector3f(cos_p * sin_t, sin_p * sin_t, 1.0 - om))
            wo = dr.select(pick, d, wo)
            lo = lo + eps
        cosine = mi.warp.square_to_cosine_hemisphere(mi.Point2f((u2.x - lo) / (1.0 - lo), u2.y))
        wo = dr.select(u2.x >= lo, mi.Vector3f(cosine.x, cosine.y, cosine.z * side), wo)
        value, pdf = eval_pdf(wo, ok)
        weight = dr.select(pdf > 0.0, value / dr.maximum(pdf, 1e-30), 0.0)
        return wo, pdf, weight, mi.Bool(False)

    return eval_pdf, sample


class GroupPath:
    """The per-group path tracer's methods (see the module doc). Mitsuba's ``SamplingIntegrator`` of the active
    variant exists only once that variant is set (and nanobind's classes take one base), so
    :func:`integrator_class` makes the integrator class then, on that base, with these methods; every method is
    here, at module level, and Mitsuba and Dr.Jit are imported where a method runs."""

    def __init__(self, props: Any) -> None:
        import mitsuba as mi

        mi.SamplingIntegrator.__init__(self, props)
        self.max_depth: int = int(props.get("max_depth", 4))
        if self.max_depth < 1:
            raise ValueError("max_depth must be >= 1")
        self.group_names: list[str] = []
        self.group_emitters: list[list[Any]] = []
        #: per group, the wavenumbers (rad/m) of its phasor channels (:meth:`set_groups`)
        self.phasors: list[list[float]] = []
        self.spectral: bool = bool(mi.is_spectral)
        #: None: every dimension from Mitsuba's sampler. Else (seed, offset, first pixel): the dimensions
        #: from the shared pattern (mbcapture.render.pattern), the sample j of a pixel being the
        #: pattern's sample offset + j (see :meth:`use_pattern`).
        self.pattern: tuple[int, int, int] | None = None
        #: With :attr:`pattern`, for a render of listed pixels: (film pixel, pattern sample) of each lane
        #: (two mi.UInt32 of the wavefront's width), any number of lanes a pixel, the offset included.
        self.pattern_lanes: Any = None
        #: Whether every BSDF of the scenes rendered is Lambertian (:func:`is_lambertian`): then a vertex's
        #: BSDF is evaluated and sampled here from its albedo, one virtual call instead of one per emitter
        #: and one more to sample (:func:`lambertian_shading`). Set by the renderer once its scenes load.
        self.lambertian: bool = False
        #: ((centre xyz, radius, share), ...): the spheres around bright reflectors that a share of the
        #: bounces is sent towards (:func:`guided_lambertian`); Lambertian scenes only. Set by the renderer.
        self.guides: tuple = ()
        #: Whether the path ends at its last vertex that samples light, estimated by light sampling alone
        #: (Lambertian scenes; see the module doc). Set by the renderer with :attr:`lambertian`.
        self.light_alone_at_last: bool = False

    def set_groups(
        self,
        names: Sequence[str],
        emitters: Sequence[Sequence[Any]],
        phasors: Sequence[Sequence[float]] | None = None,
    ) -> None:
        """Choose the groups to render: ``emitters[g]`` are the emitters of ``names[g]``; ``phasors[g]`` the
        wavenumbers k (rad/m) at which group g's light is also written as ``L cos(k l)`` and ``L sin(k l)``,
        l each path's optical length (none by default)."""
        if len(names) != len(emitters) or not names:
            raise ValueError("need one emitter list per group, at least one group")
        if self.spectral and len(names) != 1:
            raise ValueError("spectral variants render one group per pass (no per-group AOVs)")
        phasors = [[] for _ in names] if phasors is None else [[float(k) for k in p] for p in phasors]
        if len(phasors) != len(names) or (self.spectral and any(phasors)):
            raise ValueError("need one wavenumber list per group (RGB variants only)")
        self.group_names = list(names)
        self.group_emitters = [list(e) for e in emitters]
        self.phasors = phasors

    def use_pattern(self, seed: int | None, offset: int = 0, first_pixel: int = 0, lanes: Any = None) -> None:
        """Draw the next renders' samples from the pattern keyed ``seed`` (None: from Mitsuba's
        sampler), sample j of a pixel being the pattern's ``offset + j``; the film's
        pixel 0 is the image's pixel ``first_pixel`` (row-major: a band's first row x width).
        ``lanes`` (film pixel, pattern sample) of each lane, two mi.UInt32: the lanes are those samples
        (:meth:`mbcapture.render.Renderer.render_pixels`), not mi.render's wavefront of the film's rows."""
        self.pattern = None if seed is None else (int(seed) & 0xFFFFFFFF, int(offset), int(first_pixel))
        self.pattern_lanes = None if seed is None else lanes

    def aov_names(self) -> list[str]:
        if self.spectral:
            return []
        names = [f"{g}.{c}" for g in self.group_names for c in "RGB"]
        for gi, ks in enumerate(self.phasors):
            names += [f"phasor{gi}_{j}{part}.{c}" for j in range(len(ks)) for part in "cs" for c in "RGB"]
        return names

    def _draws(self, scene, sampler, ray) -> tuple[Any, Any, Any]:
        """``next_1d(sampler, dim, active)``, ``next_2d(...)`` and the camera ray for :meth:`sample`:
        Mitsuba's sampler (which counts dimensions itself and ignores ``dim``) and ``ray`` as given,
        or the shared pattern and a camera ray through the pattern's position in the pixel."""
        import drjit as dr
        import mitsuba as mi

        if self.pattern is None:
            return (
                (lambda sampler, dim, active: sampler.next_1d(active)),
                (lambda sampler, dim, active: sampler.next_2d(active)),
                ray,
            )
        # mi.render's wavefront: sample_count() consecutive lanes per pixel, pixels row-major
        spp = mi.UInt32(sampler.sample_count())
        seed, offset, first = (mi.UInt32(v) for v in self.pattern)
        dr.make_opaque(spp, seed, offset, first)  # literals would recompile the kernel for every stratum and count
        lane = dr.arange(mi.UInt32, dr.width(ray))
        if self.pattern_lanes is None:
            index, pixel = lane % spp + offset, lane // spp + first
        else:
            pixel, index = (dr.gather(mi.UInt32, a, lane) for a in self.pattern_lanes)
        key = pattern.pixel_key(pixel, seed)

        def next_2d(sampler, dim, active):
            return pattern.pair(dr, mi, index, key, dim)

        if not self.spectral:
            # The camera ray again, through the pattern's point of the pixel (and of the lens): the film's
            # box filter gives the sample to its pixel wherever in it mi.render's own ray fell, and the
            # perspective and thin-lens cameras' ray weight is 1 in RGB, as the film assumed. (Spectral: the
            # ray's wavelengths and their weight are the sampler's, so its ray is kept whole.)
            sensor = scene.sensors()[0]
            size = sensor.film().size()
            y = pixel // size.x
            offset_in_pixel = next_2d(sampler, mi.UInt32(CAMERA_DIM), True)
            pos = (mi.Point2f(mi.Float(pixel - y * size.x), mi.Float(y)) + offset_in_pixel) * mi.ScalarVector2f(
                1.0 / size.x, 1.0 / size.y
            )
            aperture = (
                next_2d(sampler, mi.UInt32(CAMERA_DIM + 1), True) if sensor.needs_aperture_sample() else mi.Point2f(0.5)
            )
            ray, _ = sensor.sample_ray(ray.time, mi.Float(0.5), pos, aperture)
        return (lambda sampler, dim, active: next_2d(sampler, dim, active).x), next_2d, ray

    def sample(self, scene, sampler, ray, medium=None, active=True):
        # A symbolic loop over path vertices: the body (a virtual call into every BSDF of the
        # scene, next-event estimation towards every requested emitter) is traced once, not
        # once per depth, which is what tracing and kernel generation cost grows with.
        import drjit as dr  # noqa: PLC0415  (dr.syntax recompiles this method: its imports are its own)
        import mitsuba as mi  # noqa: PLC0415

        ctx = mi.BSDFContext()
        n_groups = len(self.group_names)
        emitters = self.group_emitters
        ptrs = [[mi.EmitterPtr(e) for e in ems] for ems in emitters]
        max_depth = self.max_depth

        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        depth = mi.UInt32(0)
        throughput = mi.Spectrum(1.0)
        prev_si = dr.zeros(mi.SurfaceInteraction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)
        valid_first = mi.Bool(False)
        result = tuple(mi.Spectrum(0.0) for _ in range(n_groups))
        n_emitters = sum(len(e) for e in emitters)
        next_1d, next_2d, ray = self._draws(scene, sampler, ray)
        waves, waves_of, phasor, path_length = phasor_start(scene, ray, self.phasors, n_groups)
        shading = lambertian_shading if self.lambertian else general_shading
        guides = self.guides

        while dr.hint(active, max_iterations=max_depth, label="mbcapture per-group path"):
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0), active=active)
            valid_first = dr.select(depth == 0, si.is_valid(), valid_first)

            # Emission hit by this segment (camera ray or BSDF sample), per group.
            em_hit = si.emitter(scene, active)
            ds = mi.DirectionSample3f(scene, si, prev_si)
            hit_terms, hit_light = emission_hits(
                emitters, ptrs, si, ds, em_hit, prev_si, prev_bsdf_pdf, prev_bsdf_delta, active, throughput, result
            )
            here = path_length + dr.select(si.is_valid(), si.t, 0.0)  # camera to this vertex
            phasor = add_phasors(phasor, waves, hit_light, here)

            # the last vertex only collects emission
            active_next = active & si.is_valid() & (depth + 1 < max_depth)
            # The last vertex that samples light: its bounce could only collect emission, at a whole
            # intersection's cost. With Lambertian BSDFs light sampling alone estimates that light (MIS
            # weight 1) and the path ends there; a delta BSDF needs the bounce (general_shading).
            last = (depth + 2 >= max_depth) if self.light_alone_at_last else mi.Bool(False)
            bsdf = si.bsdf(ray)
            flags = bsdf.flags()
            eval_pdf, sample_bsdf = shading(ctx, bsdf, flags, si, active_next, guides)

            # Next-event estimation towards every emitter of every requested group.
            active_em = active_next & mi.has_flag(flags, mi.BSDFFlags.Smooth)
            nee_terms = []
            n_em = 0
            for g in range(n_groups):
                acc = hit_terms[g]
                for emitter in emitters[g]:
                    n_em += 1
                    u_em = next_2d(sampler, depth * (n_emitters + 2) + n_em, active_em)
                    ds_em, em_weight = emitter.sample_direction(si, u_em, active_em)
                    ok = active_em & (ds_em.pdf != 0.0)
                    wo = si.to_local(ds_em.d)
                    bsdf_val, bsdf_pdf = eval_pdf(wo, ok)
                    # the shadow ray last, and only where the light would add something (not where
                    # it lies below the surface's hemisphere): the same sums, 4-5 % less time at
                    # 640x512 (three shadow rays per vertex are 40 % of the kernel's time)
                    ok &= dr.any(bsdf_val * em_weight != 0.0)
                    ok &= ~scene.ray_test(si.spawn_ray_to(ds_em.p), ok)
                    w = dr.select(ds_em.delta | last, 1.0, mis_power(ds_em.pdf, bsdf_pdf))
                    term = dr.select(ok, throughput * bsdf_val * em_weight * w, 0.0)
                    acc = acc + term
                    phasor = add_phasors(phasor, waves_of[g], {g: term}, here + ds_em.dist)
                nee_terms.append(acc)
            result = tuple(nee_terms)

            # BSDF sampling: continue the path.
            wo_bsdf, pdf_bsdf, bsdf_weight, delta_bsdf = sample_bsdf(
                next_1d(sampler, depth * (n_emitters + 2), active_next),
                next_2d(sampler, depth * (n_emitters + 2) + n_emitters + 1, active_next),
                active_next,
            )
            throughput = dr.select(active_next, throughput * bsdf_weight, 0.0)
            ray = si.spawn_ray(si.to_world(wo_bsdf))
            prev_si = si
            prev_bsdf_pdf = pdf_bsdf
            prev_bsdf_delta = delta_bsdf
            path_length = here
            active = active_next & ~last & (dr.max(throughput) > 0.0)
            depth += 1

        total = mi.Spectrum(0.0)
        for g in range(n_groups):
            total = total + result[g]  # not '+=': Dr.Jit's += is in place
        aovs = [] if self.spectral else [result[g][c] for g in range(n_groups) for c in range(3)]
        aovs += [value[c] for value in phasor for c in range(3)]
        return total, valid_first, aovs

    def to_string(self) -> str:
        return f"GroupPathIntegrator[max_depth={self.max_depth}, groups={self.group_names}]"


@lru_cache(maxsize=None)
def integrator_class(variant: str) -> type:
    """The integrator class for the active Mitsuba ``variant``: Mitsuba's ``SamplingIntegrator`` with
    :class:`GroupPath`'s methods, its :meth:`GroupPath.sample` through ``dr.syntax`` (a symbolic loop);
    registered as plugin :data:`PLUGIN_NAME` on first call."""
    import drjit as dr
    import mitsuba as mi

    if mi.variant() != variant:
        raise RuntimeError(f"integrator_class({variant!r}) called with variant {mi.variant()!r}")
    methods = {k: v for k, v in vars(GroupPath).items() if k in ("__init__", "__doc__") or not k.startswith("__")}
    cls = type("GroupPathIntegrator", (mi.SamplingIntegrator,), {**methods, "sample": dr.syntax(GroupPath.sample)})
    mi.register_integrator(PLUGIN_NAME, lambda props: cls(props))
    return cls
