"""Spectral mode: specfilm with per-channel QE(lambda) lambda/(hc), units checked against numeric
integrals; ``sensor.spectral_response`` validation."""

from __future__ import annotations

import numpy as np
import pytest

from mbcapture.scene import scenes
from mbcapture.config import config_from_dict
from mbcapture.errors import ConfigError
from mbcapture.sensor import (
    SensorConfig,
    electrons_per_film_second,
    electrons_per_radiance_second,
)
from mbcapture.sensor.photons import (
    PLANCK_J_S,
    SPEED_OF_LIGHT_M_PER_S,
    electrons_per_render_second,
)
from mbcapture.sensor.spectral import (
    camera_names,
    channel_quantum_efficiency,
    film_sensitivity,
)

CAMERA = "Nikon 5100 (NPL)"


# -- config ----------------------------------------------------------------------------------
def test_camera_curves_peak_at_quantum_efficiency():
    cfg = SensorConfig(spectral_response=CAMERA, quantum_efficiency=[0.3, 0.6, 0.5])
    wl, qe = channel_quantum_efficiency(cfg)
    assert qe.shape == (3, wl.size)
    np.testing.assert_allclose(qe.max(axis=1), [0.3, 0.6, 0.5])
    wl2, s = film_sensitivity(cfg)
    np.testing.assert_allclose(s, qe * wl * 1e-9 / (PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S))
    assert CAMERA in camera_names()


def test_camera_curves_keep_the_dataset_shape():
    """Each channel's QE curve is the camera's relative curve (peak 1 in the dataset) times that
    channel's quantum_efficiency: the shape is kept point by point (it falls to a few percent at the
    ends of the range), and the effective-wavelength model has no curves to give."""
    import colour

    cfg = SensorConfig(spectral_response=CAMERA, quantum_efficiency=[0.3, 0.6, 0.5])
    wl, qe = channel_quantum_efficiency(cfg)
    msds = colour.MSDS_CAMERA_SENSITIVITIES[CAMERA]
    np.testing.assert_array_equal(wl, msds.wavelengths)
    np.testing.assert_allclose(qe, np.asarray(msds.values).T * np.array([[0.3], [0.6], [0.5]]), rtol=1e-12, atol=0)
    assert np.all(qe.min(axis=1) < 0.05 * qe.max(axis=1))
    with pytest.raises(
        ValueError, match="^spectral_response 'effective_wavelength' has no spectral curves; name a camera$"
    ):
        channel_quantum_efficiency(SensorConfig())


def test_unknown_camera_lists_valid_names():
    with pytest.raises(
        ConfigError, match=r"sensor\.spectral_response.*unknown camera 'Nikon D9'.*effective_wavelength.*Nikon 5100"
    ):
        config_from_dict({"render": {"variant": "llvm_ad_spectral"}, "sensor": {"spectral_response": "Nikon D9"}})


def test_camera_response_needs_spectral_variant():
    with pytest.raises(ConfigError, match=r"render\.variant 'llvm_ad_rgb'"):
        config_from_dict({"sensor": {"spectral_response": CAMERA}})
    with pytest.raises(ConfigError, match=r"needs sensor\.spectral_response to name a camera"):
        config_from_dict({"render": {"variant": "llvm_ad_spectral"}})
    cfg = config_from_dict({"render": {"variant": "cuda_ad_spectral"}, "sensor": {"spectral_response": CAMERA}})
    assert cfg.sensor.spectral_response == CAMERA


def test_render_factor_per_mode():
    cfg = SensorConfig()
    np.testing.assert_array_equal(electrons_per_render_second(cfg, "llvm_ad_rgb"), electrons_per_radiance_second(cfg))
    k = electrons_per_render_second(cfg, "llvm_ad_spectral")
    assert k.shape == (3,) and k.dtype == np.float64  # one factor per channel R, G, B
    np.testing.assert_allclose(k, np.pi * 0.9 / (4 * 2.8**2) * (5.6e-6) ** 2 * 0.5)
    np.testing.assert_array_equal(k, electrons_per_film_second(cfg))


# -- rendering --------------------------------------------------------------------------------
def _flatfield_renderer(radiance, cfg, size=8):
    from mbcapture.render import Renderer

    scene = scenes.make_scene("flatfield", scenes.load_module("flatfield").Params(radiance=radiance))
    return Renderer(scene, size, size, variant="llvm_ad_spectral", max_depth=1, sensor=cfg)


def _emitted_spectrum(renderer, wl_nm):
    """Mitsuba's own spectral radiance of the flat field's environment at ``wl_nm``."""
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, wl_nm.size)
    w = mi.Float(np.asarray(wl_nm, np.float32))
    si.wavelengths = mi.Spectrum(w, w, w, w)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    value = renderer._scene.environment().eval(si)
    return np.asarray(value[0], dtype=np.float64)


@pytest.mark.render
def test_flatfield_spectral_matches_numeric_integral():
    """RGB radiance upsampled by Mitsuba, times the camera response: e-/s within 1 %."""
    cfg = SensorConfig(spectral_response=CAMERA)
    radiance = [0.8, 0.5, 0.3]
    r = _flatfield_renderer(radiance, cfg)
    film = r.render(0.0, spp=256, seed=3)  # (1, H, W, 3)
    rate = film[0].reshape(-1, 3).astype(np.float64).mean(axis=0) * electrons_per_film_second(cfg)

    wl, s = film_sensitivity(cfg)
    grid = np.arange(wl[0], wl[-1] + 0.25, 0.5)
    emitted = _emitted_spectrum(r, grid)
    s_grid = np.stack([np.interp(grid, wl, sc) for sc in s])
    expected = np.trapezoid(s_grid * emitted, grid, axis=1) * electrons_per_film_second(cfg)
    np.testing.assert_allclose(rate, expected, rtol=0.01)
    assert np.all(expected > 0)


@pytest.mark.render
def test_narrowband_constant_spectrum_equals_effective_wavelength_model():
    """A constant spectrum L0 (W m^-2 sr^-1 nm^-1) seen through a narrow band around lambda_c with
    peak QE_c gives the RGB mode's K_c times the in-band radiance L0 * bandwidth."""
    import mitsuba as mi

    from mbcapture.render import Renderer  # noqa: F401  (sets up libLLVM)
    from mbcapture.render.llvm import ensure_llvm

    ensure_llvm()
    mi.set_variant("llvm_ad_spectral")
    cfg = SensorConfig()
    centres, sigma = np.asarray(cfg.wavelength_nm), 2.0
    wl = np.arange(400.0, 660.0 + 1e-9, 0.25)
    shape = np.exp(-0.5 * ((wl[None, :] - centres[:, None]) / sigma) ** 2)  # peak 1 at lambda_c
    qe = shape * np.asarray(cfg.quantum_efficiency)[:, None]
    # the effective-wavelength model: photon energy of lambda_c over the whole (narrow) band
    srf = qe * centres[:, None] * 1e-9 / (PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S)
    film = {"type": "specfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}
    for c, v in zip("RGB", srf):
        film[c] = {
            "type": "regular",
            "wavelength_min": wl[0],
            "wavelength_max": wl[-1],
            "values": ", ".join(repr(float(x)) for x in v),
        }
    L0 = 0.02
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 30,
                "film": film,
                "sampler": {"type": "independent", "sample_count": 1},
            },
            "env": {"type": "constant", "radiance": {"type": "uniform", "value": L0}},
        }
    )
    img = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "direct"}), spp=4096, seed=1), dtype=np.float64)
    rate_spectral = img.reshape(-1, 3).mean(axis=0) * electrons_per_film_second(cfg)
    in_band_radiance = L0 * np.trapezoid(shape, wl, axis=1)  # W m^-2 sr^-1 per channel
    rate_rgb = in_band_radiance * electrons_per_radiance_second(cfg)
    np.testing.assert_allclose(rate_spectral, rate_rgb, rtol=0.01)
