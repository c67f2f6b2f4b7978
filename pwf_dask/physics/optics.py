"""Optics of the speckle set-up: free-space propagation and the Fourier-space filters of PWF.

Every filter of the paper lives here, by the paper's name:

* :func:`angular_spectrum_kernel` / :func:`angular_spectrum_propagate` - ``FreePropagation``
  of Algorithm S2, the angular-spectrum operator P_L with w = sqrt(1/lambda^2 - u^2 - v^2);
* :func:`iotf` - the intensity optical transfer function, Eq. (IOTF);
* :func:`pixel_transfer_function` - detector pixel integration (a box), used when the model
  forms intensities on a grid finer than the detector;
* :func:`detector_transfer_function` - the detector's own blur (scintillator, microscope), not
  in the paper's model: simulated scenes carry it, and a Gaussian one is the IOTF's
  (:func:`blurred_coherence_length_m`);
* :func:`intensity_transfer_function` - what the model applies to |v|^2: the IOTF, times the
  detector's halo where the user gives one;
* :func:`sample_transfer_function` and :func:`regularization_window` - Eqs. (STF), (regWin);
* :func:`preconditioner` - the inverse-Laplacian filter 1/(u^2+v^2), Eq. (precondFilter).

Frequencies are built on the host in float64 and cast once: in single precision the
propagation phase 2 pi w L would be ~1e9 rad and lose every significant digit.
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
from scipy import constants

PLANCK_EV_M = constants.h * constants.c / constants.e  # h c / e, in eV m


def wavelength_m(energy_eV: float) -> float:
    """X-ray wavelength lambda = h c / E in metres."""
    if not energy_eV > 0:
        raise ValueError(f"energy_eV must be positive, got {energy_eV}")
    return PLANCK_EV_M / float(energy_eV)


#: Where a speckle-imaging geometry can lie; a value outside is a unit slip (keV for eV, um
#: for m), refused before anything is computed or written. Wide on purpose: soft X-ray
#: microscopes to MeV radiography, nanometre pixels to 1 mm, tabletop to 1 km beamlines.
PLAUSIBLE_GEOMETRY = {
    "energy_eV": (1e2, 1e6, "X-ray photon energy in eV, e.g. 20000 for 20 keV"),
    "pixel_size_m": (1e-9, 1e-3, "the effective pixel in metres, e.g. 6.5e-06 for 6.5 um"),
    "sample_diffuser_distance_m": (0.0, 1e2, "L1 in metres"),
    "diffuser_detector_distance_m": (1e-5, 1e2, "L2 in metres, e.g. 0.02 for 20 mm"),
    "diffuser_upstream_m": (0.0, 1e3, "in metres"),
    "coherence_length_x_m": (1e-9, 1e-2, "in metres, e.g. 3.5e-06"),
    "coherence_length_y_m": (1e-9, 1e-2, "in metres, e.g. 3.5e-06"),
}


def check_diffuser_upstream(diffuser_upstream_m: float, sample_diffuser_distance_m: float) -> float:
    """A diffuser upstream of the sample: >= 0 m, and only where the scan records L1 = 0."""
    d = float(diffuser_upstream_m)
    if not (math.isfinite(d) and d >= 0):
        raise ValueError(f"diffuser_upstream_m must be >= 0, got {diffuser_upstream_m}")
    if d > 0 and sample_diffuser_distance_m != 0:
        raise ValueError(
            "diffuser_upstream_m > 0 puts the diffuser before the sample, which needs "
            f"sample_diffuser_distance_m = 0 (L1 = 0), got {sample_diffuser_distance_m}"
        )
    return d


def check_plausible_geometry(**values: float | None) -> None:
    """Refuse (ValueError, one line) a geometry value outside :data:`PLAUSIBLE_GEOMETRY`; None
    skips a value, and 0 is accepted for a coherence length (full coherence)."""
    for name, value in values.items():
        if value is None:
            continue
        low, high, hint = PLAUSIBLE_GEOMETRY[name]
        v = float(value)
        if name.startswith("coherence_length") and v == 0:
            continue
        if not (np.isfinite(v) and low <= v <= high):
            raise ValueError(f"{name} = {value:g} is outside {low:g} to {high:g}: expected {hint}")


def frequency_grid(shape: tuple[int, int], spacing: float | tuple[float, float] = 1.0, half: bool = False):
    """Spatial frequencies (v, u) in cycles per unit of ``spacing`` (float64, host); a pair
    is (y, x) spacing.

    ``v`` has shape (ny, 1) and ``u`` shape (1, nx) (or nx // 2 + 1 with ``half=True``, the
    rfft layout), so they broadcast to the spectrum's shape.
    """
    ny, nx = shape
    dy, dx = spacing if isinstance(spacing, tuple) else (spacing, spacing)
    v = np.fft.fftfreq(ny, d=dy)[:, None]
    u = (np.fft.rfftfreq(nx, d=dx) if half else np.fft.fftfreq(nx, d=dx))[None, :]
    return v, u


def _to(xp: ModuleType, a: np.ndarray, dtype):
    return xp.asarray(a.astype(dtype, copy=False))


def angular_spectrum_kernel(
    shape: tuple[int, int],
    pixel_size_m: float | tuple[float, float],
    wavelength: float,
    distance_m: float,
    xp: ModuleType = np,
    dtype=np.complex64,
):
    """Transfer function Q_k = exp(i 2 pi (w - 1/lambda) L) of Algorithm S2 ``FreePropagation``.

    The constant exp(i 2 pi L / lambda) is dropped (it does not change any intensity), and
    w - 1/lambda is evaluated as -q^2 / (1/lambda + w), which has no cancellation. Evanescent
    components (q > 1/lambda; never reached for X-rays at micrometre pixels) are zeroed.
    A pair ``pixel_size_m`` is the (y, x) pixel of a grid whose axes differ.
    """
    v, u = (xp.asarray(f) for f in frequency_grid(shape, pixel_size_m))
    q2 = u * u + v * v
    k2 = 1.0 / wavelength**2
    propagating = q2 < k2
    w = xp.sqrt(xp.where(propagating, k2 - q2, 0.0))
    phase = 2 * np.pi * (-q2 / (1.0 / wavelength + w)) * distance_m
    # exp(i phase) as cos + i sin, in float64 on xp's device: NumPy's complex exp is several
    # times slower for the same values, and a frame's kernels built on the host took 0.4 s each
    # at 2160 x 2560 before every GPU projection
    kernel = xp.empty(phase.shape, dtype=np.result_type(dtype, np.complex64))
    kernel.real = xp.where(propagating, xp.cos(phase), 0.0)
    kernel.imag = xp.where(propagating, xp.sin(phase), 0.0)
    return kernel


def angular_spectrum_propagate(field, pixel_size_m: float, wavelength: float, distance_m: float, fft=None):
    """Propagate a complex field by ``distance_m`` (negative: back-propagation); L = 0 is free."""
    from pwf_dask.backend import FFT, get_array_module

    if distance_m == 0:
        return field
    xp = get_array_module(field)
    fft = fft or FFT.for_module(xp)
    kernel = angular_spectrum_kernel(field.shape[-2:], pixel_size_m, wavelength, distance_m, xp, field.dtype)
    return fft.ifft2(fft.fft2(field) * kernel)


def _gaussian_lengths_sq(shape, pixel_size_m, length_x_m, length_y_m, half):
    v, u = frequency_grid(shape, pixel_size_m, half=half)
    return u * u * length_x_m**2 + v * v * length_y_m**2


def iotf(
    shape: tuple[int, int],
    pixel_size_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """Intensity optical transfer function, Eq. (IOTF):
    exp[-pi/2 (u^2 x_coh^2 + v^2 y_coh^2)], the Fourier transform of the Gaussian IPSF, Eq. (IPSF).

    Returns None for full coherence (both lengths 0): the blur then costs nothing.
    """
    if coherence_length_x_m == 0 and coherence_length_y_m == 0:
        return None
    a = _gaussian_lengths_sq(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, half)
    return _to(xp, np.exp(-0.5 * np.pi * a), dtype)


def pixel_transfer_function(
    shape: tuple[int, int],
    grid_spacing_m: float,
    detector_pixel_m: float,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """Transfer function sinc(u p) sinc(v p) of integration over a square detector pixel p."""
    v, u = frequency_grid(shape, grid_spacing_m, half=half)
    return _to(xp, np.sinc(u * detector_pixel_m) * np.sinc(v * detector_pixel_m), dtype)


#: FWHM of a Gaussian over its sigma, 2 sqrt(2 ln 2)
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


def check_detector_blur(blur_fwhm_m: float, halo_fraction: float, halo_radius_m: float) -> None:
    """One line for a detector blur that is not one: a negative width, a halo fraction outside [0, 1)."""
    if not (blur_fwhm_m >= 0 and 0 <= halo_fraction < 1 and halo_radius_m >= 0):
        raise ValueError(
            "detector blur: need a FWHM >= 0, a halo fraction (detector_halo_fraction) in [0, 1) and a halo "
            f"radius (detector_halo_radius_m) >= 0, got {blur_fwhm_m}, {halo_fraction}, {halo_radius_m}"
        )


def detector_transfer_function(
    shape: tuple[int, int],
    grid_spacing_m: float,
    blur_fwhm_m: float = 0.0,
    halo_fraction: float = 0.0,
    halo_radius_m: float = 0.0,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """Transfer function of the detector's point-spread function, which blurs the intensity
    before the pixels integrate it (the scintillator's depth of light emission, the
    microscope's aperture, scattered scintillation light).

    The PSF is a Gaussian core of FWHM ``blur_fwhm_m`` convolved with (1 - f) delta + f h,
    h(r) = exp(-r / a) / (2 pi a^2) a halo of 1/e radius a = ``halo_radius_m`` holding the
    fraction f = ``halo_fraction`` of the light. Its transfer function, with q = |(u, v)|:
    exp(-2 pi^2 sigma^2 q^2) [(1 - f) + f (1 + (2 pi a q)^2)^(-3/2)] (the exponential's Hankel
    transform). Not a term of the paper: the reference's calibration takes a Gaussian core
    into the coherence lengths (:func:`blurred_coherence_length_m`); a halo is outside the
    model. Returns None when there is no blur, so that it costs nothing.
    """
    check_detector_blur(blur_fwhm_m, halo_fraction, halo_radius_m)
    halo = halo_fraction > 0 and halo_radius_m > 0
    if blur_fwhm_m == 0 and not halo:
        return None
    v, u = frequency_grid(shape, grid_spacing_m, half=half)
    q2 = u * u + v * v
    sigma = blur_fwhm_m / FWHM_PER_SIGMA
    transfer = np.exp(-2.0 * np.pi**2 * sigma**2 * q2)
    if halo:
        transfer *= (1.0 - halo_fraction) + halo_fraction * (1.0 + (2.0 * np.pi * halo_radius_m) ** 2 * q2) ** -1.5
    return _to(xp, transfer, dtype)


def blurred_coherence_length_m(coherence_length_m: float, blur_fwhm_m: float) -> float:
    """The coherence length a Gaussian detector blur of FWHM ``blur_fwhm_m`` adds up to.

    The IOTF exp(-pi/2 u^2 x^2), Eq. (IOTF), times the blur's exp(-2 pi^2 sigma^2 u^2) is the
    IOTF of sqrt(x^2 + 4 pi sigma^2): the two blurs are one in PWF's forward model, Eq.
    (forwardModel), and a length calibrated from the reference includes the detector's.
    """
    sigma = blur_fwhm_m / FWHM_PER_SIGMA
    return math.sqrt(coherence_length_m**2 + 4.0 * math.pi * sigma**2)


def intensity_transfer_function(
    shape: tuple[int, int],
    pixel_size_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    detector_halo_fraction: float = 0.0,
    detector_halo_radius_m: float = 0.0,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """The filter PWF's forward model applies to the intensity |v|^2, Eq. (forwardModel): the
    IOTF, Eq. (IOTF), times the detector's halo (:func:`detector_transfer_function` with no
    Gaussian core: the calibrated lengths carry the core) where one is given. Without a halo it
    is :func:`iotf` itself, and None at full coherence."""
    otf = iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, xp, dtype, half)
    halo = detector_transfer_function(
        shape, pixel_size_m, 0.0, detector_halo_fraction, detector_halo_radius_m, xp, dtype, half
    )
    if halo is None:
        return otf
    return halo if otf is None else otf * halo


def sample_transfer_function(
    shape: tuple[int, int],
    pixel_size_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    gamma: float = 1.0,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """Sample transfer function, Eq. (STF): exp[-pi gamma (u^2 x_coh^2 + v^2 y_coh^2)]."""
    a = _gaussian_lengths_sq(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, half)
    return _to(xp, np.exp(-np.pi * gamma * a), dtype)


def regularization_window(
    shape: tuple[int, int],
    pixel_size_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    gamma: float = 1.0,
    xp: ModuleType = np,
    dtype=np.float32,
    half: bool = True,
):
    """Regularization window Gamma_k^2 = 1 - STF_k, Eq. (regWin). gamma = 0 gives 0 (no regularizer)."""
    stf = sample_transfer_function(
        shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, gamma, np, np.float64, half
    )
    return _to(xp, 1.0 - stf, dtype)


def preconditioner(shape: tuple[int, int], xp: ModuleType = np, dtype=np.float32, half: bool = True):
    """Inverse quadratic preconditioning filter P_k^-1 = 1/(u^2+v^2), Eq. (precondFilter).

    u, v in cycles per pixel, as the authors' released code (other units rescale the step by
    the pixel size squared); the DC term is 0: the mean phase is fixed afterwards by the
    background fit.
    """
    v, u = frequency_grid(shape, 1.0, half=half)
    q2 = u * u + v * v
    q2[0, 0] = 1.0
    p = 1.0 / q2
    p[0, 0] = 0.0
    return _to(xp, p, dtype)


def laplacian_symbol(shape: tuple[int, int], xp: ModuleType = np, dtype=np.float32, half: bool = True):
    """u^2 + v^2 (cycles per pixel squared): the inverse of :func:`preconditioner` away from DC."""
    v, u = frequency_grid(shape, 1.0, half=half)
    return _to(xp, u * u + v * v, dtype)
