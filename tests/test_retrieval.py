"""retrieve_projection against ground truth on realistic simulated scenes (CONTRACT §4)."""

from dataclasses import replace

import numpy as np
import pytest
from measures import gain, kwargs, relative_phase_error

from benchmarks.stability import errors
from pwf_dask import backend, retrieve_projection
from pwf_dask.physics import optics
from pwf_dask.pwf import solver
from pwf_dask.retrieval import estimate_diffuser
from pwf_dask.simulation import (
    FINE_DIFFUSER,
    Phantom,
    SpeckleSetup,
    SpeckleSimulator,
    default_phantom,
    simulate_projection,
)


def bead_contrast(image, sim, sphere):
    """Mean over the bead's central disk minus the mean over a ring around it."""
    ny, nx = image.shape
    p = sim.pixel_size_m
    yy, xx = np.mgrid[0:ny, 0:nx]
    cx = sphere.u_m / p + (nx - 1) / 2
    cy = sphere.y_m / p + (ny - 1) / 2
    r = np.hypot(xx - cx, yy - cy) * p / sphere.radius_m
    return float(np.mean(image[r < 0.5]) - np.mean(image[(r > 1.2) & (r < 1.6)]))


@pytest.fixture(scope="module")
def scene():
    """The issue's scene: 512 x 512, the paper's geometry, sub-pixel sandpaper, 1e4 photons."""
    sim = simulate_projection(SpeckleSetup(shape=(512, 512), photons=1e4), seed=1)
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim))
    return sim, res


@pytest.mark.slow
def test_contract_result(scene):
    sim, res = scene
    assert res.phase.shape == sim.sample.shape and res.attenuation.shape == sim.sample.shape
    assert isinstance(res.phase, np.ndarray)
    assert res.converged and 0 < res.iterations <= 2000
    assert res.parameters["coherence_calibrated"]
    assert res.parameters["fft_library"] == backend.resolve_fft_library()  # provenance
    # a thin sample: field_upsample="auto" keeps the paper's detector-grid model
    # P3000 grains alias on the detector grid: the field goes on the 1.5x grid (retrieval.diffuser_aliasing)
    assert res.parameters["diffuser_aliasing"] > 0.06 and res.parameters["field_upsample"] == 1.5
    assert res.parameters["phase_gradient_rad_per_px"] < np.pi / 2


def test_phase_gain_within_10_percent(scene):
    sim, res = scene
    g = gain(res.phase, sim.phase, sim.phase < -0.5)
    assert 0.9 <= g <= 1.1, g


def test_largest_bead_phase_contrast_within_10_percent(scene):
    """The default alpha (0.1+0.05j): +4.2 % measured (the paper's gave +10 % here, and +34 to
    +53 % at 256^2)."""
    sim, res = scene
    bead = max(sim.phantom.spheres, key=lambda s: s.radius_m)
    true_c = bead_contrast(sim.phase, sim, bead)
    got = bead_contrast(res.phase, sim, bead)
    assert res.parameters["diffuser_model"] == "single-material"
    assert res.parameters["alpha"] == "0.1+0.05j"
    assert got == pytest.approx(true_c, rel=0.10)


@pytest.mark.slow
def test_zero_phase_diffuser_overshoots_the_bead(scene):
    """Where the paper's zero-phase diffuser estimate fails: the same scene with the paper's
    alpha gives a bead phase contrast > 15 % too deep (docs/validation.md, Where PWF fails)."""
    sim, _ = scene
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, diffuser_model="zero-phase", alpha="paper"))
    bead = max(sim.phantom.spheres, key=lambda s: s.radius_m)
    assert bead_contrast(res.phase, sim, bead) / bead_contrast(sim.phase, sim, bead) > 1.15
    assert 0.9 <= gain(res.phase, sim.phase, sim.phase < -0.5) <= 1.1


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_papers_diffuser_calibrated_coherence_and_alpha_from_the_data(seed, request):
    """Issue #27 on the paper's diffuser (four layers of P3000), 256^2, everything from the
    data: coherence lengths by the template fit, the 1.5x field grid chosen by the diffuser's
    aliasing, the default alpha (0.1+0.05j). Measured, seeds 1-3: phase gain 1.008 /
    1.001 / 0.993, bead phase contrast -2.2 / +0.5 / -0.3 %, attenuation gain 0.995 / 0.990 /
    0.989 (the 2x grid the same to 0.001; the detector grid 0.88-0.91; the paper's alpha:
    gain 1.02-1.03, bead +34 to +53 %, attenuation 0.86-0.92)."""
    if seed == 1:  # conftest's small scene (the same setup and seed), retrieved once for several tests
        sim, res = request.getfixturevalue("small_scene"), request.getfixturevalue("small_scene_result")
    else:
        sim = simulate_projection(SpeckleSetup(shape=(256, 256)), seed=seed)
        res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim))
    assert res.parameters["coherence_method"] == "template" and res.parameters["field_upsample"] == 1.5
    # the dose the calibration read: 1e4 ph/px through the diffuser's absorption (~0.9)
    assert 6e3 < res.parameters["coherence_reference_photons_per_px"] < 1.1e4
    assert 0.95 <= gain(res.phase, sim.phase, sim.phase < -0.5) <= 1.05
    bead = max(sim.phantom.spheres, key=lambda s: s.radius_m)
    assert bead_contrast(res.phase, sim, bead) == pytest.approx(bead_contrast(sim.phase, sim, bead), rel=0.10)
    inside = sim.attenuation > 0.2 * sim.attenuation.max()
    assert 0.85 <= gain(res.attenuation, sim.attenuation, inside) <= 1.15


def test_attenuation_gain_within_15_percent(scene):
    sim, res = scene
    inside = sim.attenuation > 0.2 * sim.attenuation.max()
    g = gain(res.attenuation, sim.attenuation, inside)
    assert 0.85 <= g <= 1.15, g


def test_fits_data_to_near_the_noise_level(scene):
    """Residual at the photon noise, not far below it (over-fitting) nor above (a model that
    cannot hold the scene): the single-material diffuser leaves 0.95x the noise (0.932 %);
    the paper's zero-phase diffuser left 1.08x, with the beads over-fitted (+28 %, docs/validation.md)."""
    sim, res = scene
    noise_pct = 100 * np.sqrt(np.mean(sim.sample) / sim.photons) / np.mean(sim.reference)
    assert 0.9 * noise_pct < res.residual_rmse < 1.45 * noise_pct


def test_background_is_zero(scene):
    sim, res = scene
    bg = sim.phase > -0.01
    assert abs(float(np.mean(res.phase[bg]))) < 0.05 * abs(sim.phase.min())


def test_ablation_without_preconditioner_leaves_phase_near_zero(small_scene):
    sim = small_scene
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, preconditioner=False, max_iter=300))
    assert gain(res.phase, sim.phase, sim.phase < -0.5) < 0.2


def test_j_alone_stops_the_small_scene_later_at_the_same_phase(small_scene, small_scene_result):
    """The default ``stationary_terms="j-or-data"`` (since session 67; the camera frame 300
    iterations for 587, session 62) stops the P3000 256^2 scene from zero at about half the
    iterations of the former rule, J's test on J alone, at the same phase: measured 174 for
    360 iterations, gain 1.0086 / 1.0085, relative phase error 0.0668 / 0.0655."""
    sim, default = small_scene, small_scene_result
    j_alone = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, stationary_terms="j"))
    assert (default.parameters["stationary_terms"], j_alone.parameters["stationary_terms"]) == ("j-or-data", "j")
    assert default.converged and default.iterations < 0.7 * j_alone.iterations, (default.iterations, j_alone.iterations)
    g_default, g_j = (gain(r.phase, sim.phase, sim.phase < -0.5) for r in (default, j_alone))
    assert abs(g_default - g_j) < 0.01, (g_default, g_j)
    assert relative_phase_error(default, sim) < relative_phase_error(j_alone, sim) + 0.01


def test_the_sample_field_on_the_detector_grid_reads_the_beads_as_the_field_grid_does(small_scene, small_scene_result):
    """``sample_field_grid="detector"`` (6 field-grid FFTs per iteration, not 10) on the P3000
    256^2 scene, calibrated coherence: the same 1.5x grid and phase gain to 0.01 (measured
    1.0035 against 1.0086, both stopped at 174 iterations, the phases 0.12 rad rms apart of
    14.3; under J's test alone 1.0068 against 1.0085, 0.09 rad; docs/methods.md), recorded."""
    sim, field = small_scene, small_scene_result
    detector = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, sample_field_grid="detector"))
    assert detector.parameters["sample_field_grid"] == "detector" and field.parameters["sample_field_grid"] == "field"
    assert detector.parameters["field_upsample"] == field.parameters["field_upsample"] == 1.5
    g_field, g_detector = (gain(r.phase, sim.phase, sim.phase < -0.5) for r in (field, detector))
    assert abs(g_detector - g_field) < 0.01 and 0.95 < g_detector < 1.05, (g_field, g_detector)
    rms = float(np.sqrt(np.mean((np.asarray(detector.phase) - np.asarray(field.phase)) ** 2)))
    assert rms < 0.01 * float(np.sqrt(np.mean(sim.phase**2))), rms


def test_coarse_pixels_keep_the_sample_field_on_the_field_grid_under_auto():
    """Under ``field_upsample="auto"``, ``sample_field_grid="detector"`` holds on the aliasing
    diffuser's 1.5x grid only (above): where the pixel itself asks for a field grid (1.3 um
    pixels at 3.5 um coherence: 2x) the sample's field is formed on it, the same run as the
    default's to the bit and recorded so; a given factor is taken as asked. Measured on the 80
    random geometries: docs/methods.md, "The diffuser estimate and its field grid"."""
    from pwf_dask.retrieval import auto_field_upsample, sample_field_grid_on

    sim = simulate_projection(SpeckleSetup(shape=(64, 80), pixel_size_m=1.3e-6), seed=3)
    assert auto_field_upsample(1.3e-6, sim.coherence_length_x_m, sim.coherence_length_y_m) == 2
    run = dict(kwargs(sim), coherence_length_x_m=sim.coherence_length_x_m, max_iter=12, min_iter=12)
    run["coherence_length_y_m"] = sim.coherence_length_y_m
    field = retrieve_projection(sim.sample, sim.reference, **run)
    auto = retrieve_projection(sim.sample, sim.reference, **run, sample_field_grid="detector")
    assert auto.parameters["field_upsample"] == field.parameters["field_upsample"] == 2
    assert auto.parameters["sample_field_grid"] == "field"
    np.testing.assert_array_equal(np.asarray(auto.phase), np.asarray(field.phase))
    given = retrieve_projection(sim.sample, sim.reference, **run, sample_field_grid="detector", field_upsample=2)
    assert given.parameters["sample_field_grid"] == "detector"
    assert not np.array_equal(np.asarray(given.phase), np.asarray(field.phase))
    assert [sample_field_grid_on("detector", s) for s in (None, 1, 2, 4)] == ["detector", "detector", "field", "field"]
    assert sample_field_grid_on("field", None) == "field"
    with pytest.raises(ValueError, match="sample_field_grid must be one of field, detector, got 'fine'"):
        sample_field_grid_on("fine", 2)


def test_the_background_planes_rebuild_the_solvers_psi():
    """``parameters["background_planes"]``: the zeroed phase and attenuation plus the planes
    recorded are what the solver returned before the background fit (a scan's warm start)."""
    from pwf_dask.physics.background import plane_from_terms

    sim = simulate_projection(SpeckleSetup(shape=(64, 96), photons=1e4), seed=2)
    common = kwargs(sim, max_iter=40, tol=0)
    raw = retrieve_projection(sim.sample, sim.reference, zero_background=False, **common)
    zeroed = retrieve_projection(sim.sample, sim.reference, **common)
    assert raw.parameters["background_planes"] is None
    planes = zeroed.parameters["background_planes"]
    assert abs(planes["phase"][0]) > 1e-3  # something was taken off
    for name in ("phase", "attenuation"):
        rebuilt = getattr(zeroed, name) + plane_from_terms(planes[name], sim.sample.shape)
        scale = float(np.abs(getattr(raw, name)).max())
        np.testing.assert_allclose(rebuilt, getattr(raw, name), atol=1e-5 * scale, err_msg=name)


@pytest.mark.slow
def test_start_from_umpa_reaches_the_solution(small_scene):
    """``initial="umpa"``: PWF refines UMPA's one-image estimate to the same accuracy."""
    sim = small_scene
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, initial="umpa"))
    assert res.parameters["initial"] == "umpa" and res.converged
    assert 0.9 <= gain(res.phase, sim.phase, sim.phase < -0.5) <= 1.1


@pytest.mark.slow
def test_double_precision_agrees_with_single(small_scene):
    """60 iterations in float32 and float64 (the curvature estimate and the momentum steps)
    give the same phase to float32 rounding: measured 5.0e-6 of the sample's mean phase after
    60 iterations, 1.0e-6 after 150 (session 65)."""
    sim = small_scene
    r32 = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, tol=0))
    r64 = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, tol=0, precision="double"))
    inside = sim.phase < -0.5
    assert r64.phase.dtype == np.float64 and r32.phase.dtype == np.float32
    assert np.abs(r64.phase - r32.phase)[inside].mean() < 1e-3 * np.abs(sim.phase[inside]).mean()


@pytest.mark.parametrize("upstream_m", [0.0, 5e-3])
def test_l1_zero_converges_to_the_best_iterate(upstream_m):
    """L1 = 0, with the diffuser at the sample or 5 mm upstream of it (the independent
    checks' geometry). Before the stalled-momentum restart the gradient rule never fired
    here: one 1000-iteration momentum run, J ending 60 % above its best, error 0.25."""
    setup = SpeckleSetup(
        shape=(128, 128), sample_diffuser_distance_m=0.0, diffuser_upstream_m=upstream_m, **FINE_DIFFUSER
    )
    sim = simulate_projection(setup, seed=1)
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=1000))
    assert res.converged, res.parameters["stop_reason"]
    assert res.loss_history[-1] <= min(res.loss_history) * (1 + 1e-6)
    assert 0.9 <= gain(res.phase, sim.phase, sim.phase < -0.5) <= 1.1
    assert relative_phase_error(res, sim) < 0.15


def test_upstream_diffuser_reference_propagates_over_both_distances():
    """Free-space propagators compose: a diffuser d upstream of the sample plane gives the
    reference of the same diffuser d + L2 before the detector."""
    up = SpeckleSimulator(
        SpeckleSetup(shape=(64, 64), sample_diffuser_distance_m=0.0, diffuser_upstream_m=5e-3, photons=np.inf), seed=3
    )
    down = SpeckleSimulator(SpeckleSetup(shape=(64, 64), diffuser_detector_distance_m=25e-3, photons=np.inf), seed=3)
    np.testing.assert_allclose(up.reference(), down.reference(), rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="L1 = 0"):
        SpeckleSetup(diffuser_upstream_m=5e-3)


def test_a_known_upstream_distance_puts_the_diffuser_field_at_the_sample():
    """``diffuser_upstream_m``: t_r is the single-material fit over d + L2, propagated over d
    to the sample plane, so over L2 it must reproduce the reference (to the noise); 0 m is
    the detector-plane model itself, with nothing computed."""
    setup = SpeckleSetup(shape=(96, 96), sample_diffuser_distance_m=0.0, diffuser_upstream_m=10e-3)
    sim = simulate_projection(setup, seed=2)
    geo = sim.geometry()
    lengths = dict(coherence_length_x_m=sim.coherence_length_x_m, coherence_length_y_m=sim.coherence_length_y_m)
    common = dict(energy_eV=geo["energy_eV"], pixel_size_m=geo["pixel_size_m"], pad=16, **lengths)
    d0 = estimate_diffuser(sim.reference, diffuser_detector_distance_m=0.03, **common)
    again = estimate_diffuser(sim.reference, diffuser_detector_distance_m=0.03, diffuser_upstream_m=0.0, **common)
    np.testing.assert_array_equal(d0, again)
    t = estimate_diffuser(sim.reference, diffuser_detector_distance_m=0.02, diffuser_upstream_m=10e-3, **common)
    assert t.shape == d0.shape
    wl = optics.wavelength_m(geo["energy_eV"])
    h = optics.iotf(t.shape, geo["pixel_size_m"], half=False, **lengths)
    v = optics.angular_spectrum_propagate(t, geo["pixel_size_m"], wl, 0.02)
    model = np.real(np.fft.ifft2(np.fft.fft2(np.abs(v) ** 2) * h))[16:-16, 16:-16]
    ref = sim.reference / sim.reference.mean()
    noise = np.sqrt(ref.mean() / sim.photons)
    assert np.sqrt(np.mean((model - ref) ** 2)) < 1.3 * noise
    # the same fit at the detector-plane distance alone does not (the wrong propagation)
    v0 = optics.angular_spectrum_propagate(d0, geo["pixel_size_m"], wl, 0.02)
    wrong = np.real(np.fft.ifft2(np.fft.fft2(np.abs(v0) ** 2) * h))[16:-16, 16:-16]
    assert np.sqrt(np.mean((wrong - ref) ** 2)) > 3 * noise


@pytest.mark.gpu
def test_upstream_diffuser_on_cupy(cupy):
    setup = SpeckleSetup(shape=(64, 64), sample_diffuser_distance_m=0.0, diffuser_upstream_m=5e-3)
    sim = simulate_projection(setup, seed=2)
    geo = sim.geometry()
    kw = dict(
        energy_eV=geo["energy_eV"],
        pixel_size_m=geo["pixel_size_m"],
        diffuser_detector_distance_m=geo["diffuser_detector_distance_m"],
        coherence_length_x_m=sim.coherence_length_x_m,
        coherence_length_y_m=sim.coherence_length_y_m,
        diffuser_upstream_m=5e-3,
    )
    cpu = estimate_diffuser(sim.reference, **kw)
    gpu = estimate_diffuser(cupy.asarray(sim.reference), **kw)
    assert isinstance(gpu, cupy.ndarray) and gpu.shape == cpu.shape
    assert np.abs(cupy.asnumpy(gpu) - cpu).max() < 1e-3 * np.abs(cpu).mean()


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.slow
def test_a_known_upstream_distance_lowers_the_error(seed):
    """The independent checks' L1 = 0 geometry, 10 mm upstream (128^2, fine grains): fitted at
    the sample plane (the scan says only L1 = 0) the diffuser keeps the phase gain (0.994-0.997
    measured with the template calibration; 0.91-0.93 with the Gaussian one of sessions 19-21)
    but not the accuracy; given the distance, the error drops (0.061 -> 0.051, 0.084 -> 0.066).
    Measured with the paper's alpha: with the default (Im 0.05) the blind fit reaches 0.050 on
    seed 0 and the known distance no longer lowers it (0.056; 0.090 on seed 1), open in #27."""
    setup = SpeckleSetup(shape=(128, 128), sample_diffuser_distance_m=0.0, diffuser_upstream_m=10e-3, **FINE_DIFFUSER)
    sim = simulate_projection(setup, seed=seed)
    inside = sim.phase < -0.5
    blind = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, alpha="paper"))
    known = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, diffuser_upstream_m=10e-3, alpha="paper"))
    assert known.parameters["diffuser_upstream_m"] == 10e-3
    assert 0.95 <= gain(blind.phase, sim.phase, inside) <= 1.05
    assert 0.95 <= gain(known.phase, sim.phase, inside) <= 1.07
    known_error, blind_error = relative_phase_error(known, sim), relative_phase_error(blind, sim)
    assert known_error < 0.07 and known_error < 0.9 * blind_error


@pytest.mark.parametrize(
    "change,message",
    [
        (dict(sample=np.ones((40, 40))), "differ in shape"),
        (dict(diffuser_upstream_m=5e-3, sample_diffuser_distance_m=3e-3), "needs sample_diffuser_distance_m = 0"),
        (dict(diffuser_upstream_m=-1e-3), "diffuser_upstream_m must be >= 0"),
        (dict(sample=np.full((64, 64), np.nan)), "non-finite values .NaN or inf.: fill them, and for PWF pass"),
        (dict(sample=np.ma.masked_less(np.ones((64, 64)), 2)), "masked array: pass its filled data"),
        (dict(reference=np.ma.masked_less(np.ones((64, 64)), 2), method="umpa"), "reference is a masked array"),
        (dict(reference=-np.ones((64, 64))), "negative"),
        (dict(sample=np.ones((64, 64), complex)), "real intensities"),  # its imaginary part was dropped
        (dict(reference=np.ones((64, 64), bool)), "real intensities"),
        (dict(sample=np.ones((64, 64), complex), method="lcs"), "real intensities"),
        (dict(sample=np.ones(64)), "2-D"),
        (dict(diffuser_detector_distance_m=0.0), "diffuser_detector_distance_m must be positive"),
        (dict(method="magic"), "unknown method"),
        (dict(initial="random"), "unknown initial"),
        (dict(restart="sometimes"), "unknown restart"),
        (dict(field_upsample=0), "field_upsample"),
        (dict(max_iter=0), "max_iter must be"),
        (dict(max_iter=2.5), "max_iter must be"),
        (dict(tol=-1.0), "tol must be"),
        (dict(gamma=-1.0), "gamma must be"),
        (dict(step=0.0), "step must be"),
        (dict(phase_scale=0.0), "phase_scale must be"),
        (dict(low_band_atol_rad=-0.05), "low_band_atol_rad must be >= 0"),
        (dict(alpha="foo"), "alpha must be"),
        (dict(field_upsample="fine"), "field_upsample"),
        (dict(sample_field_grid="fine"), "sample_field_grid must be one of field, detector, got 'fine'"),
        (dict(initial=np.zeros((8, 8), complex)), "initial psi has shape"),
    ],
)
def test_bad_input_gets_one_line_error(change, message):
    args = dict(
        sample=np.ones((64, 64)),
        reference=np.ones((64, 64)),
        energy_eV=1e4,
        pixel_size_m=1e-6,
        sample_diffuser_distance_m=0.0,
        diffuser_detector_distance_m=0.02,
    )
    args.update(change)
    with pytest.raises(ValueError, match=message) as err:
        retrieve_projection(**args)
    assert "\n" not in str(err.value)


@pytest.mark.gpu
def test_cupy_matches_numpy(cupy, small_scene):
    sim = small_scene
    kw = kwargs(sim, max_iter=100, tol=0)
    cpu = retrieve_projection(sim.sample, sim.reference, **kw)
    gpu = retrieve_projection(cupy.asarray(sim.sample), cupy.asarray(sim.reference), **kw)
    assert isinstance(gpu.phase, cupy.ndarray)
    diff = np.abs(cupy.asnumpy(gpu.phase) - cpu.phase)
    assert diff.max() < 1e-3 * np.abs(sim.phase).max() + 1e-3


@pytest.mark.gpu
@pytest.mark.parametrize(
    "options",
    [
        {"coherence_length_x_m": None, "coherence_length_y_m": None, "diffuser_drift": "auto"},
        {"initial": "umpa", "field_upsample": 2, "precision": "double"},
        {"single_material": True, "sample_material": "cellulose"},
        {"diffuser_beta_over_delta": 1e-4},  # "auto" gives zero phase and probes both models
        {"detector_halo_fraction": 0.3, "detector_halo_radius_m": 3e-6},
    ],
    ids=["calibrated-drift", "umpa-start-fine-grid-double", "single-material", "diffuser-probe", "detector-halo"],
)
def test_cupy_options_match_numpy(cupy, options):
    """The option paths on CuPy: the Siegert calibration, drift estimate, UMPA start,
    field on a finer grid, double precision, the single-material prior, the detector's halo in
    the model and the diffuser fit (a 96 x 96 frame, 30 iterations)."""
    sim = simulate_projection(SpeckleSetup(shape=(96, 96), photons=1e4), seed=2)
    kw = kwargs(sim, max_iter=30, tol=0, **options)
    cpu = retrieve_projection(sim.sample, sim.reference, **kw)
    gpu = retrieve_projection(cupy.asarray(sim.sample), cupy.asarray(sim.reference), **kw)
    assert isinstance(gpu.phase, cupy.ndarray) and isinstance(gpu.attenuation, cupy.ndarray)
    for key in ("coherence_length_x_m", "coherence_length_y_m"):
        assert getattr(gpu, key) == pytest.approx(getattr(cpu, key), rel=1e-4)
    scale = float(np.abs(cpu.phase).max())
    np.testing.assert_allclose(cupy.asnumpy(gpu.phase), cpu.phase, atol=1e-3 * scale)
    np.testing.assert_allclose(cupy.asnumpy(gpu.residual), cpu.residual, atol=1e-3 * float(cpu.residual.max()))


def test_a_diffuser_estimated_once_gives_the_same_result(small_scene):
    """What a scan does per diffuser position: estimate_diffuser then retrieve_projection(diffuser=)."""
    from pwf_dask.retrieval import estimate_diffuser

    sim = small_scene
    opts = dict(coherence_length_x_m=sim.coherence_length_x_m, coherence_length_y_m=sim.coherence_length_y_m)
    own = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, **opts))
    t = estimate_diffuser(
        sim.reference,
        energy_eV=sim.energy_eV,
        pixel_size_m=sim.pixel_size_m,
        diffuser_detector_distance_m=sim.diffuser_detector_distance_m,
        **opts,
    )
    given = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, diffuser=t, **opts))
    assert given.parameters["diffuser_given"]
    np.testing.assert_array_equal(given.phase, own.phase)
    # the sample image's noise floors the Wiener NSR only where the reference is far cleaner
    geometry = dict(energy_eV=sim.energy_eV, pixel_size_m=sim.pixel_size_m)
    geometry["diffuser_detector_distance_m"] = sim.diffuser_detector_distance_m
    np.testing.assert_array_equal(estimate_diffuser(sim.reference, sample=sim.sample, **geometry, **opts), t)
    noisier = sim.sample + np.random.default_rng(0).normal(0.0, 0.2, sim.sample.shape).astype(np.float32)
    floored = estimate_diffuser(sim.reference, sample=noisier, **geometry, **opts)
    assert not np.allclose(floored, t)
    as_read = estimate_diffuser(sim.reference, sample=noisier, diffuser_nsr_floor=0.0, **geometry, **opts)
    np.testing.assert_array_equal(as_read, t)
    with pytest.raises(ValueError, match="computational grid"):
        retrieve_projection(sim.sample, sim.reference, **kwargs(sim, diffuser=t[1:], **opts))


def test_small_strong_bead_overshoots_with_the_papers_alpha():
    """Where the paper's alpha fails: a 16-px-radius glass bead in a 128^2 frame. It damps the
    bead's attenuation (Re alpha) and the phase makes up the missing signal, so the bead's phase
    contrast overshoots; the default alpha (Im 0.05) holds it."""
    from benchmarks import stability

    setup = SpeckleSetup(shape=(128, 128), photons=1e4)
    p = setup.pixel_size_m
    cyl = Phantom(cylinder_radius_m=0.5 * 0.72 * 0.8 * 128 * p)
    ph = replace(cyl, spheres=(stability.single_bead(cyl, 16 * p),))
    sim = simulate_projection(setup, phantom=ph, seed=0)
    regions = stability.bead_regions(SpeckleSimulator(setup, seed=0), ph)
    errs = {}
    for alpha in ("paper", solver.DEFAULT_ALPHA):
        res = retrieve_projection(sim.sample, sim.reference, alpha=alpha, max_iter=500, **kwargs(sim))
        errs[alpha] = stability.bead_contrast_error(res.phase, sim.phase, regions)
    assert errs["paper"] > 0.3
    assert abs(errs[solver.DEFAULT_ALPHA]) < 0.2, errs


def test_an_absorbing_beads_overshoot_falls_with_re_alpha_at_a_sample_wide_cost():
    """The same 16-px bead with three times its glass's beta (benchmarks/bead_absorption.py on
    the map's scene: +49 % at Re(alpha) 0.1, +12 % at 0.03): Re(alpha) damps the bead's
    attenuation and the phase makes up the light, so the default overshoots (measured +47 %)
    and Re 0.03 reads it (-0.4 %). The sample-wide phase error pays for it (0.164 -> 0.194):
    why the default stays at 0.1 below the contrast threshold (docs/methods.md, "The largest
    bead against Re(alpha)")."""
    from benchmarks import stability

    setup = SpeckleSetup(shape=(128, 128), photons=1e4)
    p = setup.pixel_size_m
    cyl = Phantom(cylinder_radius_m=0.5 * 0.72 * 0.8 * 128 * p)
    scene = stability.Scene(setup, replace(cyl, spheres=(stability.single_bead(cyl, 16 * p),)), 1.0, 1, 0, 3.0)
    s, r = scene.images(setup.photons, 1, seed=7)
    geometry = setup.geometry()
    geometry.update(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    errs = {}
    for re_alpha in (0.1, 0.03):
        res = retrieve_projection(
            s[0], r[0], alpha=complex(re_alpha, 0.05), background_mask=scene.background, **geometry
        )
        errs[re_alpha] = stability.errors(
            res.phase, res.attenuation, scene.phase, scene.attenuation, scene.background, scene.bead
        )
    assert errs[0.1]["bead_contrast_error"] > 0.3, errs
    assert abs(errs[0.03]["bead_contrast_error"]) < 0.1, errs
    assert errs[0.03]["phase_error"] > 1.1 * errs[0.1]["phase_error"], errs


@pytest.mark.parametrize(
    "ratios,chosen",
    [
        ({0.05: 0.99, 0.1: 1.03}, 0.05),  # measured at 1e4 ph/px, 256^2 P3000: the usual answer
        ({0.05: 1.5, 0.02: 1.3, 0.01: 1.2}, 0.01),  # 1e5: the model's error above the noise
        ({0.05: 0.93, 0.1: 0.95, 0.2: 0.97, 0.5: 0.996}, 0.5),  # 1e3: noise fitted inside the STF
        ({0.05: 1.02, 0.02: 0.98}, 0.02),
    ],
)
def test_discrepancy_alpha_walks_the_ladder(ratios, chosen):
    """The rule of alpha="discrepancy" on residuals measured at three doses (docs/methods.md):
    the largest Im(alpha) whose residual stays at the noise, the paper's as the floor, each
    rung started from the one before."""
    starts = []

    class Run:
        def __init__(self, a):
            self.psi, self.iterations = a, 10

    def solve(alpha, psi0):
        starts.append(psi0)
        return Run(alpha), ratios[alpha.imag] * 2.0

    choice = solver.discrepancy_alpha(solve, noise_pct=2.0)
    assert choice.alpha == complex(0.1, chosen) and choice.result.psi == choice.alpha
    assert [complex(a).imag for a, _, _ in choice.trials] == list(ratios)
    assert starts[0] is None and all(s is not None for s in starts[1:])


def test_sensitivity_alpha_keeps_the_default_where_the_data_see_the_phase_as_the_papers_do():
    """From the tuned sensitivity up, the default alpha exactly; below, Im(alpha) by the
    square root of the ratio, Re(alpha) kept, down to the floor (a non-positive measure:
    no speckle seen above the noise); a NaN measure changes nothing."""
    tuned = solver.TUNED_PHASE_SENSITIVITY
    assert solver.sensitivity_alpha(tuned) == solver.DEFAULT_ALPHA
    assert solver.sensitivity_alpha(10 * tuned) == solver.DEFAULT_ALPHA
    assert solver.sensitivity_alpha(float("nan")) == solver.DEFAULT_ALPHA
    assert solver.sensitivity_alpha(tuned / 100) == pytest.approx(complex(0.1, 0.005))
    floor = complex(0.1, 0.05 * solver.MIN_ALPHA_SCALE)
    assert solver.sensitivity_alpha(0.0) == pytest.approx(floor) == solver.sensitivity_alpha(-1e-3)


def test_sensitivity_alpha_lowers_re_alpha_only_where_the_sample_absorbs_strongly():
    """Up to the tuned attenuation contrast Re(alpha) is the default's, bit for bit; above, it
    falls as (tuned / contrast)^2, whatever Im(alpha) the phase sensitivity sets."""
    tuned, s = solver.TUNED_ATTENUATION_CONTRAST, solver.TUNED_PHASE_SENSITIVITY
    assert solver.sensitivity_alpha(s, attenuation_contrast=tuned) == solver.DEFAULT_ALPHA
    assert solver.sensitivity_alpha(s, attenuation_contrast=0.1) == solver.DEFAULT_ALPHA
    assert solver.sensitivity_alpha(s, attenuation_contrast=2 * tuned) == pytest.approx(complex(0.025, 0.05))
    assert solver.sensitivity_alpha(s / 100, attenuation_contrast=4 * tuned) == pytest.approx(complex(0.1 / 16, 0.005))


def test_the_rule_takes_s_noise_bound_only_where_s_reads_none_and_the_noise_could_hide_it():
    """S as read wherever it reads anything; where it reads none, its noise bound from
    NOISE_HIDDEN_SENSITIVITY up (a bound below: the geometry sees no phase, the floor stays)."""
    hidden = solver.NOISE_HIDDEN_SENSITIVITY
    assert solver.rule_sensitivity(2e-6, 1e-3) == 2e-6
    assert solver.rule_sensitivity(0.0, 1e-3) == 1e-3
    assert solver.rule_sensitivity(0.0, hidden) == hidden
    assert solver.rule_sensitivity(0.0, 0.5 * hidden) == 0.0
    assert solver.rule_sensitivity(0.0, None) == 0.0


def test_a_low_dose_reference_whose_s_reads_none_no_longer_sets_im_alpha_at_its_floor():
    """Random geometry 143 at its own 783 ph/px: S reads 0 where the speckle carries 4.8e-4 (S at
    1e5 ph/px, benchmarks/results/holds_by_dose.md). At the floor's Im(alpha) the phase fitted
    the noise (error 1.76, gain 2.67); from the noise bound (1.8e-3) it reads error 0.38, gain
    0.66. The warning keeps S as read (0), and the bound is recorded."""
    from benchmarks.random_scenes import draw_scene, retrieve_scene

    setup, sim, background = draw_scene(143)
    res = retrieve_scene(setup, sim, background)
    p = res.parameters
    assert p["phase_sensitivity"] == 0.0 and 1e-3 < p["phase_sensitivity_noise_bound"] < 3e-3
    assert complex(p["alpha"]) == solver.sensitivity_alpha(p["phase_sensitivity_noise_bound"])
    assert "phase sensitivity" in p["sensitivity_warning"]
    err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
    assert err["phase_error"] < 0.6 and 0.4 < err["phase_gain"] < 1.2, err


@pytest.mark.slow
def test_alpha_from_the_phase_sensitivity_reads_the_phase_the_default_holds_back_at_20_kev():
    """The paper's 256^2 scene at 20 keV: the data see the phase 46x more weakly than at 10 keV
    (S 0.00038 against 0.0177), and the default Im(alpha) holds 12 % of it back (gain 0.884,
    error 0.135, attenuation error 0.84); alpha="sensitivity" takes Im(alpha) 0.008 and reads
    gain 1.012, error 0.102, attenuation error 0.42 (benchmarks/results/alpha_sensitivity.md).
    At 10 keV it keeps the default, bit for bit."""
    sim = simulate_projection(SpeckleSetup(shape=(256, 256), energy_eV=20e3), seed=1)
    background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
    found = {}
    for alpha in (solver.DEFAULT_ALPHA, "sensitivity"):
        res = retrieve_projection(sim.sample, sim.reference, alpha=alpha, background_mask=background, **kwargs(sim))
        found[alpha] = (res, errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background))
    res, err = found["sensitivity"]
    assert res.parameters["alpha_rule"] == "sensitivity"
    assert 3e-4 < res.parameters["phase_sensitivity"] < 5e-4
    assert 0.006 < complex(res.parameters["alpha"]).imag < 0.01 and complex(res.parameters["alpha"]).real == 0.1
    assert 0.95 <= err["phase_gain"] <= 1.05 and err["phase_error"] < 0.12
    default = found[solver.DEFAULT_ALPHA][1]
    assert default["phase_gain"] < 0.92 and err["attenuation_error"] < 0.7 * default["attenuation_error"]


def test_alpha_from_the_phase_sensitivity_keeps_the_default_on_the_papers_scene():
    """The default rule (alpha="sensitivity") on the paper's scene is the fixed 0.1+0.05j, bit for bit."""
    sim = simulate_projection(SpeckleSetup(shape=(96, 96)), seed=1)
    given = retrieve_projection(sim.sample, sim.reference, max_iter=30, alpha=solver.DEFAULT_ALPHA, **kwargs(sim))
    rule = retrieve_projection(sim.sample, sim.reference, max_iter=30, **kwargs(sim))
    assert rule.parameters["alpha_rule"] == "sensitivity"
    assert rule.parameters["phase_sensitivity"] > solver.TUNED_PHASE_SENSITIVITY
    assert rule.parameters["alpha"] == given.parameters["alpha"] == "0.1+0.05j"
    assert given.parameters["alpha_rule"] == "given"
    assert "alpha_rule_model_ratio" not in rule.parameters  # nothing lowered, nothing probed
    np.testing.assert_array_equal(rule.phase, given.phase)


@pytest.mark.slow
def test_re_alpha_falls_where_the_sample_absorbs_strongly_and_the_phase_no_longer_makes_up_its_edges():
    """The stability map's scene (256^2, 1e4 ph/px, true lengths) with 10x its beads' beta
    (intensity down to 0.047 through the largest): Re(alpha) 0.1 damps the beads' attenuation
    and the phase makes it up, a lens over each bead (error 0.264, bead +398 %, misfit 1.66: the
    same from the true psi). The rule reads the attenuation contrast (1.17) and lowers Re(alpha);
    the phase then holds and the fit reaches the sample's data (docs/methods.md, "Re(alpha) and
    a strongly absorbing sample")."""
    from benchmarks.stability import Scene

    setup = SpeckleSetup(shape=(256, 256))
    phantom = default_phantom(256 * setup.pixel_size_m, np.random.default_rng(1))
    scene = Scene(setup, phantom, 1.0, 1, 0, absorption_factor=10.0)
    sample, reference = (a[0] for a in scene.images(setup.photons, 1, seed=7))
    geometry = {
        "energy_eV": setup.energy_eV,
        "pixel_size_m": setup.pixel_size_m,
        "sample_diffuser_distance_m": setup.sample_diffuser_distance_m,
        "diffuser_detector_distance_m": setup.diffuser_detector_distance_m,
        "coherence_length_x_m": setup.coherence_length_x_m,
        "coherence_length_y_m": setup.coherence_length_y_m,
        "background_mask": scene.background,
    }
    found = {}
    for alpha in ("sensitivity", solver.DEFAULT_ALPHA):
        res = retrieve_projection(sample, reference, alpha=alpha, **geometry)
        err = errors(res.phase, res.attenuation, scene.phase, scene.attenuation, scene.background, scene.bead)
        found[alpha] = (res.parameters, err)
    p, err = found["sensitivity"]
    assert 1.0 < p["attenuation_contrast"] < 1.4
    assert complex(p["alpha"]) == solver.sensitivity_alpha(
        p["phase_sensitivity"], attenuation_contrast=p["attenuation_contrast"]
    )
    assert complex(p["alpha"]).real < 0.05 and err["phase_error"] < 0.15 and p["sample_misfit"] < 1.3
    fixed_p, fixed = found[solver.DEFAULT_ALPHA]
    assert fixed["phase_error"] > 0.2 and fixed["bead_contrast_error"] > 3 * err["bead_contrast_error"] > 0
    assert fixed_p["sample_misfit"] > 1.3 and "attenuation_contrast" not in fixed_p


def _random_scene(i: int, **options):
    """Scene ``i`` of benchmarks/random_scenes.py retrieved with its true coherence lengths, as
    benchmarks/diffuser_models.py does; with its phase error."""
    from benchmarks.random_scenes import draw_scene

    setup, sim, background = draw_scene(i)
    res = retrieve_projection(
        sim.sample,
        sim.reference,
        **sim.geometry(),
        background_mask=background,
        coherence_length_x_m=setup.coherence_length_x_m,
        coherence_length_y_m=setup.coherence_length_y_m,
        diffuser_upstream_m=setup.diffuser_upstream_m,
        **options,
    )
    return res, errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)["phase_error"]


@pytest.mark.slow
def test_the_alpha_rule_gives_up_the_fit_or_its_alpha_where_the_single_material_fit_misfits_more():
    """Scenes 55 and 11 of the random geometries (8.0 and 10.3 keV, S 6.7e-3 and 3.3e-4): every
    default, so "auto" takes the single-material diffuser fit by the grains' absorption and the
    alpha rule would lower Im(alpha). After the probe scene 55's fit leaves 1.01x zero phase's
    data residual: its misfit is model error, which the rule's lower alpha follows. So "auto"
    gives the fit up for zero phase at the rule's alpha (phase error 0.125), and a fit the user
    names keeps the default alpha (0.229; the rule's alpha 0.258). Scene 11's fit leaves 0.93x:
    the rule's alpha stands with it (0.223; the default reads 0.420). docs/validation.md, "The
    alpha rule's model probe"."""
    res, error = _random_scene(55)
    p = res.parameters
    lowered = solver.sensitivity_alpha(p["phase_sensitivity"])
    assert p["diffuser_model_requested"] == "auto" and p["diffuser_model"] == "zero-phase"
    assert p["alpha_rule_took_zero_phase"] and not p["alpha_rule_kept_default"]
    assert 1.0 < p["alpha_rule_model_ratio"] < 1.1 and p["diffuser_beta_over_delta"] is None
    assert complex(p["alpha"]) == lowered and error < 0.15
    named, error_named = _random_scene(55, diffuser_model="single-material")
    q = named.parameters
    assert q["alpha_rule_kept_default"] and not q["alpha_rule_took_zero_phase"]
    assert q["diffuser_model"] == "single-material" and q["alpha"] == "0.1+0.05j"
    assert error + 0.05 < error_named < 0.24
    assert _random_scene(55, diffuser_model="single-material", alpha=lowered)[1] > error_named + 0.01

    res, error = _random_scene(11)
    p = res.parameters
    assert p["diffuser_model"] == "single-material" and not p["alpha_rule_kept_default"]
    assert not p["alpha_rule_took_zero_phase"] and 0.85 < p["alpha_rule_model_ratio"] < 1.0
    assert complex(p["alpha"]) == solver.sensitivity_alpha(p["phase_sensitivity"]) and error < 0.24
    assert _random_scene(11, alpha=solver.DEFAULT_ALPHA)[1] > 0.35


def test_alpha_by_name_and_bad_alpha_refused():
    from pwf_dask.retrieval import parse_alpha

    assert parse_alpha("paper") == solver.PAPER_ALPHA and parse_alpha(" Discrepancy ") == "discrepancy"
    assert parse_alpha("Sensitivity") == "sensitivity"
    assert parse_alpha("0.1+0.05j") == 0.1 + 0.05j
    for bad, message in (("foo", "alpha must be"), ("-0.1+0.01j", "non-negative"), (complex(np.nan, 0), "finite")):
        with pytest.raises(ValueError, match=message):
            parse_alpha(bad)


@pytest.mark.parametrize("beam", [0.98, 0.95])
@pytest.mark.slow
def test_a_beam_weaker_than_at_the_reference_still_converges(small_scene, small_scene_result, beam):
    """The sample frame a little darker than the reference (ring current decay): a global
    factor that Re(psi)'s mean absorbs and the background plane removes. With the former
    doubling search the step followed the beam level past Nesterov's 4/(3 L): at 0.98 the
    stiffest mode's growth left a +35 rad bump in the background (phase error 0.29), at 0.95
    it took 1717 iterations. The curvature step (solver.largest_curvature) does not move. Its
    iterations stay within J's own count: the full beam stops on the data term's test at 174,
    0.98 at 175, while at 0.95 the data term settles no sooner than J and the run stops at 360,
    as on the full beam under J's test alone (session 67)."""
    sim, full = small_scene, small_scene_result
    assert full.converged and full.iterations < 1000  # what max_iter=1000 gives too
    res = retrieve_projection(beam * sim.sample, sim.reference, **kwargs(sim, max_iter=1000))
    assert res.converged and res.iterations < 2.5 * full.iterations, (res.iterations, full.iterations)
    assert res.parameters["step_final"] > 0.9 * full.parameters["step_final"]  # no halving needed
    assert relative_phase_error(res, sim) < relative_phase_error(full, sim) + 0.01
    assert float(np.abs(res.phase - sim.phase).max()) < 2 * np.pi  # no bump (it was +35 rad)
    assert float(np.abs(np.mean(res.attenuation[res.background]))) < 0.01


def test_diffuser_drift_since_the_reference_is_measured_and_corrected():
    """The diffuser moved (-0.5, 1.5) px between the reference and the sample frame (thermal
    drift; not in the paper). Uncorrected, PWF fits the wrong grains and the phase is lost;
    ``diffuser_drift="auto"`` measures the shift, moves t_r and leaves out the strips whose
    grains the reference never saw: back to the still-diffuser error. Measured with the
    paper's alpha: with the default (Im 0.05) the corrected error is 0.34 against 0.11 still,
    the strips' regularized guess gone wrong (open in #27)."""
    setup = SpeckleSetup(shape=(128, 128), **FINE_DIFFUSER)
    sim = SpeckleSimulator(setup, seed=1)
    fov = 128 * setup.pixel_size_m
    field, psi = sim.sample_field(default_phantom(fov, np.random.default_rng(2), height_m=fov))
    truth = sim._bin(psi.imag)
    reference = sim.reference()
    still = sim.noisy(sim.intensity(field, sim.diffuser()))
    drifted = sim.noisy(sim.intensity(field, sim.diffuser((-0.5, 1.5))))

    def error(res):
        inside = truth < -0.5
        return float(np.sqrt(np.mean((res.phase - truth)[inside] ** 2) / np.mean(truth[inside] ** 2)))

    kw = kwargs(setup, max_iter=400, alpha="paper")
    base = retrieve_projection(still, reference, **kw)
    assert not base.parameters["diffuser_moved"]  # below drift_threshold_px: the paper's model, untouched
    fixed = retrieve_projection(drifted, reference, **kw)
    assert fixed.parameters["diffuser_moved"]
    np.testing.assert_allclose(fixed.parameters["diffuser_drift_px"], (-0.5, 1.5), atol=0.03)
    lost = retrieve_projection(drifted, reference, **{**kw, "max_iter": 150}, diffuser_drift="off")
    assert error(fixed) < 1.3 * error(base) + 0.01  # 0.113 against 0.125 still; 6.3 uncorrected
    assert error(lost) > 0.5
    # the diffuser probe fits the moved t_r too: its residuals as on the still frame (measured
    # 1.12 / 1.10 % against 1.20 / 0.99 %), not as without the correction (2.23 / 1.35 %)
    from pwf_dask.retrieval import choose_diffuser

    weak = {**kwargs(setup), "diffuser_beta_over_delta": 1e-4}  # "auto" gives zero phase: probed
    probes = [choose_diffuser(img, reference, **weak).residuals_pct["zero-phase"] for img in (still, drifted)]
    unmoved = choose_diffuser(drifted, reference, **weak, diffuser_drift="off").residuals_pct["zero-phase"]
    assert abs(probes[1] - probes[0]) < 0.15 * probes[0] and unmoved > 1.5 * probes[0], (probes, unmoved)
    with pytest.raises(ValueError, match="diffuser_drift must be"):
        retrieve_projection(drifted, reference, **kw, diffuser_drift="sideways")
    with pytest.raises(ValueError, match="take a new reference"):
        retrieve_projection(drifted, reference, **kw, diffuser_drift=(0.0, 70.0))


@pytest.mark.slow
def test_a_weakly_absorbing_diffuser_takes_the_zero_phase_estimate_by_default():
    """At 20 keV silicon carbide's kappa is 0.003 and the single-material fit drifts (phase
    error 0.60, gain 0.40); the default ``diffuser_model="auto"`` takes the paper's zero-phase
    estimate there and records the choice (0.137 measured, gain 0.88; docs/validation.md,
    Weak diffuser absorption)."""

    sim = simulate_projection(replace(SpeckleSetup(shape=(256, 256)), energy_eV=20e3), seed=1)
    background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
    auto = retrieve_projection(sim.sample, sim.reference, **kwargs(sim), background_mask=background)
    fitted = retrieve_projection(
        sim.sample, sim.reference, **kwargs(sim, diffuser_model="single-material"), background_mask=background
    )
    p = auto.parameters
    assert (p["diffuser_model"], p["diffuser_model_requested"]) == ("zero-phase", "auto")
    # the probe ran and kept zero phase: the single-material fit matches the data as well here
    probe = p["diffuser_probe_residual_pct"]
    assert probe["single-material"] > 0.5 * probe["zero-phase"], probe
    assert p["diffuser_beta_over_delta"] is None and fitted.parameters["diffuser_beta_over_delta"] < 0.005
    err_auto = errors(auto.phase, None, sim.phase, sim.attenuation, background)["phase_error"]
    err_fitted = errors(fitted.phase, None, sim.phase, sim.attenuation, background)["phase_error"]
    assert err_auto < 0.2 < 0.5 < err_fitted, (err_auto, err_fitted)


@pytest.mark.slow
def test_saturated_pixels_left_out_of_the_fit_read_as_the_unclipped_frame():
    """A detector's full scale clips the speckle's bright spots (here the brightest 10 % of a
    P3000 frame); fitted as measured they read low and pull the phase, left out by
    ``bad_pixels`` (what the workflow passes for raw counts at full scale) they cost almost
    nothing. Measured at 192^2, seed 1: phase error 0.0945 unclipped, 0.129 clipped and fitted,
    0.0986 clipped and left out; residual 1.71 % against 0.99 %."""
    setup = SpeckleSetup(shape=(192, 192))
    sim = simulate_projection(setup, seed=1)
    coherence = dict(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    full_scale = np.quantile(sim.sample, 0.9)
    clipped = np.minimum(sim.sample, full_scale)
    unclipped = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, **coherence))
    fitted = retrieve_projection(clipped, sim.reference, **kwargs(sim, **coherence))
    left_out = retrieve_projection(
        clipped, sim.reference, **kwargs(sim, **coherence), bad_pixels=sim.sample >= full_scale
    )
    assert left_out.parameters["bad_pixels"] == int(np.sum(sim.sample >= full_scale))
    background = np.abs(sim.phase) < 1e-6

    def phase_error(res) -> float:  # offset-free: each result's level from the sample-free pixels
        return errors(np.asarray(res.phase), None, sim.phase, sim.attenuation, background)["phase_error"]

    assert phase_error(left_out) < 1.1 * phase_error(unclipped)
    assert phase_error(fitted) > 1.2 * phase_error(left_out)
    assert left_out.residual_rmse < 1.1 < 1.5 < fitted.residual_rmse


def test_bad_pixels_are_refused_where_they_cannot_be_used():
    sim = simulate_projection(SpeckleSetup(shape=(32, 32), **FINE_DIFFUSER), seed=0)
    with pytest.raises(ValueError, match="boolean map of the frame's shape"):
        retrieve_projection(sim.sample, sim.reference, **kwargs(sim), bad_pixels=np.zeros((8, 8), bool))
    with pytest.raises(ValueError, match="only PWF leaves pixels out"):
        retrieve_projection(sim.sample, sim.reference, **kwargs(sim, method="lcs"), bad_pixels=sim.sample > 1)


@pytest.mark.parametrize("method", ["pwf", "umpa"])
def test_a_background_mask_that_cannot_fit_a_plane_is_refused_before_any_work(method):
    """The mask's shape and its count were found only after the retrieval (a matmul error,
    or "fewer than 6 pixels" after the whole solve); a 0/1 map is still taken."""
    sim = simulate_projection(SpeckleSetup(shape=(32, 32), **FINE_DIFFUSER), seed=0)
    few = np.zeros((32, 32), bool)
    few[0, :3] = True
    for mask, message in (
        (np.ones((8, 8), bool), "boolean \\(or 0/1\\) map of the frame's shape"),
        (np.full((32, 32), 0.5), "boolean \\(or 0/1\\) map"),
        (few, "marks 3 sample-free pixels; a background plane needs at least 6"),
    ):
        with pytest.raises(ValueError, match=message):
            retrieve_projection(
                sim.sample, sim.reference, **kwargs(sim, method=method), background_mask=mask, max_iter=1
            )
    taken = retrieve_projection(
        sim.sample, sim.reference, **kwargs(sim, method=method), background_mask=np.ones((32, 32)), max_iter=2
    )
    assert taken.background.dtype == bool and taken.background.all()


def test_the_background_plane_keeps_the_unseen_strips_only_where_nothing_else_is_left(caplog):
    from pwf_dask.retrieval import _seen_background

    mask = np.zeros((16, 16), bool)
    mask[:, :4] = True
    unseen = np.zeros((16, 16), bool)
    unseen[:, :2] = True
    np.testing.assert_array_equal(_seen_background(mask, unseen), mask & ~unseen)
    unseen[:, :5] = True
    with caplog.at_level("WARNING", logger="pwf_dask"):
        np.testing.assert_array_equal(_seen_background(mask, unseen), mask)
    assert "the plane is fitted on all 64" in caplog.text


#: Scene 68 of benchmarks/diffuser_models.py, rounded: 13.4 keV (silicon carbide absorbs
#: 3.2 /mm, so the absorption rule gives zero phase), 0.42 um pixels, L1 = 0, faceted grains
#: of 4 um radius: the zero-phase estimate fails on it.
ZERO_PHASE_FAILS = SpeckleSetup(
    shape=(96, 154),
    energy_eV=13.4e3,
    pixel_size_m=0.42e-6,
    sample_diffuser_distance_m=0.0,
    diffuser_detector_distance_m=0.091,
    coherence_length_x_m=6.5e-6,
    coherence_length_y_m=7.6e-6,
    photons=1.8e5,
    diffuser_radius_median_m=4.0e-6,
    diffuser_grain_shape="faceted",
)


@pytest.mark.slow
def test_auto_probes_the_single_material_fit_where_the_zero_phase_estimate_fails():
    """Where the grains hardly absorb "auto" runs both diffuser models for DIFFUSER_PROBE_ITER
    (20) iterations and takes the single-material fit where its data residual is under half of
    zero phase's. Measured (seed 1): zero phase alone 0.611 phase error; the probe's residuals
    4.45 % / 0.75 % (3.87 % / 0.62 % at 40 iterations), auto 0.168. A scan's choice
    (:func:`choose_diffuser`, passed as ``diffuser``) retrieves the same projection bit for bit."""
    from pwf_dask.retrieval import choose_diffuser

    setup = ZERO_PHASE_FAILS
    sim = simulate_projection(setup, seed=1)
    background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
    kw = kwargs(
        sim,
        coherence_length_x_m=setup.coherence_length_x_m,
        coherence_length_y_m=setup.coherence_length_y_m,
        background_mask=background,
    )
    auto = retrieve_projection(sim.sample, sim.reference, **kw)
    zero = retrieve_projection(sim.sample, sim.reference, **kw, diffuser_model="zero-phase")
    p = auto.parameters
    assert (p["diffuser_model"], p["diffuser_model_requested"]) == ("single-material", "auto")
    assert p["diffuser_probe_residual_pct"]["single-material"] < 0.3 * p["diffuser_probe_residual_pct"]["zero-phase"]
    assert p["diffuser_beta_over_delta"] > 0 and zero.parameters["diffuser_probe_residual_pct"] is None
    err_auto = errors(auto.phase, None, sim.phase, sim.attenuation, background)["phase_error"]
    err_zero = errors(zero.phase, None, sim.phase, sim.attenuation, background)["phase_error"]
    assert err_auto < 0.25 < 0.5 < err_zero, (err_auto, err_zero)
    geometry = {k: v for k, v in kw.items() if k != "background_mask"}
    choice = choose_diffuser(sim.sample, sim.reference, **geometry)
    assert choice.model == "single-material" and choice.residuals_pct == p["diffuser_probe_residual_pct"]
    # the probe's own alpha: the choice does not follow the solve's regularizer
    assert choose_diffuser(sim.sample, sim.reference, **geometry, alpha="paper").residuals_pct == choice.residuals_pct
    given = retrieve_projection(
        sim.sample, sim.reference, **kw, diffuser=choice.transmission, diffuser_model=choice.model
    )
    np.testing.assert_array_equal(given.phase, auto.phase)


def test_the_probe_window_is_the_whole_frame_up_to_its_pixel_count_and_centred_beyond():
    """Frames up to DIFFUSER_PROBE_MAX_PX (512^2) are probed whole, as before the window; a
    wide strip keeps its rows, a camera frame is probed on its centred 512^2."""
    from pwf_dask.retrieval import DIFFUSER_PROBE_MAX_PX, probe_window

    assert DIFFUSER_PROBE_MAX_PX == 512 * 512
    for shape in ((256, 256), (512, 512), (160, 700), (32, 2560)):
        assert probe_window(shape) == (slice(0, shape[0]), slice(0, shape[1]))
    assert probe_window((430, 2220)) == (slice(0, 430), slice(805, 1414))  # the whole frame
    assert probe_window((2160, 2560)) == (slice(824, 1336), slice(1024, 1536))
    assert probe_window((520, 520)) == (slice(4, 516), slice(4, 516))


def test_the_probe_reads_a_wide_frame_on_its_window_as_a_frame_of_its_own(monkeypatch):
    """A frame over the probe's pixel count is probed on its centred window as a frame of its
    own. On the 25 keV strip regime with no sample (the sample frame is the reference) the
    window's 20 iterations leave the whole frame's residual (zero phase 1.120 % against
    1.116 %, single material 1.334 % against 1.330 %) in a fraction of the time; on the
    issue's 430 x 2220 frame of rods the residual ratio reads 1.19-1.20 whole, 1.20-1.22 on
    the window (four draws). The zero-phase t_r returned is the whole frame's."""
    from benchmarks.frame_size import STRIP_SETUP, strip_projection
    from pwf_dask import retrieval

    setup = replace(STRIP_SETUP, shape=(64, 320))
    _, reference, _, _ = strip_projection(setup, 1)
    whole = retrieval.choose_diffuser(reference.copy(), reference, **setup.geometry())
    monkeypatch.setattr(retrieval, "DIFFUSER_PROBE_MAX_PX", 64 * 160)
    assert retrieval.probe_window(reference.shape) == (slice(0, 64), slice(80, 240))
    window = retrieval.choose_diffuser(reference.copy(), reference, **setup.geometry())
    assert window.model == whole.model == "zero-phase"
    for model, pct in whole.residuals_pct.items():
        assert window.residuals_pct[model] == pytest.approx(pct, rel=0.02), (window.residuals_pct, pct)
    np.testing.assert_array_equal(window.transmission, whole.transmission)


def test_a_probe_on_a_window_that_chooses_the_fit_returns_the_whole_frames(monkeypatch):
    """The window's own single-material fit only decides: where it wins, the diffuser returned
    is the whole reference's fit, as a frame under the cap gets. Scene 68 rounded on a
    96 x 100 window of its 96 x 154 frame: ratio 0.187 (0.169 whole)."""
    from pwf_dask import retrieval

    setup = ZERO_PHASE_FAILS
    sim = simulate_projection(setup, seed=1)
    kw = kwargs(sim, coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    monkeypatch.setattr(retrieval, "DIFFUSER_PROBE_MAX_PX", 96 * 100)
    assert retrieval.probe_window(sim.sample.shape) == (slice(0, 96), slice(27, 127))
    choice = retrieval.choose_diffuser(sim.sample, sim.reference, **kw)
    r = choice.residuals_pct
    assert choice.model == "single-material" and r["single-material"] < 0.3 * r["zero-phase"], r
    geometry = {k: v for k, v in kw.items() if k != "sample_diffuser_distance_m"}
    whole = estimate_diffuser(sim.reference, **geometry, diffuser_model="single-material")
    np.testing.assert_array_equal(choice.transmission, whole)


@pytest.mark.gpu
def test_the_probe_window_on_cupy_reads_as_on_numpy(cupy, monkeypatch):
    """The window's crop on the device, bad pixels left out in the window as on the whole
    frame: the same residuals as NumPy's."""
    from benchmarks.frame_size import STRIP_SETUP, strip_projection
    from pwf_dask import retrieval

    setup = replace(STRIP_SETUP, shape=(64, 320))
    sample, reference, _, _ = strip_projection(setup, 1)
    bad = np.zeros(sample.shape, bool)
    bad[30:33, 150:152] = True  # inside the window
    monkeypatch.setattr(retrieval, "DIFFUSER_PROBE_MAX_PX", 64 * 160)
    cpu = retrieval.choose_diffuser(sample, reference, **setup.geometry(), bad_pixels=bad)
    gpu = retrieval.choose_diffuser(cupy.asarray(sample), cupy.asarray(reference), **setup.geometry(), bad_pixels=bad)
    assert gpu.model == cpu.model and isinstance(gpu.transmission, cupy.ndarray)
    for model, pct in cpu.residuals_pct.items():
        assert gpu.residuals_pct[model] == pytest.approx(pct, rel=1e-3)


def test_auto_probes_only_where_the_absorption_rule_gives_zero_phase():
    """Asked by name, or where the grains absorb (10 keV), no probe runs: the model named or
    chosen by absorption, as before the probe."""
    from pwf_dask.retrieval import choose_diffuser, probes_diffuser

    assert probes_diffuser("auto", "zero-phase")
    assert not probes_diffuser("auto", "single-material")
    assert not probes_diffuser("zero-phase", "zero-phase")
    sim = simulate_projection(SpeckleSetup(shape=(48, 48)), seed=2)
    choice = choose_diffuser(
        sim.sample, sim.reference, **kwargs(sim, coherence_length_x_m=3.5e-6, coherence_length_y_m=4.3e-6)
    )
    assert (choice.model, choice.residuals_pct) == ("single-material", {}) and choice.beta_over_delta > 0
    res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=5, diffuser_model="zero-phase"))
    assert res.parameters["diffuser_probe_residual_pct"] is None


def test_a_warm_start_stops_once_j_settles_at_the_error_of_a_start_from_zero():
    """The J test's jtol 3e-5 (docs/methods.md, "jtol 3e-5, judged against the truth"): a
    projection warm-started from its neighbour (0.45 deg before, its unzeroed psi, as a chain
    does) stops at 180 iterations with the phase error of the run from zero (360); with the
    former 1e-5 it took 300 for the same error (measured: 0.0724 / 0.0709 against 0.0716).
    Run under J's test alone (``stationary_terms="j"``): with the default ``"j-or-data"`` the
    data term stops this small frame from zero at 176 (0.0757) and the warm start at 200
    (0.0745), a tie (session 67)."""
    setup = SpeckleSetup(shape=(64, 256))
    fov_m = setup.shape[1] * setup.pixel_size_m
    phantom = default_phantom(fov_m, np.random.default_rng(2), height_m=setup.shape[0] * setup.pixel_size_m)
    before = simulate_projection(setup, phantom, 0.0, seed=1)
    now = simulate_projection(setup, phantom, 0.45, seed=1)
    kw = dict(
        setup.geometry(),
        coherence_length_x_m=setup.coherence_length_x_m,
        coherence_length_y_m=setup.coherence_length_y_m,
        fft_workers=1,
        stationary_terms="j",
    )
    start = retrieve_projection(before.sample, before.reference, zero_background=False, **kw)
    cold = retrieve_projection(now.sample, now.reference, **kw)
    warm = retrieve_projection(now.sample, now.reference, initial=-start.attenuation + 1j * start.phase, **kw)
    assert cold.converged and warm.converged
    assert warm.iterations < 0.6 * cold.iterations

    def error(r):
        return float(np.sqrt(np.mean((r.phase - now.phase) ** 2) / np.mean(now.phase**2)))

    assert error(warm) < error(cold) + 0.005


@pytest.mark.slow
def test_a_detector_halo_given_is_modelled_and_gives_back_the_phase_it_cost():
    """The detector spreads 30 % of the light over a 3 um halo (scattered scintillation light,
    beside a 0.75 um core; benchmarks/detector_psf.py): outside the paper's model PWF reads
    the phase of this 1e3 ph/px P3000 scene with error 0.31 (gain 0.84). Told the halo
    (``detector_halo_fraction``, ``detector_halo_radius_m``), the model blurs |v|^2 as the
    detector did and reads 0.15 (gain 0.995), the lengths calibrated either way; recorded."""
    halo = dict(detector_halo_fraction=0.3, detector_halo_radius_m=3e-6)
    setup = SpeckleSetup(shape=(256, 256), photons=1e3, detector_blur_fwhm_m=0.75e-6, **halo)
    sim = simulate_projection(setup, seed=2)
    background = np.abs(sim.phase) < 1e-6
    err = {}
    for told in (False, True):
        res = retrieve_projection(sim.sample, sim.reference, **kwargs(sim), **(halo if told else {}))
        err[told] = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)["phase_error"]
        assert res.parameters["detector_halo_fraction"] == (0.3 if told else 0.0)
    assert err[False] > 0.25 and err[True] < 0.2, err
    with pytest.raises(ValueError, match="halo fraction"):
        retrieve_projection(sim.sample, sim.reference, **kwargs(sim), detector_halo_fraction=1.5)


@pytest.mark.slow
def test_the_sample_images_noise_as_wiener_floor_keeps_a_noise_free_reference_from_breaking_the_zero_phase_diffuser():
    """Random scene 24 of the benchmarks on a 96 x 128 frame: coarse grains (5.2 µm), a
    coherence length of 20 pixels, the zero-phase diffuser, and a noise-free reference (many
    flats averaged) beside a sample image at 842 ph/px. The Wiener filter then reads a
    noise-to-signal ratio near 1e-6 and inverts the IOTF past what the model bears: the phase
    comes out inverted with the ratio as read (``diffuser_nsr_floor=0``; measured: error 4.0,
    gain -2.6). The default floor, half the sample image's noise over the reference's speckle
    (``"sample"``), keeps it (measured: error 0.26, gain 0.86), and so does a fixed floor of
    1e-4 (0.32, gain 1.19); recorded in ``parameters``."""
    setup = SpeckleSetup(
        shape=(96, 128),
        energy_eV=21722.0,
        pixel_size_m=0.3305e-6,
        sample_diffuser_distance_m=0.0,
        diffuser_detector_distance_m=0.1315,
        coherence_length_x_m=6.687e-6,
        coherence_length_y_m=5.770e-6,
        photons=842.0,
        diffuser_radius_median_m=5.18e-6,
        diffuser_grain_shape="mixed",
    )
    sim = simulate_projection(setup, seed=24)
    noiseless = SpeckleSimulator(setup, seed=24)
    reference = noiseless.intensity(None, noiseless.diffuser())
    background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
    lengths = dict(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)

    def run(floor=None):
        told = {} if floor is None else {"diffuser_nsr_floor": floor}
        geometry = sim.geometry()
        res = retrieve_projection(sim.sample, reference, **geometry, background_mask=background, **told, **lengths)
        assert res.parameters["diffuser_model"] == "zero-phase"
        assert res.parameters["diffuser_nsr_floor"] == ("sample" if floor is None else floor)
        return errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)

    bare, floored, default = run(0.0), run(1e-4), run()
    assert bare["phase_error"] > 1.0 and bare["phase_gain"] < 0.5
    for held in (floored, default):
        assert held["phase_error"] < 0.4 and 0.8 < held["phase_gain"] < 1.3, held
