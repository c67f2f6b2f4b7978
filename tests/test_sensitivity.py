"""What the speckle can carry (pwf_dask.calibration.sensitivity): the measures against analytic
values, and PWF's warning on a scene whose data carry the phase and one whose data do not."""

import numpy as np
import pytest
from scipy import ndimage

from pwf_dask import retrieve_projection
from pwf_dask.calibration import (
    SensitivityLimits,
    phase_sensitivity,
    phase_sensitivity_noise_bound,
    position_disagreement,
    sensitivity,
    speckle_grain_px,
    speckle_shift_px,
    speckle_visibility,
)
from pwf_dask.calibration.sensitivity import misfit_hint, misfit_warning
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


def test_phase_sensitivity_is_the_speckle_gradients_power_times_the_shift_per_radian(rng):
    """Unit-variance noise smoothed by a Gaussian of sigma has <(d n / dx)^2> = 1 / (2 sigma^2)
    along each axis, so 1 + c n has <|grad I|^2> = c^2 / sigma^2 per pixel^2, and S is that
    times (lambda L2 / (2 pi p^2))^2. The photon noise's own gradient power is taken out with
    its white floor: at 1e3 photons a pixel (3 % noise, 9x the speckle's gradient power) it
    reads within 10 %; at 1e2 (90x) only within about 50 %."""
    wavelength, distance, pixel = 1e-10, 0.05, 1e-6
    per_rad = wavelength * distance / (2 * np.pi * pixel**2)
    clean = gaussian_speckle(rng, 2.0, 0.1, shape=(512, 512))
    expected = per_rad**2 * 0.1**2 / 2.0**2
    assert phase_sensitivity(clean, wavelength, distance, pixel) == pytest.approx(expected, rel=0.05)
    noisy = rng.poisson(1000 * clean) / 1000.0
    assert phase_sensitivity(noisy, wavelength, distance, pixel) == pytest.approx(expected, rel=0.1)
    assert phase_sensitivity(np.ones((64, 64)), wavelength, distance, pixel) == 0.0


def test_phase_sensitivitys_noise_bound_is_two_standard_errors_of_its_estimate(rng):
    """On flat fields with photon noise alone (S = 0) the estimate scatters about zero with the
    standard error the bound is twice: over 300 frames of 64^2 at 200 ph/px it reads 0 about
    half the time (clipped), above the bound about 2.3 % of the time (measured 3 %) and above
    half of it (one standard error) about 16 % (measured 15 %). The bound goes as 1 / photons."""
    optics_args = (1e-10, 0.05, 1e-6)
    frames = [rng.poisson(200.0, (64, 64)) / 200.0 for _ in range(300)]
    reads = np.array([phase_sensitivity(f, *optics_args) for f in frames])
    bounds = np.array([phase_sensitivity_noise_bound(f, *optics_args) for f in frames])
    assert 0.35 < np.mean(reads == 0.0) < 0.65
    assert np.mean(reads > bounds) < 0.06
    assert 0.08 < np.mean(reads > 0.5 * bounds) < 0.26
    bright = np.mean([phase_sensitivity_noise_bound(rng.poisson(2e4, (64, 64)) / 2e4, *optics_args) for _ in range(30)])
    assert bounds.mean() / bright == pytest.approx(100.0, rel=0.1)


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
    # 0.03 contrast over 2-px grains, lambda L2 / 2 pi p^2 = 0.32: S = 0.32^2 x 0.03^2 / 4
    assert found.phase_sensitivity == pytest.approx(2.3e-5, rel=0.1)
    assert "phase sensitivity is 2.3e-05 (below 3e-05" in found.warning
    assert set(found.parameters()) == {
        "speckle_visibility",
        "speckle_grain_px",
        "speckle_shift_px",
        "speckle_shift_over_grain",
        "sample_misfit",
        "phase_sensitivity",
        "sensitivity_warning",
    }
    assert np.isnan(found.sample_misfit)  # no residual given: not measured


@pytest.mark.parametrize(("distance_m", "flagged"), [(0.02, True), (0.2, False)])
def test_assess_flags_data_whose_frame_a_phase_gradient_barely_changes(rng, distance_m, flagged):
    """A bright speckle (visibility 0.2, 6.7-px grains) under a cone steep enough to move it by
    over 0.02 of its grain still carries little where lambda L2 / 2 pi p^2 is small: at 1e-11 m
    and 20 mm that factor is 0.032 and S = 0.032^2 x 0.2^2 / 2^2 = 1.0e-5, below the limit;
    ten times the distance gives 100 times S and no warning."""
    reference = gaussian_speckle(rng, 2.0, 0.2)
    y, x = np.mgrid[:256, :256]
    r = np.hypot(y - 128, x - 128)
    phase = np.where(r < 40, -6.0 * (40 - r), 0.0)
    kw = dict(wavelength_m=1e-11, diffuser_detector_distance_m=distance_m, pixel_size_m=1e-6)
    found = sensitivity.assess(phase, reference, background=r >= 44, **kw)
    limits = SensitivityLimits()
    assert found.visibility > 4 * limits.min_visibility and found.shift_over_grain > limits.min_shift_over_grain
    expected = (1e-11 * distance_m / (2 * np.pi * 1e-12)) ** 2 * 0.2**2 / 2.0**2
    assert found.phase_sensitivity == pytest.approx(expected, rel=0.05)
    assert (found.warning is not None) == flagged
    if flagged:
        assert found.warning.startswith("the data's phase sensitivity is 1.0e-05 (below 3e-05")


@pytest.mark.parametrize(
    ("setup", "alpha", "flagged"),
    [
        (SpeckleSetup(shape=(128, 128)), "sensitivity", False),  # the paper's optics: d / g ~ 0.1
        # P3000 fades at 25 keV (visibility 0.042): the fixed alpha reads 0.24 of the phase,
        # whose shift is 0.010 of the grain; the default rule lowers Im(alpha) to 0.0038 and
        # reads it (gain 1.06, shift 0.025), and the data then carry it
        (SpeckleSetup(shape=(128, 128), energy_eV=25e3), "0.1+0.05j", True),
        (SpeckleSetup(shape=(128, 128), energy_eV=25e3), "sensitivity", False),
    ],
)
def test_pwf_warns_where_the_data_carry_little_of_the_phase_and_only_there(setup, alpha, flagged):
    sim = simulate_projection(setup, seed=1)
    res = retrieve_projection(sim.sample, sim.reference, alpha=alpha, **sim.geometry())
    deep = sim.phase < -0.5
    gain = float((res.phase[deep] * sim.phase[deep]).sum() / (sim.phase[deep] ** 2).sum())
    limits = SensitivityLimits()
    p = res.parameters
    assert (p["sensitivity_warning"] is not None) == flagged
    if flagged:
        assert p["speckle_shift_over_grain"] < limits.min_shift_over_grain and gain < 0.5
    elif setup.energy_eV > 20e3:
        assert complex(p["alpha"]).imag < 0.005 and 0.9 < gain < 1.2
        assert p["speckle_shift_over_grain"] > limits.min_shift_over_grain
    else:
        assert p["speckle_shift_over_grain"] > 2 * limits.min_shift_over_grain and gain > 0.7
        assert p["speckle_visibility"] > 4 * limits.min_visibility
        assert 0.8 < p["sample_misfit"] < 1.1  # fitted to the noise in the sample as in its background


def test_a_scans_summary_counts_the_projections_below_each_limit():
    shift = np.array([[0.1, 0.015, np.nan], [0.01, 0.2, 0.3]])
    visibility = np.array([[0.2, 0.2, np.nan], [0.03, 0.2, 0.2]])
    line = sensitivity_warning(shift, visibility)
    assert "under 0.02 of its grain on 2 of 5 projections (median 0.100)" in line
    assert "visibility is under 0.035 on 1 (median 0.200)" in line
    assert sensitivity_warning(np.full((1, 3), 0.1), np.full((1, 3), 0.2)) is None
    assert sensitivity_warning(np.full((1, 3), np.nan), np.full((1, 3), np.nan)) is None
    misfit = np.array([[1.0, 2.5, np.nan], [1.4, 0.9, 1.1]])
    line = sensitivity_warning(np.full((2, 3), 0.1), np.full((2, 3), 0.2), misfit)
    assert line.startswith("the fit leaves over 1.3 times the background's misfit inside the sample on 2 of 5")
    assert "(the largest 2.50)" in line and "--diffuser-upstream-m" not in line
    # L1 = 0 and no upstream distance: the misfit's words name the likely cause and its option
    unknown = misfit_hint(0.0, 0.0)
    hinted = sensitivity_warning(np.full((2, 3), 0.1), np.full((2, 3), 0.2), misfit, misfit_hint=unknown)
    assert hinted.endswith("give its distance (--diffuser-upstream-m) where it is known")
    assert sensitivity_warning(np.full((2, 3), 0.1), np.full((2, 3), 0.2), misfit_hint=unknown) is None
    assert misfit_warning(1.5, hint=unknown).endswith("where it is known")  # a projection's words
    assert "upstream" not in misfit_warning(1.5)
    # the distance given: an extended source misfits there while delta holds; downstream: no hint
    assert misfit_warning(1.5, hint=misfit_hint(0.0, 0.05)).endswith("(docs/validation.md, 'An extended source')")
    assert misfit_hint(3e-3, 0.0) == ""
    # K = 2 positions: an angle counts once, by its largest; NaN (not retrieved) not at all
    apart = np.array([[0.1, 0.5, np.nan], [0.1, 0.5, np.nan]])
    line = sensitivity_warning(np.full((2, 3), 0.1), np.full((2, 3), 0.2), None, apart)
    assert line.startswith("the diffuser positions' phases disagree by over 0.35 of their rms on 1 of 2 angles")
    assert sensitivity_warning(np.full((2, 3), 0.1), np.full((2, 3), 0.2), None, np.full((2, 3), 0.2)) is None
    # the scan's phase sensitivity, one number for all its projections; None: not measured
    line = sensitivity_warning(np.full((1, 3), 0.1), np.full((1, 3), 0.2), phase_sensitivity=1e-5)
    assert line.startswith("the data's phase sensitivity is 1.0e-05 (below 3e-05")
    assert sensitivity_warning(np.full((1, 3), 0.1), np.full((1, 3), 0.2), phase_sensitivity=1e-3) is None
    assert sensitivity_warning(np.full((1, 3), 0.1), np.full((1, 3), 0.2), phase_sensitivity=None) is None


def test_position_disagreement_reads_a_positions_difference_over_their_mean():
    """Two positions: rms(phi_0 - phi_1) / rms of their mean over the sample the mean shows,
    the same for both; equal phases 0; one of K = 3 off by a scale reads furthest; a K of 1 or
    no phase at all has no disagreement."""
    yy, xx = np.mgrid[-32:32, -32:32]
    phase = -np.clip(1 - (xx**2 + yy**2) / 20.0**2, 0, None) * 5.0
    assert position_disagreement(np.stack([phase, phase])) == [0.0, 0.0]
    # 0.5 phi against phi: rms(phi / 2) / rms(3 phi / 4) = 2/3 for both
    assert position_disagreement(np.stack([phase, 0.5 * phase])) == pytest.approx([2 / 3, 2 / 3])
    three = position_disagreement(np.stack([phase, phase, 0.4 * phase]))
    assert three[2] > three[0] == pytest.approx(three[1])
    assert np.isnan(position_disagreement(np.zeros((2, 8, 8)))).all()
    with pytest.raises(ValueError, match="K >= 2"):
        position_disagreement(phase[None])


@pytest.mark.gpu
def test_the_check_runs_on_the_device_and_gives_the_host_numbers(cupy, rng):
    reference = rng.poisson(300 * gaussian_speckle(rng, 2.0, 0.15)) / 300.0
    y, x = np.mgrid[:256, :256]
    r = np.hypot(y - 128, x - 128)
    phase = np.where(r < 40, -0.02 * (40 - r), 0.0)
    residual = np.abs(rng.standard_normal(phase.shape)) * (1 + (r < 40))
    kw = dict(wavelength_m=1.24e-10, diffuser_detector_distance_m=0.02, pixel_size_m=0.65e-6)
    host = sensitivity.assess(phase, reference, background=r >= 44, residual=residual, intensity=reference, **kw)
    on = cupy.asarray
    device = sensitivity.assess(
        on(phase), on(reference), background=on(r >= 44), residual=on(residual), intensity=on(reference), **kw
    )
    assert host.sample_misfit > 1.3 and "misfit inside the sample" in host.warning
    for name, value in host.parameters().items():
        assert device.parameters()[name] == (pytest.approx(value, rel=1e-9) if isinstance(value, float) else value)
    bound = phase_sensitivity_noise_bound(reference, 1.24e-10, 0.02, 0.65e-6)
    assert phase_sensitivity_noise_bound(on(reference), 1.24e-10, 0.02, 0.65e-6) == pytest.approx(bound, rel=1e-9)


def test_sample_misfit_reads_the_noise_scale_inside_the_sample_against_its_background(rng):
    """A fit to the photon noise leaves residuals of sqrt(intensity) times a unit noise: the
    ratio reads 1 on a dark sample as on the bright background, twice the noise inside the
    sample reads 2, and pixels left out of the fit do not count."""
    y, x = np.mgrid[:128, :128]
    sample = np.hypot(y - 64, x - 64) < 30
    intensity = np.where(sample, 0.25, 1.0)
    noise = np.abs(rng.standard_normal(sample.shape)) * np.sqrt(intensity)
    assert sensitivity.sample_misfit(noise, intensity, ~sample) == pytest.approx(1.0, abs=0.05)
    assert sensitivity.sample_misfit(np.where(sample, 2 * noise, noise), intensity, ~sample) == pytest.approx(
        2.0, abs=0.1
    )
    hot = np.zeros(sample.shape, dtype=bool)
    hot[60:64, 60:64] = True
    assert sensitivity.sample_misfit(np.where(hot, 1e3, noise), intensity, ~sample, excluded=hot) == pytest.approx(
        1.0, abs=0.05
    )
    assert np.isnan(sensitivity.sample_misfit(noise, intensity, np.zeros(sample.shape, dtype=bool)))


def test_pwf_warns_where_its_model_does_not_reach_a_steep_samples_data():
    """The stability map's 100 pi point on a 128^2 frame (PWF, lengths calibrated): the phase is
    lost with the speckle moved far more than the shift limit, and the fit leaves 2.1 times the
    background's misfit in the sample (3.6 before session 105 lowered Re(alpha) by the thick
    sample's attenuation contrast); at 3 pi it fits to the noise (0.95)."""
    from benchmarks.sensitivity_check import STABILITY_RUN
    from benchmarks.stability import stability_map

    steep, mild = stability_map(
        shape=(128, 128), axes={"max_phase_pi": [100.0, 3.0]}, methods=[STABILITY_RUN], progress=False
    )
    limits = SensitivityLimits()
    assert steep["phase_gain"] < 0.5 and steep["speckle_shift_over_grain"] > 5 * limits.min_shift_over_grain
    assert steep["sample_misfit"] > 1.5 * limits.max_sample_misfit and steep["flagged"]
    assert mild["holds"] and mild["sample_misfit"] < 1.1 and not mild["flagged"]


@pytest.mark.parametrize("photons", [1e3, 1e5])
def test_attenuation_contrast_reads_the_samples_absorption_not_its_speckle_or_dose(rng, photons):
    """A broad disc of amplitude attenuation 1.2 on a speckle of 3-px grains: the contrast reads
    the disc's 1.2 at either dose (the speckle cancels in the ratio of local means); a
    sample image that absorbs nothing reads the noise only."""
    reference = gaussian_speckle(rng, 1.5, 0.3)
    yy, xx = np.indices(reference.shape)
    disc = np.hypot(yy - 128, xx - 128) < 60
    attenuation = 1.2 * ndimage.gaussian_filter(disc.astype(float), 2.0)

    def noisy(image):
        return rng.poisson(photons * np.clip(image, 0, None)) / photons

    found = sensitivity.attenuation_contrast(noisy(reference * np.exp(-2 * attenuation)), noisy(reference))
    assert found == pytest.approx(1.2, rel=0.05)
    assert sensitivity.attenuation_contrast(noisy(reference), noisy(reference)) < 0.1
