"""Background of retrieved projections and tomograms: the surface fit and the sample-free mask."""

import numpy as np
import pytest

from pwf_dask.physics import background as bg


def _lstsq_surface(image, mask, degree):
    """The same fit from a design matrix of every pixel (the textbook route)."""
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]].astype(np.float64)
    yy /= image.shape[0] - 1
    xx /= image.shape[1] - 1
    a = np.stack([yy**i * xx**j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=-1)
    coef, *_ = np.linalg.lstsq(a[mask], image[mask].astype(np.float64), rcond=None)
    return a @ coef


@pytest.mark.parametrize("degree", [1, 2])
def test_surface_from_moments_is_the_least_squares_surface(rng, degree):
    image = rng.normal(size=(70, 90)).astype(np.float32)
    mask = rng.random(image.shape) < 0.3
    np.testing.assert_allclose(bg.fit_surface(image, mask, degree), _lstsq_surface(image, mask, degree), atol=1e-10)
    one_row = np.zeros(image.shape, bool)
    one_row[5] = True  # rank-deficient in y: the minimum-norm solution, as lstsq gives
    np.testing.assert_allclose(
        bg.fit_surface(image, one_row, degree), _lstsq_surface(image, one_row, degree), atol=1e-9
    )


def test_a_quadratic_background_is_removed_exactly_around_a_sample(rng):
    ny, nx = 96, 128
    yy, xx = np.mgrid[0:ny, 0:nx] / 100.0
    surface = 0.3 + 0.2 * yy - 0.1 * xx + 0.05 * yy * xx + 0.07 * xx**2
    disk = (np.hypot(yy * 100 - 48, xx * 100 - 60) < 20).astype(float)
    phase = surface - 2.0 * disk + rng.normal(0, 1e-3, (ny, nx))
    mask = bg.detect_background(phase)
    assert not mask[disk > 0].any() and mask.mean() > 0.6
    flat = bg.zero_background(phase, mask, degree=2)
    assert abs(flat[mask]).max() < 6e-3
    np.testing.assert_allclose(flat[disk > 0].mean(), -2.0, atol=5e-3)


def _deep_rods_frame(rng):
    """A wide frame of three 170 rad rods on a 130 rad tilt, its background 6 rad off flat at
    low frequency (PWF's relative error) under 0.2 rad of noise: (phase, sample map, the
    phase without the tilt, which a background plane should leave)."""
    ny, nx = 60, 900
    x = np.arange(nx, dtype=float)
    rods = np.zeros(nx)
    for centre, radius in ((150, 110), (480, 150), (780, 90)):
        inside = np.abs(x - centre) < radius
        rods[inside] = -170 * np.sqrt(1 - ((x[inside] - centre) / radius) ** 2)
    untilted = rods + 6 * np.sin(2 * np.pi * x / nx)
    phase = (130 * x / nx + untilted)[None, :] + rng.normal(0, 0.2, (ny, nx))
    return phase, np.broadcast_to(rods < 0, (ny, nx)), untilted[None, :]


def test_a_projection_background_off_flat_by_a_few_per_cent_is_found_whole(rng):
    """With the noise tolerance alone the detection keeps about one gap between deep rods
    (the others sit more than 5 noise sigmas off its plane), and that gap's plane tilts the
    frame; a projection's tolerance of 5 % of the sample's depth finds every gap and halves
    the error (the 430 x 2220 rod strip: 11.5 -> 8.0 rad, docs/validation.md)."""
    phase, sample, untilted = _deep_rods_frame(rng)

    def rms_error(mask):
        return np.sqrt(np.mean((bg.zero_background(phase, mask) - untilted) ** 2))

    noise_only = bg.detect_background(phase)
    assert noise_only[~sample].mean() < 0.45 and rms_error(noise_only) > 4.0
    found = bg.projection_background(phase)
    assert not found[sample].any() and found[~sample].mean() > 0.8
    assert rms_error(found) < 2.6


def test_the_plane_taken_off_is_kept_as_three_terms(rng):
    """zeroed_with_plane: the same image as zero_background, and the plane it took off as
    [constant, row slope, column slope] per frame height and width, which rebuild the image."""
    ny, nx = 40, 70
    yy, xx = np.mgrid[0:ny, 0:nx].astype(float)
    disk = np.hypot(yy - 20, xx - 30) < 10
    image = 0.3 + 0.2 * yy / (ny - 1) - 0.1 * xx / (nx - 1) - 2.0 * disk + rng.normal(0, 1e-4, (ny, nx))
    zeroed, terms = bg.zeroed_with_plane(image, ~disk)
    np.testing.assert_array_equal(zeroed, bg.zero_background(image, ~disk))
    np.testing.assert_allclose(terms, [0.3, 0.2, -0.1], atol=2e-4)
    np.testing.assert_allclose(zeroed + bg.plane_from_terms(terms, image.shape), image, atol=1e-12)
    with pytest.raises(ValueError, match="fewer than"):
        bg.zeroed_with_plane(image, np.zeros(image.shape, bool))


def test_a_wide_tomogram_slice_is_searched_binned_and_fitted_at_full_resolution(rng):
    """Above BACKGROUND_SEARCH_PX the sample-free area is found on a binned copy (17x faster
    on 2560^2 slices); the quadratic under it still comes off at full resolution."""
    from pwf_dask.tomo import tomography

    n = 2 * tomography.BACKGROUND_SEARCH_PX + 37  # binned 2 x 2, a remainder at the edges
    yy, xx = np.mgrid[0:n, 0:n] / n
    disk = np.hypot(yy - 0.5, xx - 0.45) < 0.2
    surface = 1e-7 * (0.5 + yy - 0.7 * xx + 0.3 * xx * yy + 0.2 * yy**2)
    slices = (surface + 1e-6 * disk + rng.normal(0, 1e-8, (n, n)))[None].astype(np.float32)
    mask = tomography.background_mask(slices[0].astype(np.float64))
    assert not mask[disk].any() and mask[~disk].mean() > 0.8 and not mask[-1].any()
    out = tomography.remove_background(slices)
    assert out.dtype == np.float32
    assert abs(out[0][~disk & mask]).max() < 1e-7
    np.testing.assert_allclose(out[0][disk].mean(), 1e-6, rtol=0.01)


@pytest.mark.gpu
def test_background_is_found_and_zeroed_on_the_device(cupy, rng):
    """On CuPy the detection and the surface stay on the device (``cupyx.scipy.ndimage``;
    ~1.3 s of host NumPy per full frame before) and give NumPy's mask and images."""
    ny, nx = 80, 112
    yy, xx = np.mgrid[0:ny, 0:nx] / 100.0
    disk = (np.hypot(yy * 100 - 40, xx * 100 - 50) < 18).astype(float)
    phase = 0.2 + 0.1 * yy - 3.0 * disk + rng.normal(0, 1e-2, (ny, nx))
    attenuation = 0.01 * disk + rng.normal(0, 1e-4, (ny, nx))
    mask = bg.detect_background(phase, attenuation)
    on_device = bg.detect_background(cupy.asarray(phase), cupy.asarray(attenuation))
    assert isinstance(on_device, cupy.ndarray)
    np.testing.assert_array_equal(cupy.asnumpy(on_device), mask)
    flat = bg.zero_background(cupy.asarray(phase), on_device)
    assert isinstance(flat, cupy.ndarray)
    np.testing.assert_allclose(cupy.asnumpy(flat), bg.zero_background(phase, mask), atol=1e-12)
