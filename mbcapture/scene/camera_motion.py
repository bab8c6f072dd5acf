"""Camera motion for any scene: a seeded hand-shake trajectory, or one read from a file.

A handheld camera moves while it captures. ``camera.shake`` gives every scene a moving camera
whose pose at scene time t is the scene's own (nominal) camera perturbed in the camera's frame:

    world_from_camera(t) = L @ translate(tx(t), ty(t), tz(t)) @ Rz(rz(t)) @ Ry(ry(t)) @ Rx(rx(t))

L is the nominal ``look_at`` matrix. The camera frame is Mitsuba's: x points to the image's left,
y to its top, z along the view direction (a right-handed frame); rotations are right-handed about
those axes (rx: pitch, ry: yaw, rz: roll), translations in metres along them.

The hand-shake model
--------------------
Measured hand tremor (physiological tremor) is a narrow band peaking at 8-12 Hz riding on a slow,
larger drift of the hand and arm below ~2 Hz; the power of camera shake lies almost entirely
below ~20-30 Hz. Each of the six offsets here is an independent stationary Gaussian process whose
power spectral density has that shape:

    S(f) = (1 - share) * D(f) + share * P(f),  f in [SHAKE_F_MIN_HZ, SHAKE_F_MAX_HZ]
    D(f) ~ 1 / (1 + (f / drift_corner_hz)^2)              (drift: a low-passed random walk)
    P(f) ~ exp(-(f - tremor_hz)^2 / (2 tremor_width_hz^2))  (the tremor peak)

each normalized to unit variance over the band, ``share`` = ``camera.shake.tremor_share``. The
process is drawn by the spectral representation method: a sum of SHAKE_COMPONENTS sinusoids, one
per frequency bin (bins equally spaced in log frequency, so the slow drift gets as many components
as the tremor; the frequency jittered inside its bin so the trajectory never repeats), of amplitude
sqrt(2 S(f) df) and a uniform random phase, all fixed by ``camera.shake.seed``. The
result is a smooth function of time that can be evaluated at any instant (the planner, the
renderer and every ground truth see the same trajectory), with RMS exactly the configured
amplitude: ``rotation_deg`` for pitch and yaw, ``roll_deg`` for roll, ``translation_mm`` for each
translation. The numbers are the model's defaults, not a measurement of a particular hand.

A trajectory file (``camera.trajectory_file``) is a CSV with the header
``time_s,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm`` (scene time, increasing; rotations in degrees,
translations in millimetres, in the frame above), read with numpy and interpolated linearly
between rows; a capture outside its time range is refused.

What follows from a moving camera (all in this module or through :class:`CameraMotion`):

* the planner bounds the projected motion of the whole frame, not only of the moving parts:
  :meth:`mbcapture.scene.scenes.SceneModel.image_points` adds :func:`reference_points` (rays through a
  3 x 3 grid of pixels at 0.5, 1 and 2 times the camera's target distance, fixed in the world)
  projected through the moving camera, so strata follow shake as well as object motion;
* the renderer sets the sensor's ``to_world`` per render time (opaque, so no kernel recompiles) and
  keys its render cache with the camera's pose (:meth:`mbcapture.render.Renderer.state_at`);
* the moving region (:func:`moving_region`) is the whole frame once the frame
  itself moves more than :data:`FRAME_MOTION_PX` during the capture;
* a still-camera ground truth renders :func:`still` (the scene without camera motion).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol, TypeVar

import numpy as np
from pydantic import Field, field_validator, model_validator

from ..strict import StrictModel
from ..errors import ConfigError
from .projective import Camera, frame


class PosedScene(Protocol):
    """What camera motion needs of a scene (:class:`mbcapture.scene.scenes.SceneModel` has it)."""

    camera: Camera
    camera_motion: "CameraMotion | None"


Scene = TypeVar("Scene", bound=PosedScene)

#: Band of the shake model, Hz.
SHAKE_F_MIN_HZ = 0.1
SHAKE_F_MAX_HZ = 30.0
#: Sinusoids per offset in the spectral representation (log-spaced bins, 2.4 % wide).
SHAKE_COMPONENTS = 240
#: Image motion of the frame (px) over a capture above which the whole frame is its moving region.
FRAME_MOTION_PX = 0.25
#: Header of a trajectory file.
TRAJECTORY_COLUMNS = ("time_s", "rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm")


class ShakeSpec(StrictModel):
    """A seeded hand-shake trajectory (see :mod:`mbcapture.scene.camera_motion`)."""

    rotation_deg: float = Field(
        0.05,
        ge=0,
        le=20,
        description="RMS of the camera's pitch and of its yaw, degrees (each; a hand-held camera: a few hundredths "
        "to a few tenths of a degree).",
    )
    roll_deg: float = Field(0.02, ge=0, le=20, description="RMS of the camera's roll about its view axis, degrees.")
    translation_mm: float = Field(
        0.3, ge=0, le=100, description="RMS of the camera's translation along each of its three axes, millimetres."
    )
    tremor_hz: float = Field(
        10.0, gt=0, le=25, description="Centre of the physiological tremor peak, Hz (measured: 8-12 Hz)."
    )
    tremor_width_hz: float = Field(1.5, gt=0, le=10, description="Standard deviation of the tremor peak, Hz.")
    tremor_share: float = Field(
        0.3, ge=0, le=1, description="Fraction of each offset's variance in the tremor peak; the rest is slow drift."
    )
    drift_corner_hz: float = Field(
        1.0, gt=0, le=20, description="Corner frequency of the drift's low-pass spectrum, Hz."
    )
    seed: int = Field(
        0, ge=0, description="Seed of the trajectory (independent of the run's seed: the same hand in every run)."
    )


class CameraSection(StrictModel):
    """``camera``: how the camera moves during a capture (default: held still), and its lens: depth of
    field, relative illumination, distortion, diffraction."""

    shake: ShakeSpec | None = Field(
        None,
        description="Hand shake: a seeded trajectory of rotation and translation with a hand-tremor spectrum "
        "(camera.shake.*); null: the camera is still.",
    )
    trajectory_file: str | None = Field(
        None,
        description="CSV of the camera's offsets over scene time, header time_s,rx_deg,ry_deg,rz_deg,tx_mm,ty_mm,tz_mm "
        "(camera frame: x image left, y up, z forward); interpolated linearly. Exclusive with camera.shake.",
    )

    vignetting: Literal["none", "cos4"] = Field(
        "none",
        description="Relative illumination of the image plane: 'cos4', the natural vignetting of a thin "
        "lens (cos^4 of each pixel's field angle: the metronome's 40-degree view gets 0.78 at the edges, 0.68 in "
        "the corners); 'none': "
        "as bright in the corners as in the centre (a pinhole).",
    )

    diffraction: bool = Field(
        False,
        description="Blur every render by the diffraction of a circular aperture at sensor.f_number, per channel "
        "at sensor.wavelength_nm (its OTF, on top of the pixel aperture the render already is; mbcapture.scene.optics). "
        "false: a diffraction-free lens.",
    )

    lens: Literal["pinhole", "thin"] = Field(
        "pinhole",
        description="'pinhole' (default): everything sharp, the geometry of the scenes' ground truths. 'thin': a thin "
        "lens with depth of field (Mitsuba's thinlens), aperture radius f / (2 sensor.f_number), focused at "
        "camera.focus_distance_m; at the shipped configs' f/2.8 and 5.6 um it blurs by under a pixel. The "
        "depth AOV stays a pinhole's (docs/camera.md).",
    )
    focus_distance_m: float | None = Field(
        None,
        gt=0,
        description="Distance in metres at which the thin lens (camera.lens: thin) is sharp; null: the "
        "distance from the camera to the point it looks at.",
    )
    focal_length_mm: float | None = Field(
        None,
        gt=0,
        description="Focal length in millimetres; it sets the field of view, 2 atan(W p / 2 f) with W p "
        "the sensor's width (render.width x sensor.pixel_pitch_um), replacing the scene's. null: the scene's field "
        "of view, and the focal length it implies.",
    )

    distortion: list[float] | None = Field(
        None,
        description="Radial lens distortion, Brown-Conrady coefficients [k1] to [k1, k2, k3]: normalized pinhole "
        "position (x, y) lands at (x, y)(1 + k1 r^2 + k2 r^4 + k3 r^6) (k1 < 0 barrel, > 0 pincushion), "
        "resampled from a wider pinhole render, photometry kept. null: none. multi_flash, structured_light "
        "and flash_matting refuse it: their truths are pinhole geometry (docs/camera.md).",
    )

    @field_validator("distortion")
    @classmethod
    def _check_distortion(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (not 1 <= len(v) <= 3 or not all(np.isfinite(x) and abs(x) < 10 for x in v)):
            raise ValueError(f"distortion: expected 1 to 3 finite coefficients [k1, k2, k3] (|k| < 10), got {v}")
        return v

    @model_validator(mode="after")
    def _one_source(self) -> "CameraSection":
        if self.shake is not None and self.trajectory_file is not None:
            raise ValueError("camera.shake and camera.trajectory_file are exclusive: give one")
        return self

    @property
    def moving(self) -> bool:
        return self.shake is not None or self.trajectory_file is not None


# --------------------------------------------------------------------------- trajectories
def shake_psd(f_hz: np.ndarray, spec: ShakeSpec) -> np.ndarray:
    """S(f) of the shake model (1/Hz) at ``f_hz``: drift and tremor each normalized to unit variance
    over [SHAKE_F_MIN_HZ, SHAKE_F_MAX_HZ] (trapezoidal integrals on a fine grid), mixed by
    ``tremor_share``; 0 outside the band."""
    grid = np.linspace(SHAKE_F_MIN_HZ, SHAKE_F_MAX_HZ, 20001)

    def drift(f):
        return 1.0 / (1.0 + (f / spec.drift_corner_hz) ** 2)

    def peak(f):
        return np.exp(-0.5 * ((f - spec.tremor_hz) / spec.tremor_width_hz) ** 2)

    f = np.asarray(f_hz, dtype=np.float64)
    inside = (f >= SHAKE_F_MIN_HZ) & (f <= SHAKE_F_MAX_HZ)
    s = (1 - spec.tremor_share) * drift(f) / np.trapezoid(drift(grid), grid) + spec.tremor_share * peak(
        f
    ) / np.trapezoid(peak(grid), grid)
    return np.where(inside, s, 0.0)


@dataclass(frozen=True)
class ShakeTrajectory:
    """Six offsets (rx, ry, rz rad; tx, ty, tz m) as sums of sinusoids: offset_a(t) = sum_i amp[a, i]
    sin(2 pi freq[a, i] t + phase[a, i])."""

    freq_hz: np.ndarray  # (6, N)
    amp: np.ndarray  # (6, N)
    phase_rad: np.ndarray  # (6, N)

    @classmethod
    def from_spec(cls, spec: ShakeSpec) -> "ShakeTrajectory":
        rng = np.random.default_rng(np.random.SeedSequence(spec.seed, spawn_key=(0x5A4E,)))
        n = SHAKE_COMPONENTS
        edges = np.geomspace(SHAKE_F_MIN_HZ, SHAKE_F_MAX_HZ, n + 1)
        df = np.diff(edges)
        centres = np.sqrt(edges[:-1] * edges[1:])
        rms = np.array(
            [math.radians(spec.rotation_deg)] * 2 + [math.radians(spec.roll_deg)] + [spec.translation_mm * 1e-3] * 3
        )
        freq = edges[:-1][None, :] + rng.random((6, n)) * df[None, :]
        s = shake_psd(centres, spec)
        unit = np.sqrt(2.0 * s * df)
        unit *= 1.0 / np.sqrt(0.5 * (unit**2).sum())  # RMS exactly 1 (sum of a^2 / 2 = variance)
        amp = rms[:, None] * unit[None, :]
        phase = rng.random((6, n)) * 2 * math.pi
        return cls(freq, amp, phase)

    def offsets(self, times_s: np.ndarray, axes: tuple[int, ...] = tuple(range(6))) -> np.ndarray:
        """(T, 6) offsets at scene times ``times_s`` (T,); only ``axes`` are evaluated (the others are 0)."""
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        out = np.zeros((t.size, 6))
        for a in axes:
            if not self.amp[a].any():
                out[:, a] = 0.0
                continue
            out[:, a] = np.sin(2 * math.pi * np.outer(t, self.freq_hz[a]) + self.phase_rad[a]) @ self.amp[a]
        return out


@dataclass(frozen=True)
class FileTrajectory:
    """Offsets read from a trajectory file, interpolated linearly (rad and m)."""

    path: str
    times_s: np.ndarray  # (N,)
    values: np.ndarray  # (N, 6)

    @classmethod
    def read(cls, path: str | Path) -> "FileTrajectory":
        p = Path(path)
        where = f"camera.trajectory_file: {p}"
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(f"{where}: cannot read the file ({exc.strerror})") from None
        lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
        header = tuple(h.strip() for h in lines[0].split(",")) if lines else ()
        if header != TRAJECTORY_COLUMNS:
            raise ConfigError(
                f"{where}: expected the header {','.join(TRAJECTORY_COLUMNS)}, got {','.join(header) or 'nothing'}"
            )
        try:
            data = np.loadtxt(lines[1:], delimiter=",", ndmin=2, dtype=np.float64)
        except ValueError as exc:
            raise ConfigError(f"{where}: not numbers in 7 columns ({exc})") from None
        if data.shape[0] < 2 or data.shape[1] != 7:
            raise ConfigError(f"{where}: expected at least 2 rows of 7 numbers, got {data.shape[0]} rows")
        if not np.all(np.isfinite(data)):
            raise ConfigError(f"{where}: the file holds NaN or infinite values")
        if not np.all(np.diff(data[:, 0]) > 0):
            raise ConfigError(f"{where}: time_s must increase from row to row")
        values = np.concatenate([np.radians(data[:, 1:4]), data[:, 4:7] * 1e-3], axis=1)
        return cls(str(p), data[:, 0].copy(), values)

    def offsets(self, times_s: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
        lo, hi = float(self.times_s[0]), float(self.times_s[-1])
        if t.size and (t.min() < lo or t.max() > hi):
            raise ConfigError(
                f"camera.trajectory_file: {self.path} covers scene times {lo:g}..{hi:g} s, the capture "
                f"needs {t.min():g}..{t.max():g} s"
            )
        return np.stack([np.interp(t, self.times_s, self.values[:, a]) for a in range(6)], axis=1)


# --------------------------------------------------------------------------- poses
def look_at_matrix(camera: Camera) -> np.ndarray:
    """(4, 4) world-from-camera of Mitsuba's ``look_at`` (columns: left, up, view direction, origin)."""
    o, d, right, up = frame(camera)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -right, up, d, o
    return m


def offset_matrices(offsets: np.ndarray) -> np.ndarray:
    """(T, 4, 4) camera-frame perturbations translate(t) @ Rz @ Ry @ Rx from (T, 6) offsets."""
    o = np.asarray(offsets, dtype=np.float64).reshape(-1, 6)
    cx, sx = np.cos(o[:, 0]), np.sin(o[:, 0])
    cy, sy = np.cos(o[:, 1]), np.sin(o[:, 1])
    cz, sz = np.cos(o[:, 2]), np.sin(o[:, 2])
    one, zero = np.ones_like(cx), np.zeros_like(cx)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cx, -sx], -1), np.stack([zero, sx, cx], -1)], -2)
    ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    rz = np.stack([np.stack([cz, -sz, zero], -1), np.stack([sz, cz, zero], -1), np.stack([zero, zero, one], -1)], -2)
    m = np.tile(np.eye(4), (o.shape[0], 1, 1))
    m[:, :3, :3] = rz @ ry @ rx
    m[:, :3, 3] = o[:, 3:]
    return m


def project_through(
    world_from_camera: np.ndarray, points: np.ndarray, fov_deg: float, width: int, height: int
) -> np.ndarray:
    """Pixel coordinates (T, M, 2) (x right, y down, pixel centres at half-integers) of world points
    ``points`` (T, M, 3) seen by a pinhole with horizontal field of view ``fov_deg`` at poses
    ``world_from_camera`` (T, 4, 4): the projection of :meth:`mbcapture.scene.projective.Camera.project`."""
    inv = np.linalg.inv(np.asarray(world_from_camera, dtype=np.float64))
    p = np.asarray(points, dtype=np.float64)
    local = np.einsum("tij,tmj->tmi", inv[:, :3, :3], p) + inv[:, None, :3, 3]
    z = local[..., 2]
    if np.any(z <= 0):
        raise ValueError("a point lies behind the camera")
    tan_half = np.tan(np.radians(fov_deg) / 2)
    px = (-local[..., 0] / z / tan_half * 0.5 + 0.5) * width
    py = (0.5 - local[..., 1] / z / tan_half * 0.5 * width / height) * height
    return np.stack([px, py], axis=-1)


def reference_points(camera: Camera, width: int, height: int) -> np.ndarray:
    """(27, 3) world points fixed in the scene: the nominal camera's rays through a 3 x 3 grid of
    pixels (corners, edge midpoints, centre) at 0.5, 1 and 2 times its target distance. Projected
    through the moving camera, they show how far the frame itself moves."""
    m = look_at_matrix(camera)
    dist = float(np.linalg.norm(np.subtract(camera.target, camera.origin)))
    tan_half = math.tan(math.radians(camera.fov_deg) / 2)
    out = []
    for fx in (0.0, 0.5, 1.0):
        for fy in (0.0, 0.5, 1.0):
            x = -(fx - 0.5) * 2 * tan_half  # image right is camera -x
            y = (0.5 - fy) * 2 * tan_half * height / width
            for depth in (0.5 * dist, dist, 2.0 * dist):
                out.append(m[:3, :3] @ np.array([x * depth, y * depth, depth]) + m[:3, 3])
    return np.array(out)


@dataclass(frozen=True)
class CameraMotion:
    """The camera's offsets over scene time (:class:`ShakeTrajectory` or :class:`FileTrajectory`)
    about the nominal camera; ``label`` names the source for reports."""

    trajectory: ShakeTrajectory | FileTrajectory
    label: str

    def offsets(self, times_s) -> np.ndarray:
        """(T, 6): rx, ry, rz (rad), tx, ty, tz (m) at scene times."""
        return self.trajectory.offsets(times_s)

    def world_from_camera(self, camera: Camera, times_s) -> np.ndarray:
        """(T, 4, 4) camera poses at scene times (Mitsuba's camera frame)."""
        return look_at_matrix(camera)[None] @ offset_matrices(self.offsets(times_s))


def from_config(section: CameraSection, base_dir: Path | None = None) -> CameraMotion | None:
    """The motion ``camera`` asks for, or None for a still camera. A relative trajectory file is
    looked up from the current folder, then from ``base_dir`` (the config file's folder)."""
    if section.shake is not None:
        s = section.shake
        return CameraMotion(
            ShakeTrajectory.from_spec(s),
            f"hand shake (seed {s.seed}): RMS pitch/yaw {s.rotation_deg:g} deg, roll {s.roll_deg:g} deg, "
            f"translation {s.translation_mm:g} mm, tremor {s.tremor_hz:g} Hz ({100 * s.tremor_share:g} % of "
            "the variance)",
        )
    if section.trajectory_file is not None:
        p = Path(section.trajectory_file).expanduser()
        if not p.exists() and base_dir is not None and (base_dir / p).exists():
            p = base_dir / p
        return CameraMotion(FileTrajectory.read(p), f"trajectory file {p}")
    return None


def apply(scene: Scene, section: CameraSection) -> Scene:
    """``scene`` with the camera motion of ``section`` (unchanged for a still camera)."""
    motion = from_config(section)
    return scene if motion is None else dataclasses.replace(scene, camera_motion=motion)


def still(scene: Scene) -> Scene:
    """``scene`` with its camera held at the nominal pose (a still-camera ground truth)."""
    return scene if scene.camera_motion is None else dataclasses.replace(scene, camera_motion=None)


def frame_motion_px(scene: PosedScene, times_s: np.ndarray, width: int, height: int) -> float:
    """How far (px) the frame moves over ``times_s``: the largest diagonal, over the frame's
    :func:`reference_points`, of the box its projections span (0 for a still camera)."""
    if scene.camera_motion is None:
        return 0.0
    pts = reference_points(scene.camera, width, height)
    t = np.atleast_1d(np.asarray(times_s, dtype=np.float64))
    px = project_through(
        scene.camera_motion.world_from_camera(scene.camera, t),
        np.broadcast_to(pts, (t.size, *pts.shape)),
        scene.camera.fov_deg,
        width,
        height,
    )
    return float(np.linalg.norm(px.max(axis=0) - px.min(axis=0), axis=-1).max())


#: The times in a capture's span at which :func:`moving_region` (and the moving parts' shadows) are drawn.
MOVING_REGION_TIMES = 64


def moving_region(scene, t0_s: float, t1_s: float, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels the moving parts cover at some time in [t0, t1].

    At 64 times the convex hull of the projected motion points (grown by 1.5 px) is
    rasterized (:func:`hull_mask`); the union over times is the region swept by the moving parts. With a moving
    camera the parts are projected through its pose at each time, and once the frame itself moves
    more than :data:`mbcapture.scene.camera_motion.FRAME_MOTION_PX` during [t0, t1] every pixel moves: the
    mask is the whole image. The moving parts' shadows are :func:`mbcapture.render.shadows.moving_shadows`'.
    """
    if scene.is_static:
        return np.zeros((height, width), dtype=bool)
    times = np.linspace(t0_s, t1_s, MOVING_REGION_TIMES)
    if frame_motion_px(scene, times, width, height) > FRAME_MOTION_PX:
        return np.ones((height, width), dtype=bool)
    if scene.motion_points is None:
        return np.zeros((height, width), dtype=bool)
    return hull_mask(scene.project(np.asarray(scene.motion_points(times)), times, width, height), width, height)


def hull_mask(point_sets, width: int, height: int) -> np.ndarray:
    """(H, W) bool: the union of the convex hulls of ``point_sets`` (each (M, 2) pixel positions, x right and y
    down; fewer than 3 points or collinear ones: their bounding box), each grown by about 1.5 px (matplotlib's
    ``contains_points`` with radius 3, a stroke of that width, in either orientation), at pixel centres."""
    from matplotlib.path import Path as PolyPath
    from scipy.spatial import ConvexHull, QhullError

    mask = np.zeros((height, width), dtype=bool)
    yy, xx = np.mgrid[0:height, 0:width]
    centres = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], axis=1)
    for pts in point_sets:
        pts = np.asarray(pts, float)
        if len(pts) == 0:
            continue
        try:
            poly = pts[ConvexHull(pts).vertices]
        except (QhullError, ValueError):  # fewer than 3 points or collinear: use the points' bounding box
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            poly = np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]])
        lo, hi = poly.min(axis=0) - 2, poly.max(axis=0) + 2
        near = (centres[:, 0] >= lo[0]) & (centres[:, 0] <= hi[0]) & (centres[:, 1] >= lo[1]) & (centres[:, 1] <= hi[1])
        if near.any():
            inside = PolyPath(poly).contains_points(centres[near], radius=3.0) | PolyPath(poly[::-1]).contains_points(
                centres[near], radius=3.0
            )
            mask.ravel()[np.flatnonzero(near)[inside]] = True
    return mask
