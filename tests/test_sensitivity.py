"""What the speckle can carry (pwf_dask.calibration.sensitivity): the measures against analytic
values, and PWF's warning on a scene whose data carry the phase and one whose data do not."""

import numpy as np
import pytest
from scipy import ndimage

from pwf_dask import retrieve_projection
from pwf_dask.calibration import SensitivityLimits, sensitivity, speckle_grain_px, speckle_shift_px, speckle_visibility
from pwf_dask.pipeline.workflow import sensitivity_warning
from pwf_dask.simulation import SpeckleSetup, simulate_projection


def gaussian_speckle(rng, sigma_px: float, contrast: float, shape=(256, 256)) -> np.ndarray:
    """1 + contrast x unit-variance white noise smoothed by a Gaussian of ``sigma_px``: its
    autocorrelation is exp(-r^2 / 4 sigma^2), of FWHM 4 sqrt(ln 2) sigma."""
    n = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px, mode="wrap")
    return 1.0 + contrast * n / n.std()


@pytest.mark.parametrize("sigma_px", [1.5, 3.0])
def test_speckle_grain_is_the_autocorrelations_full_width_at_half_maximum(rng, sigma_px):
    reference = gaussian_speckle(rng, sigma_px, 0.2)
    assert speckle_grain_px(reference) == pytest.approx(4 * np.sqrt(np.log(2)) * sigma_px, rel=0.05)
    assert speckle_visibility(reference) == pytest.approx(0.2 * 1.0 / reference.mean(), rel=0.01)


def test_photon_noise_neither_adds_visibility_nor_narrows_the_grain(rng):
    """At 100 photons a pixel the noise (10 %) is as strong as the speckle (10 %): the raw rms
    reads 41 % high and the raw autocorrelation's zero-lag spike halves its width; both come
    back with the white floor taken out."""
    clean = gaussian_speckle(rng, 2.0, 0.1)
    noisy = rng.poisson(100 * clean) / 100.0
    assert noisy.std() / noisy.mean() > 1.3 * speckle_visibility(clean)
    assert speckle_visibility(noisy) == pytest.approx(speckle_visibility(clean), rel=0.05)
    assert speckle_grain_px(noisy) == pytest.approx(speckle_grain_px(clean), rel=0.05)
    assert speckle_grain_px(noisy, subtract_noise=False) < 0.8 * speckle_grain_px(clean)


def test_speckle_shift_of_a_phase_cone_is_lambda_l2_gradient_over_2_pi_p():
    """A phase slope of g rad a pixel tilts the wave by lambda g / (2 pi p), which moves the
    speckle L2 times that: lambda L2 g / (2 pi p^2) pixels. A cone has that slope everywhere
    on it: over the sample's own pixels the percentile reads it; over the whole frame, where
    the sample is under 1 %, it reads 0."""
    wavelength, l2, pixel = 1.24e-10, 0.02, 0.65e-6
    y, x = np.mgrid[:256, :256]
    r = np.hypot(y - 128, x - 128)
    sample = r < 8
    phase = np.where(sample, -0.3 * (8 - r), 0.0)
    expected = wavelength * l2 * 0.3 / (2 * np.pi * pixel**2)
    assert speckle_shift_px(phase, wavelength, l2, pixel, sample) == pytest.approx(expected, rel=0.03)
    assert speckle_shift_px(phase, wavelength, l2, pixel) == 0.0


def test_assess_words_each_limit_it_finds_broken(rng):
    reference = gaussian_speckle(rng, 2.0, 0.03)
    found = sensitivity.assess(
        np.zeros((256, 256)), reference, wavelength_m=1e-10, diffuser_detector_distance_m=0.02, pixel_size_m=1e-6
    )
    assert found.shift_over_grain == 0.0
    assert "moves the speckle by 0.000" in found.warning and "visibility is 0.030" in found.warning
    assert set(found.parameters()) == {
        "speckle_visibility",
        "speckle_grain_px",
        "speckle_shift_px",
        "speckle_shift_over_grain",
        "sensitivity_warning",
    }


@pytest.mark.parametrize(
    ("setup", "flagged"),
    [
        (SpeckleSetup(shape=(128, 128)), False),  # the paper's optics: d / g ~ 0.1
        (SpeckleSetup(shape=(128, 128), energy_eV=25e3), True),  # P3000 fades at 25 keV, the shift too
    ],
)
def test_pwf_warns_where_the_data_carry_little_of_the_phase_and_only_there(setup, flagged):
    sim = simulate_projection(setup, seed=1)
    res = retrieve_projection(sim.sample, sim.reference, **sim.geometry())
    deep = sim.phase < -0.5
    gain = float((res.phase[deep] * sim.phase[deep]).sum() / (sim.phase[deep] ** 2).sum())
    limits = SensitivityLimits()
    p = res.parameters
    assert (p["sensitivity_warning"] is not None) == flagged
    if flagged:
        assert p["speckle_shift_over_grain"] < limits.min_shift_over_grain and gain < 0.5
    else:
        assert p["speckle_shift_over_grain"] > 2 * limits.min_shift_over_grain and gain > 0.7
        assert p["speckle_visibility"] > 4 * limits.min_visibility


def test_a_scans_summary_counts_the_projections_below_each_limit():
    shift = np.array([[0.1, 0.015, np.nan], [0.01, 0.2, 0.3]])
    visibility = np.array([[0.2, 0.2, np.nan], [0.04, 0.2, 0.2]])
    line = sensitivity_warning(shift, visibility)
    assert "under 0.02 of its grain on 2 of 5 projections (median 0.100)" in line
    assert "visibility is under 0.05 on 1 (median 0.200)" in line
    assert sensitivity_warning(np.full((1, 3), 0.1), np.full((1, 3), 0.2)) is None
    assert sensitivity_warning(np.full((1, 3), np.nan), np.full((1, 3), np.nan)) is None


@pytest.mark.gpu
def test_the_check_runs_on_the_device_and_gives_the_host_numbers(cupy, rng):
    reference = rng.poisson(300 * gaussian_speckle(rng, 2.0, 0.15)) / 300.0
    y, x = np.mgrid[:256, :256]
    r = np.hypot(y - 128, x - 128)
    phase = np.where(r < 40, -0.02 * (40 - r), 0.0)
    kw = dict(wavelength_m=1.24e-10, diffuser_detector_distance_m=0.02, pixel_size_m=0.65e-6)
    host = sensitivity.assess(phase, reference, background=r >= 44, **kw)
    device = sensitivity.assess(cupy.asarray(phase), cupy.asarray(reference), background=cupy.asarray(r >= 44), **kw)
    for name, value in host.parameters().items():
        assert device.parameters()[name] == (pytest.approx(value, rel=1e-9) if isinstance(value, float) else value)
