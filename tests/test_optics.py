"""Propagation and filters against analytic results."""

import numpy as np
import pytest

from pwf_dask.physics import optics


def gaussian_beam(x, y, w0):
    return np.exp(-(x**2 + y**2) / w0**2)


def fresnel_gaussian(x, y, w0, wavelength, z):
    """Analytic paraxial Gaussian beam at z (without the exp(ikz) carrier)."""
    zr = np.pi * w0**2 / wavelength
    q0 = -1j * zr  # exp(+ikz) convention: q = z - i z_R
    q = q0 + z
    k = 2 * np.pi / wavelength
    return (q0 / q) * np.exp(1j * k * (x**2 + y**2) / (2 * q))


def test_wavelength_of_10keV():
    assert optics.wavelength_m(10_000) == pytest.approx(1.23984e-10, rel=1e-5)
    with pytest.raises(ValueError):
        optics.wavelength_m(0)


@pytest.mark.parametrize("precision", [np.complex128, np.complex64])
def test_gaussian_beam_matches_fresnel_solution(precision):
    n, p = 256, 0.5e-6
    wl = optics.wavelength_m(10_000)
    w0 = 6e-6
    c = (np.arange(n) - n // 2) * p
    x, y = np.meshgrid(c, c)
    u0 = gaussian_beam(x, y, w0).astype(precision)
    for z in (5e-3, 50e-3, 0.2):
        num = optics.angular_spectrum_propagate(u0, p, wl, z)
        ana = fresnel_gaussian(x, y, w0, wl, z)
        err = np.abs(num - ana).max() / np.abs(ana).max()
        assert err < (1e-4 if precision == np.complex128 else 2e-3), (z, err)


def test_forward_then_back_is_identity_and_energy_is_conserved(rng):
    n, p = 128, 0.65e-6
    wl = optics.wavelength_m(12_000)
    f = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))).astype(np.complex64)
    g = optics.angular_spectrum_propagate(f, p, wl, 0.02)
    assert np.sum(np.abs(g) ** 2) == pytest.approx(np.sum(np.abs(f) ** 2), rel=1e-5)
    back = optics.angular_spectrum_propagate(g, p, wl, -0.02)
    assert np.abs(back - f).max() < 1e-4 * np.abs(f).max()


def test_zero_distance_costs_nothing():
    f = np.ones((16, 16), np.complex64)
    assert optics.angular_spectrum_propagate(f, 1e-6, 1e-10, 0.0) is f


def test_kernel_has_no_single_precision_cancellation():
    # exp(i 2 pi L / lambda) would be ~1e9 rad; the kernel must be exact at DC and smooth
    k = optics.angular_spectrum_kernel((64, 64), 0.65e-6, optics.wavelength_m(10_000), 0.02, dtype=np.complex64)
    assert k[0, 0] == 1
    v, u = optics.frequency_grid((64, 64), 0.65e-6)
    wl = optics.wavelength_m(10_000)
    fresnel = np.exp(-1j * np.pi * wl * 0.02 * (u**2 + v**2))
    assert np.abs(k - fresnel).max() < 1e-5


@pytest.mark.gpu
def test_kernel_is_built_on_the_device_as_exp_i_2pi_w_minus_k_l(cupy):
    """Q = exp(i 2 pi (w - 1/lambda) L) (Algorithm S2), built on the arrays' device: the same
    values as the closed form in complex128 on the host, evanescent waves (q > 1/lambda, here
    on a grid of 0.05 nm pixels) zeroed."""
    wl = optics.wavelength_m(10_000)
    for pixel_m, dtype in ((0.65e-6, np.complex64), (5e-11, np.complex128)):
        k = optics.angular_spectrum_kernel((40, 50), pixel_m, wl, 0.02, cupy, dtype)
        assert type(k).__module__.startswith(cupy.__name__) and k.dtype == dtype
        v, u = optics.frequency_grid((40, 50), pixel_m)
        q2 = u**2 + v**2
        w = np.sqrt(np.maximum(1 / wl**2 - q2, 0))
        closed = np.where(q2 < 1 / wl**2, np.exp(2j * np.pi * (w - 1 / wl) * 0.02), 0)
        # w - 1/lambda cancels in the closed form (1/lambda = 8e9 / m): 1e-7 rad of rounding there
        np.testing.assert_allclose(cupy.asnumpy(k), closed, atol=1e-6)
        assert (pixel_m > 1e-9) or (cupy.asnumpy(k)[q2 >= 1 / wl**2] == 0).all()


def test_iotf_is_fourier_transform_of_ipsf():
    n, p = 256, 0.25e-6
    xc, yc = 3.47e-6, 4.31e-6
    c = (np.arange(n) - n // 2) * p
    x, y = np.meshgrid(c, c)
    ipsf = 2 / (xc * yc) * np.exp(-2 * np.pi * (x**2 / xc**2 + y**2 / yc**2))  # Eq. (IPSF)
    otf = np.abs(np.fft.fft2(np.fft.ifftshift(ipsf))) * p * p
    ana = optics.iotf((n, n), p, xc, yc, half=False, dtype=np.float64)
    assert np.abs(otf - ana).max() < 1e-6
    assert optics.iotf((8, 8), p, 0.0, 0.0) is None


def test_detector_halo_is_the_exponentials_hankel_transform():
    """The halo's transfer function (1 + (2 pi a q)^2)^(-3/2) is the Fourier transform of
    exp(-r / a) / (2 pi a^2): back on the grid it is that kernel, holding its fraction of the light."""
    n, p, a, f = 512, 0.25e-6, 2.5e-6, 0.3
    mtf = optics.detector_transfer_function((n, n), p, 0.0, f, a, half=False, dtype=np.float64)
    psf = np.fft.fftshift(np.fft.ifft2(mtf).real) / (p * p)
    c = (np.arange(n) - n // 2) * p
    r = np.hypot(*np.meshgrid(c, c))
    kernel = f * np.exp(-r / a) / (2 * np.pi * a * a)
    ring = (r > 2 * p) & (r < 6 * a)  # off the delta at r = 0 and the cusp's next pixels
    np.testing.assert_allclose(psf[ring], kernel[ring], rtol=0.02, atol=1e-3 * kernel.max())
    assert psf.sum() * p * p == pytest.approx(1.0)
    assert psf[n // 2, n // 2] * p * p == pytest.approx(1 - f, abs=0.01)


def test_a_gaussian_detector_blur_is_the_iotf_of_longer_coherence_lengths():
    """Eq. (IOTF) times a Gaussian of FWHM w is Eq. (IOTF) at sqrt(x^2 + 4 pi sigma^2): in PWF's
    model the detector's Gaussian blur and the source's are one, so a calibration reads both."""
    shape, p, w = (64, 96), 0.65e-6, 1.5e-6
    both = optics.iotf(shape, p, 3.47e-6, 4.31e-6, dtype=np.float64) * optics.detector_transfer_function(
        shape, p, w, dtype=np.float64
    )
    x, y = optics.blurred_coherence_length_m(3.47e-6, w), optics.blurred_coherence_length_m(4.31e-6, w)
    np.testing.assert_allclose(both, optics.iotf(shape, p, x, y, dtype=np.float64), rtol=1e-12)
    assert optics.detector_transfer_function(shape, p) is None  # no blur costs nothing
    # the model's filter without a halo is Eq. (IOTF) itself, bit for bit; at full coherence none
    np.testing.assert_array_equal(
        optics.intensity_transfer_function(shape, p, 3.47e-6, 4.31e-6), optics.iotf(shape, p, 3.47e-6, 4.31e-6)
    )
    assert optics.intensity_transfer_function(shape, p, 0.0, 0.0) is None
    halo = optics.intensity_transfer_function(shape, p, 0.0, 0.0, 0.2, 5e-6, dtype=np.float64)
    np.testing.assert_array_equal(halo, optics.detector_transfer_function(shape, p, 0.0, 0.2, 5e-6, dtype=np.float64))
    for bad in ((-1e-6, 0.0, 0.0), (0.0, 1.0, 1e-6), (0.0, 0.1, -1e-6)):
        with pytest.raises(ValueError, match="detector blur"):
            optics.detector_transfer_function(shape, p, *bad)


def test_regularization_window_and_preconditioner():
    shape = (32, 32)
    g2 = optics.regularization_window(shape, 1e-6, 3e-6, 3e-6, gamma=1.0, half=False, dtype=np.float64)
    stf = optics.sample_transfer_function(shape, 1e-6, 3e-6, 3e-6, gamma=1.0, half=False, dtype=np.float64)
    assert np.allclose(g2, 1 - stf) and g2[0, 0] == 0
    assert np.allclose(stf, optics.iotf(shape, 1e-6, 3e-6, 3e-6, half=False, dtype=np.float64) ** 2)
    assert not optics.regularization_window(shape, 1e-6, 3e-6, 3e-6, gamma=0.0).any()
    p = optics.preconditioner(shape, half=False, dtype=np.float64)
    v, u = optics.frequency_grid(shape)
    assert p[0, 0] == 0
    assert p[0, 1] == pytest.approx(1 / (1 / 32) ** 2)
    q2 = u**2 + v**2
    assert np.allclose(p[q2 > 0] * q2[q2 > 0], 1)


def test_geometry_is_validated_once_with_the_same_one_line_messages_everywhere():
    from pwf_dask import retrieve_projection
    from pwf_dask.physics.geometry import Geometry

    g = Geometry(10_000, 0.65e-6, 0.0, 20e-3, diffuser_upstream_m=0.5)
    assert g.wavelength_m == pytest.approx(1.2398e-10, rel=1e-4)
    assert g.speckle_distance_m == pytest.approx(0.52)
    assert g.keywords() == {
        "energy_eV": 10_000.0,
        "pixel_size_m": 0.65e-6,
        "sample_diffuser_distance_m": 0.0,
        "diffuser_detector_distance_m": 20e-3,
        "diffuser_upstream_m": 0.5,
    }
    assert "diffuser_upstream_m" not in Geometry(10_000, 0.65e-6, 3e-3, 20e-3).keywords()
    bad = [
        (dict(pixel_size_m=-1e-6), "pixel_size_m must be positive, got -1e-06"),
        (dict(sample_diffuser_distance_m=-1e-3), "sample_diffuser_distance_m must be >= 0"),
        (dict(energy_eV=10.0), "energy_eV = 10 is outside"),  # keV for eV
        (dict(energy_eV="ten"), "energy_eV must be a number"),
        (dict(diffuser_upstream_m=0.1), "needs sample_diffuser_distance_m = 0"),
    ]
    good = dict(
        energy_eV=10_000, pixel_size_m=0.65e-6, sample_diffuser_distance_m=3e-3, diffuser_detector_distance_m=0.02
    )
    image = np.ones((16, 16))
    for change, message in bad:
        with pytest.raises(ValueError, match=message):
            Geometry(**{**good, **change})
        with pytest.raises(ValueError, match=message):
            retrieve_projection(image, image, **{**good, **change})
