"""The lens (mbcapture.optics): the diffraction OTF of a circular aperture and its application."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mbcapture.optics import apply_diffraction, diffraction_otf


def test_the_otf_of_a_circular_aperture_by_hand():
    # nu = f lambda N: 1 at DC, (2/pi)(acos nu - nu sqrt(1 - nu^2)) below the cutoff, 0 beyond it
    lam_nm, N = 550.0, 4.0
    cutoff = 1.0 / (lam_nm * 1e-6 * N)  # cycles per mm
    f = np.array([0.0, 0.5 * cutoff, cutoff, 2 * cutoff])
    want = [1.0, (2 / math.pi) * (math.acos(0.5) - 0.5 * math.sqrt(0.75)), 0.0, 0.0]
    assert diffraction_otf(f, lam_nm, N) == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("f_number,cycles_per_px", [(2.8, 0.25), (8.0, 0.25), (8.0, 0.4)])
def test_a_sine_target_keeps_the_contrast_the_otf_says(f_number, cycles_per_px):
    """Vertical stripes at a known frequency: the contrast after the filter over the contrast before is
    the OTF at that frequency (fit of a sine of that frequency over the interior, away from the mirrored
    borders); per channel at its own wavelength. Measured agreement 3e-7; tolerance 1e-5 (a wrong
    frequency scale or OTF formula misses by orders of magnitude)."""
    W, H, pitch_um = 256, 32, 5.6
    x = np.arange(W)
    phase = 2 * np.pi * cycles_per_px * x
    img = np.broadcast_to((1.0 + 0.5 * np.cos(phase))[None, :, None], (H, W, 3)).copy()
    lam = [610.0, 540.0, 465.0]
    out = apply_diffraction(img, pitch_um, f_number, lam)
    inner = slice(48, W - 48)
    basis = np.stack([np.ones(W), np.cos(phase), np.sin(phase)], axis=1)[inner]
    f_mm = cycles_per_px / (pitch_um * 1e-3)
    for c in range(3):
        coef, *_ = np.linalg.lstsq(basis, out[H // 2, inner, c], rcond=None)
        contrast = math.hypot(coef[1], coef[2]) / 0.5
        assert coef[0] == pytest.approx(1.0, abs=1e-4)  # the mean is kept (measured within 1.4e-5)
        assert contrast == pytest.approx(float(diffraction_otf(f_mm, lam[c], f_number)), abs=1e-5)


def test_a_flat_field_stays_flat_and_the_wavelengths_must_match_the_channels():
    flat = np.full((2, 20, 24, 3), 3.0)
    assert np.allclose(apply_diffraction(flat, 5.6, 2.8, [600.0, 550.0, 450.0]), 3.0, rtol=1e-12)
    with pytest.raises(ValueError, match="wavelength_nm"):
        apply_diffraction(flat, 5.6, 2.8, [550.0])


@pytest.mark.render
def test_the_renderer_blurs_every_render_by_the_otf():
    """camera.diffraction: each render is the diffraction-free one filtered by apply_diffraction."""
    from mbcapture import scenes
    from mbcapture.render import Renderer
    from mbcapture.sensor import SensorConfig

    scene = scenes.make_scene("colour_chart", scenes.load_module("colour_chart").Params(shake_amplitude_m=0.0))
    sensor = SensorConfig(f_number=11.0)
    sharp = Renderer(scene, 48, 36, sensor=sensor).render(0.0, 4, 1)
    blurred = Renderer(scene, 48, 36, sensor=sensor, diffraction=True).render(0.0, 4, 1)
    want = apply_diffraction(sharp, sensor.pixel_pitch_um, sensor.f_number, sensor.wavelength_nm)
    assert np.allclose(blurred, want, rtol=1e-5, atol=1e-6 * float(sharp.max()))
    assert np.abs(blurred - sharp).max() > 1e-3 * float(sharp.max())  # it did blur
