"""Sensor parameters (the ``sensor.*`` config section).

Every value has a unit in its name and a description saying whether it comes from the
paper (Wan, Horowitz, Levoy et al.; the quad-bucket sensor of [Wan 12]) or is an
assumption of this project. The paper gives the array (640 x 512), the pixel pitch
(5.6 um) and the bucket count (4); everything electrical is an assumption chosen to be
typical of a 2012-era 5.6 um CMOS global-shutter pixel.

Default exposure check (green channel, see :mod:`mbcapture.sensor.photons`): a mid-grey
surface of radiance 0.3 W m^-2 sr^-1 at f/2.8, tau = 0.9 gives an image-plane irradiance
E = pi L tau / (4 N^2) = 0.0270 W m^-2; times pixel area 3.136e-11 m^2, fill factor 0.5,
QE 0.5, 8 ms and lambda/(h c) = 2.72e18 J^-1 at 540 nm gives ~4600 e-, i.e. 46 % of the
10 000 e- bucket full well: well exposed, not saturated.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from ..strict import StrictModel
from .presets import load_preset
from .spectral import check_spectral_response

__all__ = ["SensorConfig", "TofPixel"]


class TofPixel(StrictModel):
    """An indirect time-of-flight pixel's demodulation (``sensor.tof``; read by the tof_* protocols only)."""

    demodulation_contrast: float = Field(
        0.8,
        gt=0.0,
        le=1.0,
        description="Share of the photo-charge the tap gates route to the right tap at the modulation frequency "
        "(1: ideal; published 2-tap pixels: 0.45 at 50 MHz (TI OPT8241) to 0.9). Scales the correlation, not "
        "the light collected.",
    )
    waveform: Literal["sine", "square"] = Field(
        "sine",
        description="The illuminator's modulation: sine (one harmonic), or square of 50 % duty (odd harmonics "
        "4 / (pi h), rendered up to sensor.tof.harmonics: their aliasing is the 'wiggling' depth error).",
    )
    harmonics: int = Field(
        5,
        ge=1,
        le=15,
        description="Highest harmonic of a square waveform rendered (each odd harmonic costs two channels a "
        "frequency). Unused with sine.",
    )


def _three_per_channel(name: str, values: list[float]) -> list[float]:
    if len(values) != 3:
        raise ValueError(f"{name}: expected 3 values (R, G, B), got {len(values)}")
    return values


class SensorConfig(StrictModel):
    """Physical and electrical parameters of one multi-bucket pixel array."""

    preset: str | None = Field(
        None,
        description="Fill the sensor keys from a preset; keys set beside it win. A shipped preset's name "
        "(wan2012_quad_bucket: the paper's sensor; two_bucket; global_shutter_cmos: a conventional one-bucket "
        "sensor; each value's source is commented in mbcapture/sensor/presets/NAME.yaml), or a path (relative to "
        "the working directory) to a YAML file of sensor keys or to a datasheet written by mbcapture characterize "
        "(characterization.json). null: the keys below as set.",
    )
    bucket_count: int = Field(
        4,
        ge=1,
        le=64,
        description="Number of charge-storage buckets per pixel (paper: the quad-bucket sensor of [Wan 12] has 4).",
    )
    pixel_pitch_um: float = Field(
        5.6, gt=0, le=100, description="Pixel pitch in micrometres (paper: 5.6 um). Pixel area = pitch^2."
    )
    f_number: float = Field(2.8, gt=0.3, le=128, description="Lens f-number N, dimensionless (assumption).")
    lens_transmittance: float = Field(
        0.9, gt=0, le=1, description="Lens transmittance tau, fraction of light passed, dimensionless (assumption)."
    )
    fill_factor: float = Field(
        0.5,
        gt=0,
        le=1,
        description="Effective optical fill factor including the microlens, fraction of the pixel area "
        "(assumption; a 4-bucket pixel spends area on storage gates).",
    )
    quantum_efficiency: list[float] = Field(
        default_factory=lambda: [0.40, 0.50, 0.45],
        description="Quantum efficiency per colour channel R, G, B including the colour filter, "
        "electrons per photon (assumption).",
    )
    wavelength_nm: list[float] = Field(
        default_factory=lambda: [600.0, 540.0, 460.0],
        description="Effective wavelength per channel R, G, B in nanometres, used for the photon energy "
        "h c / lambda in RGB rendering mode (assumption).",
    )
    spectral_response: str = Field(
        "effective_wavelength",
        description="Per-channel spectral response. 'effective_wavelength': one wavelength (sensor.wavelength_nm) and "
        "one quantum efficiency per channel, the RGB variants' model. Otherwise a camera of colour-science's "
        "colour.MSDS_CAMERA_SENSITIVITIES (e.g. 'Nikon 5100 (NPL)'), each curve scaled to peak at the "
        "channel's quantum_efficiency, applied exactly by a *_spectral render.variant (required). "
        "docs/camera.md.",
    )
    full_well_e: float = Field(
        10_000.0,
        gt=0,
        description="Capacity of each bucket in electrons (assumption). Charge above it is drained by the "
        "anti-blooming gate and lost; the affected reads are flagged saturated.",
    )
    fd_full_well_e: float = Field(
        40_000.0,
        gt=0,
        description="Capacity of the floating diffusion (output bucket) in electrons (assumption). A read "
        "that sums buckets on it clips there and is flagged saturated.",
    )
    read_noise_e: float = Field(
        3.0, ge=0, description="Read noise in electrons rms, added once per read (paper's R; value an assumption)."
    )
    gain_dn_per_e: float = Field(
        0.4,
        gt=0,
        description="Conversion gain in digital numbers per electron (assumption; maps the floating-diffusion "
        "full well to about the ADC range).",
    )
    adc_bits: int = Field(14, ge=1, le=24, description="ADC resolution in bits; codes 0 .. 2^bits - 1 (assumption).")
    black_level_dn: float = Field(256.0, ge=0, description="Offset added before quantization, in DN (assumption).")
    dark_current_e_per_s: float = Field(
        10.0,
        ge=0,
        description="Dark current in electrons per second per bucket during storage (assumption; room temperature).",
    )
    frame_readout_s: float = Field(
        1.0 / 30.0,
        ge=0,
        description="Gap between frames of a conventional sequential capture, in seconds: the time to read "
        "one frame out (assumption: 30 frames/s). Used by the sequential protocols' timelines.",
    )
    prnu: float = Field(
        0.01,
        ge=0,
        lt=1,
        description="Photo-response non-uniformity: std of the per-pixel relative sensitivity, fraction "
        "(assumption; 1 %). Fixed pattern: identical in every bucket and read.",
    )
    dsnu_e: float = Field(
        1.0,
        ge=0,
        description="Dark-signal non-uniformity: std of a per-pixel fixed offset in electrons, added to "
        "every read (assumption). Fixed pattern: identical in every read.",
    )
    prnu_row: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="PRNU's row component (EMVA 1288 R4.0): std of a relative sensitivity shared by every pixel "
        "of a row (row drivers), multiplying the pixel one; fraction. 0: none. Fixed pattern.",
    )
    prnu_col: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="PRNU's column component: std of a relative gain shared by every pixel of a column (column "
        "amplifiers); fraction. 0: none. Fixed pattern.",
    )
    dsnu_row_e: float = Field(
        0.0,
        ge=0,
        description="DSNU's row component: std of an offset in electrons shared by every pixel of a row, added to "
        "every read. 0: none. Fixed pattern.",
    )
    dsnu_col_e: float = Field(
        0.0,
        ge=0,
        description="DSNU's column component: std of an offset in electrons shared by every pixel of a column "
        "(column amplifiers, ADCs), added to every read. 0: none. Fixed pattern.",
    )
    read_noise_row_e: float = Field(
        0.0,
        ge=0,
        description="Temporal row noise: std in electrons of an offset drawn anew for each row at each read "
        "(shared by the row's pixels: horizontal banding), besides read_noise_e. 0: none.",
    )
    cfa: Literal["none", "RGGB", "BGGR", "GRBG", "GBRG", "mono"] = Field(
        "none",
        description="Colour filter array. none: R, G and B at every pixel (three stacked photosites, the paper's model). "
        "RGGB, BGGR, GRBG, GBRG: a Bayer mosaic named by its 2x2 tile, each photosite one channel with its "
        "own noise and full well, every read demosaiced (sensor.demosaic) and DNGs keeping the mosaic. mono: "
        "one response, the channels' sum; everything grey. docs/camera.md.",
    )
    demosaic: Literal["bilinear", "malvar2004", "menon2007"] = Field(
        "menon2007",
        description="Demosaicing of a Bayer sensor's reads and HDR merges (colour-demosaicing): bilinear; malvar2004, "
        "gradient-corrected linear kernels; menon2007, directional filtering (the fewest colour fringes: "
        "figure camera_cfa). Applied in a logarithmic domain, so a bright neighbour cannot push a dark pixel "
        "negative. A demosaiced pixel is flagged saturated when a photosite within 1, 2 or 8 photosites is "
        "(docs/camera.md).",
    )
    transfer_inefficiency: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Fraction of each electron that fails to move from its bucket to the floating diffusion "
        "when read (binomial loss; 0 = ideal; typical 1e-4 .. 1e-3; assumption).",
    )
    parasitic_light: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Parasitic light sensitivity: a bucket collects this fraction of the photo-electrons "
        "generated while the other buckets of the same pixel are gated (0 = ideal; global-shutter storage "
        "nodes typically 1e-4 .. 1e-3; assumption).",
    )
    fpn_seed: int = Field(
        0,
        ge=0,
        description="Seed of the fixed-pattern noise (PRNU, DSNU) maps: it identifies one physical sensor, so "
        "the maps are identical across reads and captures made with it (assumption).",
    )
    noise_seed: int | None = Field(
        None,
        ge=0,
        description="Seed of the temporal noise of the capture (shot, transfer and read noise). null: derived "
        "from the top-level seed. The renders depend on the top-level seed only, so changing noise_seed draws new "
        "noise on the same (cached) renders.",
    )

    tof: TofPixel = Field(
        default_factory=TofPixel,
        description="Indirect time-of-flight demodulation (the tof_* protocols; docs/tof.md).",
    )

    @model_validator(mode="before")
    @classmethod
    def _fill_from_preset(cls, data):
        if isinstance(data, dict) and data.get("preset") is not None:
            if not isinstance(data["preset"], str):
                raise ValueError(f"preset: expected a preset name or a file path, got {data['preset']!r}")
            data = {**load_preset(data["preset"]), **data}
        return data

    @field_validator("quantum_efficiency")
    @classmethod
    def _check_qe(cls, v: list[float]) -> list[float]:
        _three_per_channel("quantum_efficiency", v)
        if not all(0.0 < q <= 1.0 for q in v):
            raise ValueError(f"quantum_efficiency: each value must be in (0, 1], got {v}")
        return v

    @field_validator("wavelength_nm")
    @classmethod
    def _check_wavelength(cls, v: list[float]) -> list[float]:
        _three_per_channel("wavelength_nm", v)
        if not all(200.0 <= w <= 2000.0 for w in v):
            raise ValueError(f"wavelength_nm: each value must be in [200, 2000] nm, got {v}")
        return v

    @field_validator("spectral_response")
    @classmethod
    def _check_spectral_response(cls, v: str) -> str:
        return check_spectral_response(v)

    @model_validator(mode="after")
    def _check_ranges(self) -> "SensorConfig":
        adc_max_dn = 2**self.adc_bits - 1
        if self.black_level_dn >= adc_max_dn:
            raise ValueError(
                f"black_level_dn: must be below the ADC maximum 2^adc_bits - 1 = {adc_max_dn}, "
                f"got {self.black_level_dn}"
            )
        return self

    @property
    def adc_max_dn(self) -> int:
        """Largest ADC code, 2^adc_bits - 1, in DN."""
        return 2**self.adc_bits - 1

    @property
    def pixel_area_m2(self) -> float:
        """Pixel area in square metres."""
        return (self.pixel_pitch_um * 1e-6) ** 2
