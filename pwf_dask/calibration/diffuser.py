"""The diffuser's transmission function t_r from the reference speckle (Methods: Diffuser transmission function).

* :func:`diffuser_transmission` - t_r: Wiener deconvolution of the reference with the IOTF,
  negatives clipped, square root, zero phase, back-propagation over L2 (the paper's
  estimate, ``diffuser_model="zero-phase"``); or, by default, a single-material phase screen
  t_r = exp(-(kappa + i) theta_r) fitted to the reference (``"single-material"``, see
  :func:`single_material_diffuser`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pwf_dask.backend import FFT, get_array_module
from pwf_dask.calibration.coherence import noise_to_signal, relative_noise_variance
from pwf_dask.physics import optics
from pwf_dask.pwf import kernels

#: L-BFGS iterations of the single-material fit (:func:`single_material_diffuser`)
REFINE_ITER = 25


#: ``diffuser_nsr_floor="sample"``: the Wiener NSR is at least this fraction of the ratio the
#: reference's speckle has at the sample image's photon noise (:func:`wiener_nsr`)
SAMPLE_NSR_FRACTION = 0.5
#: the floor read from the sample image's noise, not a number
SAMPLE_FLOOR = "sample"


def check_nsr_floor(nsr_floor, sample_allowed: bool = True) -> None:
    """A floor for :func:`wiener_nsr` that is not one ("sample" where ``sample_allowed``, or a
    number >= 0), refused in one line."""
    if nsr_floor == SAMPLE_FLOOR and sample_allowed:
        return
    try:
        value = float(nsr_floor)
    except (TypeError, ValueError):
        value = math.nan
    if isinstance(nsr_floor, bool) or not (math.isfinite(value) and value >= 0):
        raise ValueError(f"diffuser_nsr_floor must be 'sample' or a number >= 0, got {nsr_floor!r}")


def resolved_nsr_floor(nsr_floor, sample=None) -> tuple[float, float]:
    """``diffuser_nsr_floor`` as :func:`diffuser_transmission` takes it: (a fixed floor, the
    sample image's relative noise variance). "sample" reads the latter from ``sample``
    (:func:`pwf_dask.calibration.coherence.relative_noise_variance`; none given: no floor)."""
    check_nsr_floor(nsr_floor)
    if nsr_floor != SAMPLE_FLOOR:
        return float(nsr_floor), 0.0
    return 0.0, (0.0 if sample is None else relative_noise_variance(sample))


def wiener_nsr(
    reference_spectrum_power, pixel_radius2, iotf_half, floor: float = 0.0, sample_noise_per_bin: float = 0.0
) -> float:
    """The Wiener filters' noise-to-signal ratio: the reference's photon noise over its
    speckle (:func:`pwf_dask.calibration.coherence.noise_to_signal`), at least
    :data:`SAMPLE_NSR_FRACTION` of the sample image's noise over that speckle
    (``sample_noise_per_bin``: on the spectrum's scale) and at least ``floor``.

    Why: from a reference far cleaner than the sample image (a hundred flats averaged) the
    reference's own ratio falls to 1e-6 and the filter inverts the Gaussian IOTF down to a
    thousandth of its peak, where what it inverts is the model's own error (the IOTF's shape,
    the lengths, the pixel), not noise, and detail the sample image's noise hides anyway. On
    the random low-dose scenes with the reference at 100x the dose PWF then held 28 of 63
    (scene 24: gain 0.11, converged); with the sample's noise as the floor, 37; with a fixed
    floor of 1e-4, 34 (docs/methods.md, "A reference too clean breaks the zero-phase
    estimate"). With the reference at the sample's dose the two noises are alike and the
    reference's own ratio is taken."""
    noise = SAMPLE_NSR_FRACTION * sample_noise_per_bin
    return max(noise_to_signal(reference_spectrum_power, pixel_radius2, iotf_half, noise), floor)


def diffuser_transmission(
    reference,
    *,
    pixel_size_m: float,
    wavelength: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pad: int = 0,
    shape: tuple[int, int] | None = None,
    nsr: float | None = None,
    nsr_floor: float = 0.0,
    sample_noise_var: float = 0.0,
    detector_halo_fraction: float = 0.0,
    detector_halo_radius_m: float = 0.0,
    phase_screen_iter: int = 0,
    diffuser_model: str = "zero-phase",
    beta_over_delta: float | None = None,
    refine_iter: int = REFINE_ITER,
    upstream_m: float = 0.0,
    fft: FFT | None = None,
):
    """Diffuser transmission t_r (Methods, Diffuser transmission function).

    ``diffuser_model="single-material"`` returns :func:`single_material_diffuser` (needs
    ``beta_over_delta``). With ``"zero-phase"`` (the paper's): the reference is
    Wiener-deconvolved with the IOTF (estimating the coherent speckle intensity), clipped at
    0, square-rooted, given zero phase and back-propagated by -L2. With ``pad`` the frame is
    first extended by reflection to ``shape`` (the computational grid), so that light entering
    the frame from outside is modelled by plausible speckle, not by periodic wrap-around.
    ``upstream_m`` > 0 (not in the paper): the diffuser sits that far upstream of the sample
    (the scan records L1 = 0), so the sample is lit by the diffuser's field propagated over
    ``upstream_m`` and the reference is the diffuser seen over ``upstream_m`` + L2. The single
    material is fitted over that whole distance and t_r is its field at the sample plane. The
    zero-phase estimate does not depend on it (back-propagating over L2 + d and forward over
    d is back-propagating over L2). ``detector_halo_fraction`` and ``detector_halo_radius_m``:
    the detector's halo, deconvolved or fitted beside the IOTF
    (:func:`pwf_dask.physics.optics.intensity_transfer_function`); none by default.
    ``nsr_floor``, ``sample_noise_var``: the least noise-to-signal ratio the Wiener filters
    take, fixed and as the sample image's relative noise variance gives it (:func:`wiener_nsr`,
    :func:`resolved_nsr_floor`; 0 and 0: the reference's as read).
    """
    if diffuser_model not in DIFFUSER_MODELS:
        raise ValueError(f"unknown diffuser_model {diffuser_model!r}: choose one of {', '.join(DIFFUSER_MODELS)}")
    if not (math.isfinite(upstream_m) and upstream_m >= 0):
        raise ValueError(f"diffuser_upstream_m must be >= 0, got {upstream_m}")
    check_nsr_floor(nsr_floor, sample_allowed=False)  # resolved_nsr_floor reads "sample"
    if diffuser_model == "single-material":
        if beta_over_delta is None:
            raise ValueError("diffuser_model='single-material' needs beta_over_delta")
        t = single_material_diffuser(
            reference,
            beta_over_delta=beta_over_delta,
            pixel_size_m=pixel_size_m,
            wavelength=wavelength,
            diffuser_detector_distance_m=diffuser_detector_distance_m + upstream_m,
            coherence_length_x_m=coherence_length_x_m,
            coherence_length_y_m=coherence_length_y_m,
            pad=pad,
            shape=shape,
            nsr=nsr,
            nsr_floor=nsr_floor,
            sample_noise_var=sample_noise_var,
            iterations=refine_iter,
            detector_halo_fraction=detector_halo_fraction,
            detector_halo_radius_m=detector_halo_radius_m,
            fft=fft,
        ).transmission
        # the diffuser's field at the sample plane (0 m: the same array, nothing computed)
        return optics.angular_spectrum_propagate(t, pixel_size_m, wavelength, upstream_m, fft)
    xp = get_array_module(reference)
    fft = fft or FFT.for_module(xp)
    ref, shape = _padded_reference(reference, pad, shape, xp)
    spec = fft.rfft2(ref)
    h = optics.intensity_transfer_function(
        shape,
        pixel_size_m,
        coherence_length_x_m,
        coherence_length_y_m,
        detector_halo_fraction,
        detector_halo_radius_m,
        xp,
        np.float64,
    )
    if h is not None:
        v, u = optics.frequency_grid(shape, 1.0, half=True)
        r2 = xp.asarray(u * u + v * v)
        if nsr is None:
            nsr = wiener_nsr(spec.real**2 + spec.imag**2, r2, h, nsr_floor, sample_noise_var * shape[0] * shape[1])
        spec *= h / (h * h + max(nsr, 1e-12))
    intensity = fft.irfft2(spec, s=shape)
    amplitude = xp.sqrt(xp.clip(intensity, 0, None)).astype(xp.complex128)
    t = optics.angular_spectrum_propagate(amplitude, pixel_size_m, wavelength, -diffuser_detector_distance_m, fft)
    if phase_screen_iter:
        t = refine_phase_screen(
            t, amplitude.real, pixel_size_m, wavelength, diffuser_detector_distance_m, phase_screen_iter, fft
        )
    return t


def refine_phase_screen(t, detector_amplitude, pixel_size_m, wavelength, distance_m, iterations, fft=None):
    """Gerchberg-Saxton refinement of the zero-phase diffuser estimate towards a phase screen.

    The zero-phase estimate reproduces the reference at exactly L2 but is strongly
    amplitude-modulated at the diffuser (max|t|^2 ~ 6 on sandpaper), unlike a real abrasive
    layer (|t| <= 1, nearly pure phase). Alternating |t| = mean|t| at the diffuser with the
    measured amplitude at the detector gives a screen that also behaves like the real one at
    other distances, which is what the sample's lens-like curvature probes.
    """
    xp = get_array_module(t)
    fft = fft or FFT.for_module(xp)
    k = optics.angular_spectrum_kernel(t.shape, pixel_size_m, wavelength, distance_m, xp, t.dtype)
    kc = xp.conj(k)
    level = float(xp.mean(xp.abs(t)))
    for _ in range(iterations):
        t = level * xp.exp(1j * xp.angle(t))
        v = fft.ifft2(fft.fft2(t) * k)
        v = detector_amplitude * xp.exp(1j * xp.angle(v))
        t = fft.ifft2(fft.fft2(v) * kc)
    return t


DIFFUSER_MODELS = ("single-material", "zero-phase")
#: what ``diffuser_model`` may ask for: a model, or ``"auto"`` (:func:`choose_diffuser_model`)
DIFFUSER_MODEL_CHOICES = (*DIFFUSER_MODELS, "auto")
#: the diffuser material's linear attenuation coefficient (1/m) below which ``"auto"`` takes the
#: zero-phase estimate: under it the single-material fit drifts (docs/methods.md, "Weak diffuser
#: absorption"); silicon carbide reaches it near 11.4 keV, alumina near 10.7 keV
AUTO_MIN_ATTENUATION_PER_M = 5e3


def choose_diffuser_model(diffuser_model: str, attenuation_per_m: float) -> str:
    """The diffuser model to fit: ``"auto"`` takes the single material where the diffuser's
    linear attenuation coefficient mu = 2 k beta reaches :data:`AUTO_MIN_ATTENUATION_PER_M`,
    else the paper's zero-phase estimate.

    The single-material fit sees the slow part of theta only through the grains' absorption
    (kappa theta, the absorption term of the CTF). Where they hardly absorb (silicon carbide:
    mu 7.4 /mm at 10 keV, 3.8 at 12.5, 0.9 at 20) each fit iteration lowers the sample's phase
    gain, from 0.96 at the fit's linear start to 0.40 after the default 25 at 20 keV, and zero
    phase is the better model (Methods, Diffuser transmission function). Any other model is
    returned as given.
    """
    if diffuser_model not in DIFFUSER_MODEL_CHOICES:
        raise ValueError(
            f"unknown diffuser_model {diffuser_model!r}: choose one of {', '.join(DIFFUSER_MODEL_CHOICES)}"
        )
    if diffuser_model != "auto":
        return diffuser_model
    return "single-material" if attenuation_per_m >= AUTO_MIN_ATTENUATION_PER_M else "zero-phase"


@dataclass
class DiffuserEstimate:
    """A single-material diffuser fitted to the reference: t_r = exp(-(kappa + i) theta_r)."""

    transmission: Any  # t_r on the computational grid (complex128)
    phase_delay: Any  # theta_r = k delta T_r in radians (>= 0 where there is more material)
    beta_over_delta: float
    residual_rmse: float  # rms(|P2 t|^2 * IPSF - reference) over the frame, in units of its mean
    initial_residual_rmse: float  # the same for the linear (CTF) start


def _padded_reference(reference, pad: int, shape, xp):
    ref = xp.asarray(reference, dtype=xp.float64)
    ny, nx = ref.shape
    shape = shape or (ny + 2 * pad, nx + 2 * pad)
    if tuple(shape) != (ny, nx):
        after = (shape[0] - ny - pad, shape[1] - nx - pad)
        ref = xp.pad(ref, ((pad, after[0]), (pad, after[1])), mode="reflect")
    return ref, tuple(shape)


def ctf_phase_delay(
    reference,
    *,
    beta_over_delta: float,
    pixel_size_m: float,
    wavelength: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pad: int = 0,
    shape: tuple[int, int] | None = None,
    nsr: float | None = None,
    nsr_floor: float = 0.0,
    sample_noise_var: float = 0.0,
    detector_halo_fraction: float = 0.0,
    detector_halo_radius_m: float = 0.0,
    fft: FFT | None = None,
):
    """Linear (contrast transfer function) estimate of a single-material diffuser's phase delay.

    A weak single-material object t = exp(-(kappa + i) theta) (kappa = beta/delta) gives, after
    L2 and the IPSF, reference - 1 ~ -2 IOTF (sin chi + kappa cos chi) theta in Fourier space,
    chi = pi lambda L2 q^2 (Cloetens et al. 1999). Inverted by a Wiener filter with the
    noise-to-signal of :func:`noise_to_signal`; the start of :func:`single_material_diffuser`.
    """
    xp = get_array_module(reference)
    fft = fft or FFT.for_module(xp)
    ref, shape = _padded_reference(reference, pad, shape, xp)
    spec = fft.rfft2(ref / float(xp.mean(ref)) - 1.0)
    v, u = optics.frequency_grid(shape, pixel_size_m, half=True)
    chi = np.pi * wavelength * diffuser_detector_distance_m * (u * u + v * v)
    transfer = 2.0 * (np.sin(chi) + beta_over_delta * np.cos(chi))
    h = optics.intensity_transfer_function(
        shape,
        pixel_size_m,
        coherence_length_x_m,
        coherence_length_y_m,
        detector_halo_fraction,
        detector_halo_radius_m,
        np,
        np.float64,
    )
    if h is not None:
        transfer = transfer * h
    transfer = xp.asarray(transfer)
    if nsr is None:
        vp, up = optics.frequency_grid(shape, 1.0, half=True)
        hh = xp.asarray(h) if h is not None else None
        noise = sample_noise_var * shape[0] * shape[1]
        nsr = wiener_nsr(spec.real**2 + spec.imag**2, xp.asarray(up * up + vp * vp), hh, nsr_floor, noise)
    theta_hat = -transfer * spec / (transfer * transfer + max(nsr, 1e-6))
    theta_hat[0, 0] = 0
    return fft.irfft2(theta_hat, s=shape)


def _two_loop_direction(g, pairs: list, first_step: float):
    """L-BFGS's direction q ~ H g by the two-loop recursion (Nocedal & Wright, Alg. 7.4) and
    the slope -<g, q>. Each update of q is fused with the next inner product taken of it
    (:func:`pwf_dask.pwf.kernels.axpy_dot`): the first loop's s_{k-1}.q, the second's
    y_{k+1}.q, and finally g.q; at 1080^2 this halved the fit's bookkeeping (issue #31)."""
    xp = get_array_module(g)
    q = g.copy()
    if not pairs:
        q *= first_step / max(float(xp.max(xp.abs(g))), 1e-300)
        return q, -float(xp.vdot(g, q))
    coeffs = []
    dot = float(xp.vdot(pairs[-1][0], q))
    for k in range(len(pairs) - 1, -1, -1):
        s, y, rho = pairs[k]
        coeffs.append(rho * dot)
        # after the oldest pair, the first inner product of the second loop: y_0.q
        dot = kernels.axpy_dot(q, -coeffs[-1], y, pairs[k - 1][0] if k else pairs[0][1])
    s, y, _ = pairs[-1]
    gamma = float(xp.vdot(s, y)) / float(xp.vdot(y, y))
    q *= gamma
    dot *= gamma
    for k, ((s, _y, rho), a) in enumerate(zip(pairs, reversed(coeffs))):
        dot = kernels.axpy_dot(q, a - rho * dot, s, pairs[k + 1][1] if k + 1 < len(pairs) else g)
    return q, -dot


def _lbfgs(value_and_gradient, x, iterations: int, memory: int = 10, first_step: float = 0.1):
    """Limited-memory BFGS with Armijo backtracking (Nocedal & Wright, Alg. 7.4/7.5), on any
    array module; ``first_step`` bounds the first move (max |dx|)."""
    xp = get_array_module(x)
    f, g = value_and_gradient(x)
    pairs: list[tuple[Any, Any, float]] = []
    for _ in range(iterations):
        q, slope = _two_loop_direction(g, pairs, first_step)
        if not slope < 0:  # not a descent direction: forget the curvature pairs
            pairs.clear()
            q = g * (first_step / max(float(xp.max(xp.abs(g))), 1e-300))
            slope = -float(xp.vdot(g, q))
        step = 1.0
        while True:
            x_new = x - step * q
            f_new, g_new = value_and_gradient(x_new)
            if f_new <= f + 1e-4 * step * slope:
                break
            step *= 0.5
            if step < 1e-8:
                return x, f
        s, y = x_new - x, g_new - g
        sy = float(xp.vdot(s, y))
        if sy > 0:
            pairs.append((s, y, 1.0 / sy))
            if len(pairs) > memory:
                pairs.pop(0)
        x, f, g = x_new, f_new, g_new
    return x, f


def single_material_diffuser(
    reference,
    *,
    beta_over_delta: float,
    pixel_size_m: float,
    wavelength: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pad: int = 0,
    shape: tuple[int, int] | None = None,
    nsr: float | None = None,
    nsr_floor: float = 0.0,
    sample_noise_var: float = 0.0,
    detector_halo_fraction: float = 0.0,
    detector_halo_radius_m: float = 0.0,
    iterations: int = REFINE_ITER,
    fft: FFT | None = None,
) -> DiffuserEstimate:
    """Diffuser transmission t_r = exp(-(kappa + i) theta_r) of one material (kappa = beta/delta)
    that reproduces the reference: |P2{t}|^2 convolved with the IPSF, Eqs. (IPSF, IOTF), fitted
    in least squares over the detector frame by L-BFGS from :func:`ctf_phase_delay`.

    Why not the paper's zero phase: that estimate reproduces the reference at exactly L2 but
    its speckle does not evolve with distance to first order (zero detector phase means dI/dz
    = 0 by the TIE). A sample's lens-like curvature changes the effective distance, and PWF
    then puts the missing evolution into extra curvature (+25 % bead phase contrast on the
    test scene). A diffuser is one material (abrasive grains; kappa from xraydb), which makes
    its phase retrievable from one image; at kappa = 0 the slow part of theta is not
    (docs/methods.md). Returns the estimate with its fit residuals.
    """
    xp = get_array_module(reference)
    fft = fft or FFT.for_module(xp)
    ref, shape = _padded_reference(reference, pad, shape, xp)
    ny, nx = xp.asarray(reference).shape
    frame = (slice(pad, pad + ny), slice(pad, pad + nx))
    ref = ref / float(xp.mean(ref[frame]))
    theta = ctf_phase_delay(
        ref,
        beta_over_delta=beta_over_delta,
        pixel_size_m=pixel_size_m,
        wavelength=wavelength,
        diffuser_detector_distance_m=diffuser_detector_distance_m,
        coherence_length_x_m=coherence_length_x_m,
        coherence_length_y_m=coherence_length_y_m,
        shape=shape,
        nsr=nsr,
        nsr_floor=nsr_floor,
        sample_noise_var=sample_noise_var,
        detector_halo_fraction=detector_halo_fraction,
        detector_halo_radius_m=detector_halo_radius_m,
        fft=fft,
    )
    kernel = optics.angular_spectrum_kernel(
        shape, pixel_size_m, wavelength, diffuser_detector_distance_m, xp, np.complex128
    )
    kernel_conj = xp.conj(kernel)
    h = optics.intensity_transfer_function(
        shape,
        pixel_size_m,
        coherence_length_x_m,
        coherence_length_y_m,
        detector_halo_fraction,
        detector_halo_radius_m,
        xp,
        np.float64,
    )
    mask = None
    if (ny, nx) != tuple(shape):
        mask = xp.zeros(shape)
        mask[frame] = 1.0
    kappa = float(beta_over_delta)

    def blur(a):
        if h is None:
            return a
        spec = fft.rfft2(a)
        spec *= h
        return fft.irfft2(spec, s=shape, overwrite=True)

    def propagate(a, k):
        spec = fft.fft2(a)
        spec *= k
        return fft.ifft2(spec, overwrite=True)

    def value_and_gradient(th):
        # f = sum over the frame of r^2 / (ny nx), r = |P2 t|^2 * IPSF - reference
        t = kernels.single_material_transmission(th, kappa)
        v = propagate(t, kernel)
        r, sum_sq = kernels.residual_and_loss(blur(kernels.intensity(v)), ref, mask)
        # d f / d theta by the chain rule through the IPSF, |v|^2, P2 and exp (Wirtinger):
        # 2 Re(c conj(back) t), back = P2^H{(IPSF * 2 r / (ny nx)) v}
        back = propagate(blur(r) * v, kernel_conj)
        return sum_sq / (ny * nx), kernels.single_material_gradient(back, t, kappa, 4.0 / (ny * nx))

    f0, _ = value_and_gradient(theta)
    theta, f = _lbfgs(value_and_gradient, theta, iterations)
    return DiffuserEstimate(
        transmission=kernels.single_material_transmission(theta, kappa),
        phase_delay=theta,
        beta_over_delta=float(beta_over_delta),
        residual_rmse=float(np.sqrt(f)),
        initial_residual_rmse=float(np.sqrt(f0)),
    )


# --- diffuser drift between the reference and a sample image (not in the paper) -------------
