"""Detector defects (zingers, hot and dead pixels): found, left out of PWF's data term, repaired."""

import numpy as np
import pytest
from measures import kwargs, relative_phase_error
from scipy import ndimage

from pwf_dask import retrieve_projection
from pwf_dask.physics.detector import _neighbours, find_outliers, noise_sigma, repair_outliers


@pytest.fixture(scope="module")
def sim(small_scene):
    """conftest's 256^2 P3000 scene."""
    return small_scene


def with_defects(image, seed, n_spikes, n_dead, amplitude=1.0):
    """Spikes of ``amplitude`` x the mean and dead (zero) pixels at random places, edges included."""
    rng = np.random.default_rng(seed)
    out = image.copy()
    idx = rng.choice(out.size, n_spikes + n_dead, replace=False)
    idx[0] = 0  # a corner: its neighbours are all inside the frame
    out.flat[idx[:n_spikes]] += amplitude * image.mean()
    out.flat[idx[n_spikes:]] = 0.0
    truth = np.zeros(out.shape, bool)
    truth.flat[idx] = True
    return out, truth


def test_neighbour_views_equal_the_ndimage_ring_filters(rng):
    """The shifted views give scipy.ndimage's 3 x 3 ring maximum, minimum and mean (mode
    "mirror", edges and corners included), and Immerkaer's sigma its convolution's."""
    img = rng.random((37, 52)).astype(np.float32)
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    views = _neighbours(img, np)
    np.testing.assert_array_equal(np.max(views, axis=0), ndimage.maximum_filter(img, footprint=ring, mode="mirror"))
    np.testing.assert_array_equal(np.min(views, axis=0), ndimage.minimum_filter(img, footprint=ring, mode="mirror"))
    mean = ndimage.convolve(img.astype(np.float64), ring / 8.0, mode="mirror")
    np.testing.assert_allclose(np.mean(views, axis=0), mean, rtol=1e-6)
    kernel = np.outer([1.0, -2.0, 1.0], [1.0, -2.0, 1.0])
    d = ndimage.convolve(img.astype(np.float64), kernel, mode="mirror")[1:-1:2, 1:-1:2]
    assert noise_sigma(img) == pytest.approx(1.4826 * np.median(np.abs(d)) / 6.0, rel=1e-5)


def test_clean_speckle_images_have_no_outliers(sim):
    """Speckle peaks are shared with their neighbours (coherence blur, pixel aperture)."""
    for image in (sim.sample, sim.reference):
        assert not find_outliers(image).any()


def test_spikes_and_dead_pixels_are_found_and_nothing_else(sim):
    img, truth = with_defects(sim.reference, 0, n_spikes=40, n_dead=10)
    found = find_outliers(img)
    np.testing.assert_array_equal(found, truth)
    repaired, mask = repair_outliers(img)
    np.testing.assert_array_equal(mask, truth)
    assert np.array_equal(repaired[~truth], img[~truth])
    # the neighbours' median is within the speckle's local spread of the true value
    err = np.abs(repaired[truth] - sim.reference[truth]) / sim.reference.mean()
    assert np.median(err) < 0.1
    assert img[truth].tolist() != repaired[truth].tolist()  # the input is not touched


def test_stacks_are_repaired_frame_by_frame(sim):
    a, ta = with_defects(sim.reference, 1, 5, 0)
    b, tb = with_defects(sim.sample, 2, 0, 5)
    _, mask = repair_outliers(np.stack([a, b]))
    np.testing.assert_array_equal(mask, np.stack([ta, tb]))


@pytest.mark.slow
def test_pwf_with_zingers_matches_the_clean_result(sim, small_scene_result):
    """65 zingers of 10x the mean in each image (1e-3 of the pixels): the clean image's error
    when they are left out (docs/validation.md); 2.7x it (0.177 for 0.067) with every pixel
    fitted after 300 iterations. The zingers lower the reference's phase sensitivity under the
    alpha rule's limit, and "auto" then gives the single-material fit up for zero phase (since
    session 101; the fit reads 0.476 there)."""
    clean = relative_phase_error(small_scene_result, sim)
    sample, truth_s = with_defects(sim.sample, 3, 65, 0, amplitude=10.0)
    reference, truth_r = with_defects(sim.reference, 4, 65, 0, amplitude=10.0)
    res = retrieve_projection(sample, reference, **kwargs(sim))
    assert res.parameters["outlier_pixels"] == truth_s.sum()
    assert res.parameters["outlier_pixels_reference"] == truth_r.sum()
    assert res.converged
    assert relative_phase_error(res, sim) < 1.1 * clean + 0.005
    assert res.residual_rmse < 1.2 * 100 * np.sqrt(np.mean(sim.sample) / sim.photons) / np.mean(sim.reference)
    raw = retrieve_projection(sample, reference, **kwargs(sim, outlier_sigma=0, max_iter=300))
    assert raw.parameters["outlier_pixels"] == 0
    assert relative_phase_error(raw, sim) > 2 * clean


def test_off_is_the_model_without_it(sim):
    """Nothing flagged on a clean scene: the result is bitwise the one with the test off."""
    on = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, tol=0))
    off = retrieve_projection(sim.sample, sim.reference, **kwargs(sim, max_iter=60, tol=0, outlier_sigma=None))
    assert on.parameters["outlier_pixels"] == 0
    np.testing.assert_array_equal(on.phase, off.phase)
    np.testing.assert_array_equal(on.attenuation, off.attenuation)


def test_tracking_methods_get_repaired_images(sim):
    sample, _ = with_defects(sim.sample, 5, 20, 0, amplitude=10.0)
    res = retrieve_projection(sample, sim.reference, **kwargs(sim, method="umpa"))
    assert res.parameters["outlier_pixels"] == 20
    assert res.parameters["outlier_pixels_reference"] == 0


def test_a_negative_threshold_is_refused(sim):
    with pytest.raises(ValueError, match="outlier_sigma must be >= 0"):
        retrieve_projection(sim.sample, sim.reference, **kwargs(sim, outlier_sigma=-1))


def test_cupy_finds_and_repairs_the_same_pixels(cupy, sim):
    # seed 6 puts two dead pixels side by side, which neither module flags (a cluster)
    img, _ = with_defects(sim.reference, 6, 30, 10)
    repaired, mask = repair_outliers(cupy.asarray(img))
    assert isinstance(repaired, cupy.ndarray)
    cpu_repaired, cpu_mask = repair_outliers(img)
    assert cpu_mask.sum() == 38
    np.testing.assert_array_equal(cupy.asnumpy(mask), cpu_mask)
    np.testing.assert_allclose(cupy.asnumpy(repaired), cpu_repaired, rtol=1e-6)
