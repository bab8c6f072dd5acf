"""Indirect time of flight: the tap model against a brute-force correlation, the phasor channels against
analytic and quadrature phasors, the protocols' timelines, reconstruction and unwrapping, and a plane at
1.000 m through the whole camera."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mbcapture.errors import ConfigError
from script_modules import load_script
from mbcapture.reconstruct.tof import flying_pixels, joint_range_m, phasor_fit, unwrap
from mbcapture.sensor.demodulation import (
    C_M_PER_S,
    DESIGNS,
    basis_name,
    make_demodulation,
    phases_rad,
    wavenumber,
)


def _brute_correlation(theta: float, phi: float, duty: float, waveform: str, contrast: float) -> float:
    """A tap's charge per unit gated time for a path of phase theta, by integrating gate x delayed waveform
    over one period on a fine grid (independent of the Fourier series the model uses)."""
    x = (np.arange(200_000) + 0.5) / 200_000 * 2 * math.pi  # one modulation period, rad
    gate = np.abs(((x - phi + math.pi) % (2 * math.pi)) - math.pi) <= duty * math.pi  # centred on phi
    shifted = (x - theta) % (2 * math.pi)
    if waveform == "sine":
        light = 1 + np.cos(shifted)
    else:  # on for half the period, centred on 0, mean 1
        light = 2.0 * (np.abs(((shifted + math.pi) % (2 * math.pi)) - math.pi) <= math.pi / 2)
    corr = (gate * light).mean() / duty  # per unit of gated time
    return 1 + contrast * (corr - 1)  # the contrast scales the correlation, not the light


@pytest.mark.parametrize("protocol", sorted(DESIGNS))
@pytest.mark.parametrize("waveform", ["sine", "square"])
def test_a_tap_collects_what_a_brute_force_correlation_gives(protocol, waveform):
    design = DESIGNS[protocol]
    demod = make_demodulation("led", [20e6], 4, design, 0.8, waveform, harmonics=15)
    for theta in (0.3, 1.9, 4.4):
        # one path of unit light at phase theta: the basis images L, C_h, S_h
        basis = ["led"] + [basis_name("led", wavenumber(h * 20e6), p) for h in range(1, 16, 2) for p in ("cos", "sin")]
        values = np.array(
            [1.0] + [f(h * theta) for h in range(1, 16, 2) for f in (math.cos, math.sin)],
        )[:, None]
        for g in demod.groups:
            img = demod.combine(values, basis, [g.name])[0, 0]
            want = _brute_correlation(theta, g.phase_rad, design.duty, waveform, 0.8)
            # the square wave truncated at harmonic 15 and the grid: within 1 %
            assert img == pytest.approx(want, abs=0.01 if waveform == "square" else 1e-4)


def test_a_correlation_that_would_go_negative_is_refused():
    with pytest.raises(ConfigError, match="demodulation_contrast"):
        make_demodulation("led", [20e6], 4, DESIGNS["tof_4tap"], 1.0, "square", harmonics=3)


def test_phasor_fit_and_unwrapping_recover_distances_beyond_one_frequency_s_range():
    rng = np.random.default_rng(3)
    freqs = [80e6, 100e6]
    d = rng.uniform(0.2, joint_range_m(freqs) - 0.2, size=500)  # up to 7.3 m; 100 MHz wraps every 1.5 m
    phases = []
    for f in freqs:
        theta = 4 * math.pi * f * d / C_M_PER_S
        phi = np.array(phases_rad(4))
        taps = 50.0 + 20.0 * np.cos(theta[None, :] - phi[:, None])
        fit = phasor_fit(taps, phi)
        np.testing.assert_allclose(fit["amplitude"], 20.0, rtol=1e-9)
        np.testing.assert_allclose(fit["offset"], 50.0, rtol=1e-9)
        phases.append(fit["phase"])
    depth, spread = unwrap(np.stack(phases), freqs, joint_range_m(freqs))
    np.testing.assert_allclose(depth, d, atol=1e-9)
    assert spread.max() < 1e-9
    assert joint_range_m(freqs) == pytest.approx(C_M_PER_S / (2 * 20e6))
    # one frequency wraps: 2.0 m at 100 MHz reads as 2.0 - 1.499 m
    single, _ = unwrap(np.stack(phases[1:]), freqs[1:], 10.0)
    far = d > C_M_PER_S / 2 / 100e6
    assert np.all(single[far] < d[far] - 1.0)


def test_flying_pixels_are_those_between_the_two_surfaces():
    truth = np.full((8, 8), 3.0)
    truth[:, :4] = 1.0  # a depth edge between columns 3 and 4
    depth = truth.copy()
    depth[2, 3] = 2.0  # half way: flying
    depth[5, 4] = 2.9  # near the far surface: not flying
    fly, edge = flying_pixels(depth, np.ones_like(depth, bool), truth, jump_m=0.5)
    assert edge == 16 and fly.sum() == 1 and fly[2, 3]


def _tof_cfg(**sets):
    from mbcapture.config import load_config

    over = [f"{k}={v}" for k, v in sets.items()]
    return load_config("tof_4tap", over)


@pytest.mark.parametrize(
    "protocol,buckets,span_ms",
    [("tof_4tap", 4, 1.0), ("tof_2tap", 4, 1.0), ("tof_2tap_sequential", 2, 5.0), ("tof_1tap", 1, 13.0)],
)
def test_every_design_gives_each_frequency_the_same_on_time(protocol, buckets, span_ms):
    from mbcapture.timing import protocols

    cfg = _tof_cfg(**{"capture.protocol": protocol, "sensor.bucket_count": buckets})
    tl = protocols.build(cfg)
    exposures = [float(tl.read_exposure_ticks(r) * tl.tick_s) for r in tl.reads]
    # each phase's tap collects exposure / phases (x 1/2 for a one-tap pixel, which drains half of each period)
    share = 0.5 if DESIGNS[protocol].taps == 1 else 1.0
    np.testing.assert_allclose(exposures, [1e-3 / 4 * share] * 4, rtol=1e-12)
    assert float((tl.end_tick - tl.start_tick) * tl.tick_s) == pytest.approx(span_ms * 1e-3)
    assert tl.sequential == DESIGNS[protocol].sequential


def test_a_design_without_enough_buckets_or_keys_is_one_line():
    from mbcapture.timing import protocols

    with pytest.raises(ConfigError, match="needs 8 buckets"):
        protocols.build(_tof_cfg(**{"capture.tof.frequencies_mhz": "[80, 100]"}))
    with pytest.raises(ConfigError, match="capture.tof is required"):
        _tof_cfg(**{"capture.tof": "null"})
    with pytest.raises(ConfigError, match="multiple of 4"):
        _tof_cfg(**{"capture.tof.phases": 6})
    with pytest.raises(ConfigError, match="capture.tof.group"):
        from mbcapture.config import scene_of

        scene_of(_tof_cfg(**{"capture.tof.group": "ambient"}))


@pytest.mark.usefixtures("mitsuba_ready")
def test_the_phasor_channels_of_a_plane_carry_its_round_trip():
    """A plane 1.000 m ahead lit from the camera: every pixel's phasor over its light is exp(i k 2 d), d its
    distance (the LED's 1 cm extent changes the path by under 0.1 mm)."""
    from mbcapture.render import Renderer
    from mbcapture.render.aov import render_depth
    from mbcapture.scene.scenes import load_module, make_scene

    params = load_module("tof_room").Params(layout="plane", plane_distance_m=1.0, fov_deg=40.0)
    scene = make_scene("tof_room", params)
    r = Renderer(scene, 16, 12, max_depth=2)
    k = wavenumber(100e6)
    names = ["illuminator", basis_name("illuminator", k, "cos"), basis_name("illuminator", k, "sin")]
    img = r.raw_render(0.0, 64, 5, names)[..., 1].astype(np.float64)
    phase = np.angle((img[1] + 1j * img[2]) / img[0])
    d = render_depth(r, 0.0).distance_m
    want = np.angle(np.exp(1j * k * 2 * d))
    # the pixel's area spans ~1 mm of distance at the edges of the view: the centre ray's phase within 2 mrad
    assert np.abs(np.angle(np.exp(1j * (phase - want)))).max() < 2e-3
    assert d.min() == pytest.approx(1.0, abs=2e-3)


def _quadrature(k: float, n: int = 1200) -> complex:
    """Radiance phasor (L and L exp(i k l)) at the wall point straight ahead, direct plus one bounce off the
    floor: the floor integrated on an n x n/2 midpoint grid (the LED as a point of intensity L_e A cos)."""
    Le, A = 1e4, 1e-4
    p = np.array([0.0, 0.0, -1.0])
    direct = 0.5 / math.pi * Le * A * 1.0 * 1.0 / 1.0  # cos at LED 1, cos at the wall 1, r = 1
    total = direct * np.exp(1j * k * 2.0)
    xs = -1 + (np.arange(n) + 0.5) / n * 2
    zs = -(np.arange(n // 2) + 0.5) / (n // 2)
    X, Z = np.meshgrid(xs, zs)
    x = np.stack([X, np.full_like(X, -0.3), Z], axis=-1)
    dA = (2 / n) * (1 / (n // 2))
    r_lx = np.linalg.norm(x, axis=-1)
    cos_led = -Z / r_lx
    cos_floor_in = 0.3 / r_lx  # floor normal +y, light above it at y = 0
    E = Le * A * cos_led * cos_floor_in / r_lx**2
    to_p = p - x
    r_xp = np.linalg.norm(to_p, axis=-1)
    cos_floor_out = to_p[..., 1] / r_xp
    cos_wall_in = -to_p[..., 2] / r_xp  # wall normal +z; the light arrives travelling in -z
    L_floor = 0.8 / math.pi * E
    integrand = 0.5 / math.pi * L_floor * cos_floor_out * cos_wall_in / r_xp**2
    length = 1.0 + r_xp + r_lx
    total += np.sum(integrand * np.exp(1j * k * length)) * dA
    light = direct + np.sum(integrand) * dA
    return light, total


@pytest.mark.usefixtures("mitsuba_ready")
def test_two_planes_phasor_matches_the_quadrature_within_its_monte_carlo_interval():
    from mbcapture.render import Renderer

    r = Renderer(load_script("check_tof_mitransient").two_planes_model(), 3, 3, max_depth=3)
    ks = [wavenumber(20e6), wavenumber(100e6)]
    names = ["led"] + [basis_name("led", k, p) for k in ks for p in ("cos", "sin")]
    runs = np.stack([r.raw_render(0.0, 1024, 11 + s, names)[:, 1, 1, 1].astype(np.float64) for s in range(8)])
    mean, se = runs.mean(axis=0), runs.std(axis=0, ddof=1) / math.sqrt(len(runs))
    for i, k in enumerate(ks):
        light, phasor = _quadrature(k)
        got = (mean[1 + 2 * i], mean[2 + 2 * i])
        # the pixel's 2 degrees see the wall's radiance vary by ~0.1 %: that and 4 standard errors
        assert mean[0] == pytest.approx(light, rel=2e-3, abs=4 * se[0])
        for g, want, s in zip(got, (phasor.real, phasor.imag), se[1 + 2 * i : 3 + 2 * i]):
            assert abs(g - want) <= 4 * s + 2e-3 * light
        # the bounce turns the phasor: it is not the direct path's alone
        assert abs(np.angle(complex(*got)) - np.angle(np.exp(1j * k * 2.0))) > 5 * max(se[1:].max() / light, 1e-4)


@pytest.mark.usefixtures("mitsuba_ready")
def test_a_plane_at_one_metre_reconstructs_at_one_metre_within_the_predicted_noise(tmp_path):
    from mbcapture import load_config, run_capture

    cfg = load_config(
        "tof_4tap",
        [
            "scene.layout=plane",
            "scene.plane_distance_m=1.0",
            "scene.illuminator_radiance=3e4",
            "render.width=24",
            "render.height=18",
            "render.max_depth=2",
            "sensor.prnu=0",
            "sensor.dsnu_e=0",
        ],
    )
    res = run_capture(cfg, tmp_path / "out", progress=False)
    img = res.app_output.images
    depth, truth, sigma = img["depth"], img["depth_truth"], img["depth_sigma_m"]
    err = depth - truth
    n = err.size
    assert img["depth_valid"].all()
    # the mean error within 4 standard errors of 0; the spread as predicted (chi-square, n - 1 dof, 4 sigma)
    assert abs(err.mean()) < 4 * sigma.mean() / math.sqrt(n)
    ratio = np.mean((err / sigma) ** 2)
    assert abs(ratio - 1) < 4 * math.sqrt(2 / n)
    assert truth.min() == pytest.approx(1.0, abs=1e-3)


@pytest.mark.slow
@pytest.mark.usefixtures("mitsuba_ready")
def test_the_phasor_channels_agree_with_mitransient_s_histogram():
    """mitransient (an independent transient renderer, a test dependency) renders the two planes' time-resolved
    histogram; its phasor at 20 and 100 MHz and its light agree with the phasor channels within 4 standard errors
    of the difference (5 components: a false alarm 3 times in 10 000)."""
    rows = load_script("check_tof_mitransient").compare(seeds=16, spp=4096)
    assert len(rows) == 5
    for row in rows:
        assert abs(row["z"]) < 4, row


def test_a_sweep_shares_renders_between_designs_but_not_their_accumulation():
    """The taps' images are combined from the rendered channels before accumulation: a 4-tap and an interleaved
    2-tap capture render the same images (render_key) but accumulate different ones (group_key: their gates' duty
    differs), as does another demodulation contrast."""
    from mbcapture.sweep.groups import group_key, render_key

    four = _tof_cfg(**{"render.spp": 4, "render.width": 32, "render.height": 24})
    two = _tof_cfg(**{"render.spp": 4, "render.width": 32, "render.height": 24, "capture.protocol": "tof_2tap"})
    dim = _tof_cfg(
        **{"render.spp": 4, "render.width": 32, "render.height": 24, "sensor.tof.demodulation_contrast": 0.6}
    )
    assert render_key(four) == render_key(two) == render_key(dim)
    assert len({group_key(four), group_key(two), group_key(dim)}) == 3


@pytest.mark.slow
@pytest.mark.usefixtures("mitsuba_ready")
def test_one_frequency_shorter_than_the_room_is_a_warning_in_the_report(tmp_path):
    """At 100 MHz alone the phase wraps every 1.50 m; the room reaches 3 m: the run says so (report.json, its
    summary lines, report.html), and the depths past 1.5 m come out wrapped to near ones."""
    import json

    from mbcapture import load_config, run_capture

    cfg = load_config(
        "tof_4tap", ["capture.tof.frequencies_mhz=[100]", "render.width=24", "render.height=18", "render.spp=4"]
    )
    res = run_capture(cfg, tmp_path / "out", progress=False)
    warnings = res.app_output.metrics["warnings"]
    assert len(warnings) == 1 and "1.50 m" in warnings[0] and "second frequency" in warnings[0]
    assert json.loads((tmp_path / "out" / "report.json").read_text())["metrics"]["warnings"] == warnings
    assert "warning: the scene reaches" in (tmp_path / "out" / "report.html").read_text()
    img = res.app_output.images
    far = img["depth_truth"] > 1.6
    assert far.any() and np.all(img["depth"][far & (img["depth_valid"] > 0)] < 1.5)


def test_the_tof_application_names_what_it_needs():
    from mbcapture.apps.tof import tap_groups

    class NotTof:
        scene = type("S", (), {"demodulation": None})()

    with pytest.raises(ConfigError, match="tof_"):
        tap_groups(NotTof())
