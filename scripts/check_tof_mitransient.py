"""The time-of-flight phasor channels against an independent transient renderer, mitransient.

Two planes (a wall 1 m ahead, albedo 0.5, and a floor 0.3 m below the view reaching from the camera to the
wall, albedo 0.8) lit by a 1 x 1 cm Lambertian LED at the camera: light reaches the wall directly and after a
bounce off the floor. mitransient (``transient_path``, a ``transient_hdr_film`` of 1 mm bins of optical path
length) gives the time-resolved histogram of the centre pixel; its phasor at frequency f is
sum_bins h(l) exp(i 2 pi f l / c). mbcapture's per-group integrator writes the same phasor directly
(``L cos(k l)``, ``L sin(k l)``). Both are Monte Carlo estimates from independent code: they must agree within
their standard errors (over independent seeds).

    python scripts/check_tof_mitransient.py [--seeds 16 --spp 4096]

Prints each component with its standard errors and the z-score of the difference.
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from mbcapture.render.build import Light, Material, SceneBuild, Shape, frame_towards, scale, translate
from mbcapture.scene.scenes import Camera, SceneModel
from mbcapture.sensor.demodulation import C_M_PER_S, basis_name, wavenumber

FREQUENCIES_HZ = (20e6, 100e6)
LED_RADIANCE = 1e4
# optical path lengths 1.8995 .. 4.8995 m in 1 mm bins: the direct path (2.000 m at the centre pixel) in the middle
# of a bin, not on an edge where rounding would put all of it half a bin (1 mrad at 100 MHz) to one side
BINS, START_M, BIN_M = 3000, 1.8995, 0.001
NEAR_CLIP_M = 1e-4  # mitransient's camera rays start here, counting length from it

WALL = translate(0, 0, -1) @ scale(2, 2, 1)
FLOOR = frame_towards((0, -0.3, -0.5), (0, 1, -0.5), up=(0, 0, -1)) @ scale(1, 0.5, 1)
LED = frame_towards((0, 0, 0), (0, 0, -1)) @ scale(0.005, 0.005, 1)


def two_planes_model() -> SceneModel:
    """The scene as mbcapture describes it: group ``led``; a 2-degree camera at the origin looking along -z."""
    shapes = (
        Shape("wall", "rectangle", WALL, Material((0.5,) * 3)),
        Shape("floor", "rectangle", FLOOR, Material((0.8,) * 3)),
        Shape("led", "rectangle", LED, None, Light("led", (LED_RADIANCE,) * 3)),
    )
    cam = Camera(origin=(0.0, 0.0, 0.0), target=(0.0, 0.0, -1.0), up=(0.0, 1.0, 0.0), fov_deg=2.0)
    return SceneModel("two_planes", ("led",), frozenset(), cam, SceneBuild(shapes=shapes), None)


def _mitransient_scene(mi, spp: int):
    def tf(m):
        return mi.ScalarTransform4f(np.asarray(m).tolist())

    def diffuse(v):
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [v] * 3}}

    return mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "transient_path", "max_depth": 3, "camera_unwarp": False},
            "sensor": {
                "type": "perspective",
                "fov": 2.0,
                "fov_axis": "x",
                "near_clip": NEAR_CLIP_M,
                "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
                "film": {
                    "type": "transient_hdr_film",
                    "width": 3,
                    "height": 3,
                    "temporal_bins": BINS,
                    "start_opl": START_M,
                    "bin_width_opl": BIN_M,
                    "rfilter": {"type": "box"},
                },
                "sampler": {"type": "independent", "sample_count": spp},
            },
            "wall": {"type": "rectangle", "to_world": tf(WALL), "bsdf": diffuse(0.5)},
            "floor": {"type": "rectangle", "to_world": tf(FLOOR), "bsdf": diffuse(0.8)},
            "led": {
                "type": "rectangle",
                "to_world": tf(LED),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [LED_RADIANCE] * 3}},
                "bsdf": diffuse(0.0),
            },
        }
    )


def mitransient_phasors(seeds: int, spp: int) -> np.ndarray:
    """(seeds, 1 + 2 F): the centre pixel's light and, per frequency, the real and imaginary parts of its
    histogram's phasor, one row per seed."""
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    import mitransient  # noqa: F401  (registers transient_path and transient_hdr_film)

    scene = _mitransient_scene(mi, spp)
    length = START_M + (np.arange(BINS) + 0.5) * BIN_M + NEAR_CLIP_M  # bin centres, from the camera's centre
    rows = []
    for s in range(seeds):
        _, transient = mi.render(scene, spp=spp, seed=1000 + s)
        h = np.asarray(transient, dtype=np.float64)[1, 1, :, 1]  # (x, y, bin, channel): the centre pixel
        row = [h.sum()]
        for f in FREQUENCIES_HZ:
            p = np.sum(h * np.exp(1j * 2 * math.pi * f / C_M_PER_S * length))
            row += [p.real, p.imag]
        rows.append(row)
    return np.array(rows)


def mbcapture_phasors(seeds: int, spp: int) -> np.ndarray:
    """The same rows from mbcapture's phasor channels (its renderer, the camera's near clip accounted for)."""
    from mbcapture.render import Renderer

    r = Renderer(two_planes_model(), 3, 3, max_depth=3)
    names = ["led"] + [basis_name("led", wavenumber(f), p) for f in FREQUENCIES_HZ for p in ("cos", "sin")]
    return np.stack([r.raw_render(0.0, spp, 11 + s, names)[:, 1, 1, 1].astype(np.float64) for s in range(seeds)])


def compare(seeds: int = 16, spp: int = 4096) -> list[dict]:
    """Per component: both means, their standard errors and the z-score of the difference."""
    a, b = mitransient_phasors(seeds, spp), mbcapture_phasors(seeds, spp)
    names = ["light"] + [f"{part} @ {f / 1e6:g} MHz" for f in FREQUENCIES_HZ for part in ("re", "im")]
    out = []
    for i, name in enumerate(names):
        sa, sb = a[:, i].std(ddof=1) / math.sqrt(seeds), b[:, i].std(ddof=1) / math.sqrt(seeds)
        diff = b[:, i].mean() - a[:, i].mean()
        out.append(
            {
                "component": name,
                "mitransient": a[:, i].mean(),
                "mitransient_se": sa,
                "mbcapture": b[:, i].mean(),
                "mbcapture_se": sb,
                "z": diff / math.hypot(sa, sb),
            }
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--spp", type=int, default=4096)
    args = ap.parse_args()
    print(f"{'component':16s} {'mitransient':>22s} {'mbcapture':>22s} {'z':>6s}")
    for row in compare(args.seeds, args.spp):
        print(
            f"{row['component']:16s} {row['mitransient']:12.6f} +- {row['mitransient_se']:.6f} "
            f"{row['mbcapture']:12.6f} +- {row['mbcapture_se']:.6f} {row['z']:6.2f}"
        )


if __name__ == "__main__":
    main()
