"""Calibration from the reference speckle (Methods: IOTF; Diffuser transmission function).

* :func:`coherence_lengths` - x_coh, y_coh by the Siegert relation, Eq. (sigert): 1-D
  normalised autocorrelations of the reference along each axis, averaged over the other,
  fitted with the Gaussian 1 + exp(-pi dx^2 / x_coh^2).
* :func:`diffuser_transmission` - t_r: Wiener deconvolution of the reference with the IOTF,
  negatives clipped, square root, zero phase, back-propagation over L2 (the paper's
  estimate, ``diffuser_model="zero-phase"``); or, by default, a single-material phase screen
  t_r = exp(-(kappa + i) theta_r) fitted to the reference (``"single-material"``, see
  :func:`single_material_diffuser`).
* :func:`speckle_drift_px`, :func:`shift_transmission`, :func:`unseen_by_reference` - not in
  the paper: the diffuser's drift between the reference and a sample frame, measured and
  followed (README, "Diffuser drift").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from . import optics
from .backend import FFT, get_array_module, to_numpy


def _axis_power_spectra(img: np.ndarray):
    """1-D power spectra along x and along y (Hann-windowed, averaged over the other axis),
    their frequencies (cycles/pixel), and the white-noise floor from the 2-D spectrum's
    corners beyond the Nyquist circle, where the IOTF has removed all speckle."""
    ny, nx = img.shape
    win = np.outer(np.hanning(ny), np.hanning(nx))
    spec = np.abs(np.fft.fft2((img - img.mean()) * win)) ** 2
    v, u = np.fft.fftfreq(ny)[:, None], np.fft.fftfreq(nx)[None, :]
    corners = (u * u + v * v) > 0.3
    # a white-noise periodogram is exponentially distributed: its median is ln 2 of the
    # mean floor that the 1-D spectra carry (the median alone left 31 % of it on the flank)
    noise = float(np.median(spec[np.broadcast_to(corners, spec.shape)])) / np.log(2.0)
    px = spec.mean(axis=0)[: nx // 2]
    py = spec.mean(axis=1)[: ny // 2]
    return (np.fft.fftfreq(nx)[: nx // 2], px), (np.fft.fftfreq(ny)[: ny // 2], py), noise


def _fit_gaussian_flank(freq: np.ndarray, power: np.ndarray, noise: float) -> float:
    """Width c of exp(-pi c^2 q^2) fitted to the decaying flank of ``power - noise``.

    The flank runs from where the spectrum has fallen to 70 % of its peak down to 0.3 %
    of it (or the noise): there the IOTF^2 dominates the shape.
    """
    sig = power - noise
    smooth = np.convolve(sig, np.ones(3) / 3, mode="same")
    ipk = int(np.argmax(smooth[1:])) + 1
    peak = smooth[ipk]
    sel = np.zeros(freq.shape, bool)
    for i in range(ipk, freq.size):
        if smooth[i] < max(3e-3 * peak, 3 * noise / np.sqrt(max(power.size, 1))):
            break
        # a point the noise pushed to or below zero has no logarithm to fit
        if smooth[i] <= 0.7 * peak and sig[i] > 0:
            sel[i] = True
    if sel.sum() < 3:
        raise ValueError("too few frequencies on the spectrum's flank")
    q2 = freq[sel] ** 2
    slope, _ = np.polyfit(q2, np.log(sig[sel]), 1, w=np.sqrt(sig[sel] / peak))
    if not slope < 0:
        raise ValueError("the spectrum does not decay")
    return float(np.sqrt(-slope / np.pi))


def coherence_lengths(reference, pixel_size_m: float) -> tuple[float, float]:
    """Coherence lengths (x_coh, y_coh) in metres from the reference speckle, Eq. (sigert).

    The paper fits g2(dx) = 1 + exp(-pi dx^2 / x_coh^2) to the 1-D normalised
    autocorrelation along each axis, averaged over the other. The same Gaussian model is
    fitted here in Fourier space, where it reads IOTF_x(u)^2 = exp(-pi u^2 x_coh^2) times the
    spectrum of the coherent speckle: on the decaying flank the IOTF dominates, while the
    coherent speckle of a phase diffuser is band-pass (little power at low frequencies), which
    gives its autocorrelation negative lobes and made the real-space fit 15 % short on our
    sandpaper scenes (README, "Accuracy"). Photon noise is white and is subtracted as the
    floor beyond the Nyquist circle.
    """
    img = to_numpy(reference).astype(np.float64)
    if img.ndim != 2 or min(img.shape) < 32:
        raise ValueError(f"reference must be a 2-D image of at least 32 x 32 pixels, got shape {img.shape}")
    img = img - ndimage.gaussian_filter(img, 32.0, mode="reflect")
    (fx, px), (fy, py), noise = _axis_power_spectra(img)
    out = []
    for name, f, p in (("x", fx, px), ("y", fy, py)):
        try:
            c = _fit_gaussian_flank(f, p, noise)
        except ValueError as exc:
            raise ValueError(
                f"coherence-length fit along {name} failed ({exc}): the reference shows no resolvable "
                "speckle blur; give coherence_length_x_m and coherence_length_y_m explicitly"
            ) from None
        out.append(c * pixel_size_m)
    return out[0], out[1]


def noise_to_signal(reference_spectrum_power, pixel_radius2, iotf_half) -> float:
    """Scalar noise-to-signal ratio of the Wiener filter.

    White noise fills the spectrum beyond the Nyquist circle (u^2 + v^2 > 1/4 cycles/pixel^2,
    the corners), where the IOTF has removed any speckle; the coherent signal power is what
    the low-frequency band holds above that floor, corrected for the IOTF there.
    """
    xp = get_array_module(reference_spectrum_power)
    corners = pixel_radius2 > 0.25
    noise = float(xp.mean(reference_spectrum_power[corners])) if bool(xp.any(corners)) else 0.0
    if iotf_half is None:
        return 0.0
    band = (iotf_half > 0.5) & (pixel_radius2 > 0)
    if not bool(xp.any(band)):
        return 0.0
    signal = float(xp.mean((reference_spectrum_power[band] - noise) / iotf_half[band] ** 2))
    if signal <= 0:
        return 1.0
    return noise / signal


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
    phase_screen_iter: int = 0,
    diffuser_model: str = "zero-phase",
    beta_over_delta: float | None = None,
    refine_iter: int = 25,
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
    d is back-propagating over L2).
    """
    if diffuser_model not in DIFFUSER_MODELS:
        raise ValueError(f"unknown diffuser_model {diffuser_model!r}: choose one of {', '.join(DIFFUSER_MODELS)}")
    if not (math.isfinite(upstream_m) and upstream_m >= 0):
        raise ValueError(f"diffuser_upstream_m must be >= 0, got {upstream_m}")
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
            iterations=refine_iter,
            fft=fft,
        ).transmission
        # the diffuser's field at the sample plane (0 m: the same array, nothing computed)
        return optics.angular_spectrum_propagate(t, pixel_size_m, wavelength, upstream_m, fft)
    xp = get_array_module(reference)
    fft = fft or FFT.for_module(xp)
    ref, shape = _padded_reference(reference, pad, shape, xp)
    spec = fft.rfft2(ref)
    h = optics.iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, xp, np.float64)
    if h is not None:
        v, u = optics.frequency_grid(shape, 1.0, half=True)
        r2 = xp.asarray(u * u + v * v)
        if nsr is None:
            nsr = noise_to_signal(spec.real**2 + spec.imag**2, r2, h)
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
    h = optics.iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, np, np.float64)
    if h is not None:
        transfer = transfer * h
    transfer = xp.asarray(transfer)
    if nsr is None:
        vp, up = optics.frequency_grid(shape, 1.0, half=True)
        hh = xp.asarray(h) if h is not None else None
        nsr = noise_to_signal(spec.real**2 + spec.imag**2, xp.asarray(up * up + vp * vp), hh)
    theta_hat = -transfer * spec / (transfer * transfer + max(nsr, 1e-6))
    theta_hat[0, 0] = 0
    return fft.irfft2(theta_hat, s=shape)


def _lbfgs(value_and_gradient, x, iterations: int, memory: int = 10, first_step: float = 0.1):
    """Limited-memory BFGS with Armijo backtracking (Nocedal & Wright, Alg. 7.4/7.5), on any
    array module; ``first_step`` bounds the first move (max |dx|)."""
    xp = get_array_module(x)
    f, g = value_and_gradient(x)
    pairs: list[tuple[Any, Any, float]] = []
    for _ in range(iterations):
        q = g.copy()
        coeffs = []
        for s, y, rho in reversed(pairs):
            a = rho * float(xp.vdot(s, q))
            q -= a * y
            coeffs.append(a)
        if pairs:
            s, y, _ = pairs[-1]
            q *= float(xp.vdot(s, y)) / float(xp.vdot(y, y))
        else:
            q *= first_step / max(float(xp.max(xp.abs(g))), 1e-300)
        for (s, y, rho), a in zip(pairs, reversed(coeffs)):
            q += s * (a - rho * float(xp.vdot(y, q)))
        slope = -float(xp.vdot(g, q))
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
    iterations: int = 25,
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
    (README, Numerical choices). Returns the estimate with its fit residuals.
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
        fft=fft,
    )
    kernel = optics.angular_spectrum_kernel(
        shape, pixel_size_m, wavelength, diffuser_detector_distance_m, xp, np.complex128
    )
    h = optics.iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, xp, np.float64)
    weight = xp.zeros(shape)
    weight[frame] = 1.0 / (ny * nx)
    c = complex(-beta_over_delta, -1.0)

    def blur(a):
        return a if h is None else fft.irfft2(fft.rfft2(a) * h, s=shape)

    def value_and_gradient(th):
        t = xp.exp(c * th)
        v = fft.ifft2(fft.fft2(t) * kernel)
        r = blur(v.real**2 + v.imag**2) - ref
        f = float(xp.sum(weight * r * r))
        # d f / d theta by the chain rule through the IPSF, |v|^2, P2 and exp (Wirtinger)
        back = fft.ifft2(fft.fft2(blur(2 * weight * r) * v) * xp.conj(kernel))
        return f, 2 * xp.real(xp.conj(back) * c * t)

    f0, _ = value_and_gradient(theta)
    theta, f = _lbfgs(value_and_gradient, theta, iterations)
    return DiffuserEstimate(
        transmission=xp.exp(c * theta),
        phase_delay=theta,
        beta_over_delta=float(beta_over_delta),
        residual_rmse=float(np.sqrt(f)),
        initial_residual_rmse=float(np.sqrt(f0)),
    )


# --- diffuser drift between the reference and a sample image (not in the paper) -------------

#: Tukey taper of the frame before correlating: the frame edges do not move with the
#: diffuser, and an untapered edge pulls the peak towards zero shift (0.45 px for 1.3 px).
DRIFT_TAPER = 0.2


def _upsampled_dft_kernels(shape, centre, upsample_factor: int, half_width: int, xp):
    """Row and column kernels of the inverse DFT at offsets k / ``upsample_factor`` px,
    |k| <= ``half_width``, around ``centre`` (Guizar-Sicairos et al., Opt. Lett. 33, 156
    (2008)): ``rows @ spectrum @ cols`` instead of an FFT ``upsample_factor`` times larger,
    and ``rows @ a`` times ``b @ cols`` for a separable spectrum a b^T."""
    ny, nx = shape
    offsets = xp.arange(-half_width, half_width + 1) / upsample_factor
    rows = xp.exp(2j * np.pi * (centre[0] + offsets)[:, None] * xp.fft.fftfreq(ny)[None, :])
    cols = xp.exp(2j * np.pi * xp.fft.fftfreq(nx)[:, None] * (centre[1] + offsets)[None, :])
    return rows, cols, to_numpy(offsets)


def speckle_drift_px(sample, reference, *, fft: FFT | None = None) -> tuple[float, float]:
    """Global shift (dy, dx) in pixels, to 0.01 px, of the sample image's speckle against the
    reference: the sample was taken through the diffuser moved to t_r(r - d).

    Not in the paper, whose diffuser holds still: on a beamline it drifts between the
    reference and the sample frames (thermal, stage settling), and PWF fits t_r P1{x_r} to the
    speckle grain by grain: half a pixel of drift multiplied the phase error by 3.5 and
    1.5 pixels ruined it (README, "Diffuser drift"). Cross-correlation of the mean-normalised,
    Tukey-tapered frames divided by the tapers' own correlation (the overlap of the two
    windows falls with the shift and would pull the peak towards zero), refined by
    upsampled DFTs around the integer peak (1/10, then 1/100 px). Not whitened: phase
    correlation weighs the noise-only frequencies beyond the speckle band like the rest and
    scattered by 0.07 px between two references. The sample's refraction moves the speckle
    only locally.
    """
    from scipy.signal.windows import tukey

    xp = get_array_module(sample, reference)
    fft = fft or FFT.for_module(xp)
    ny, nx = sample.shape
    wy, wx = tukey(ny, DRIFT_TAPER), tukey(nx, DRIFT_TAPER)
    window = xp.asarray(np.outer(wy, wx), dtype=xp.float32)

    def spectrum(a):
        a = xp.asarray(a, dtype=xp.float32)
        return fft.fft2((a / xp.mean(a) - 1.0) * window)

    cross = spectrum(sample) * xp.conj(spectrum(reference))
    # the taper is separable, so its power spectrum and autocorrelation are outer products
    # of 1-D ones: no frame-sized FFT for them
    power_y, power_x = np.abs(np.fft.fft(wy)) ** 2, np.abs(np.fft.fft(wx)) ** 2
    window_correlation = np.outer(np.fft.ifft(power_y).real, np.fft.ifft(power_x).real)
    floor = 1e-3 * float(np.sum(wy**2) * np.sum(wx**2))
    correlation = fft.ifft2(cross).real / xp.asarray(np.maximum(window_correlation, floor), dtype=xp.float32)
    peak = np.unravel_index(int(xp.argmax(correlation)), correlation.shape)
    centre = np.array([q - n if q > n // 2 else q for q, n in zip(peak, (ny, nx))], float)
    power_y, power_x = xp.asarray(power_y), xp.asarray(power_x)
    cross = cross.astype(xp.complex128)  # the kernels' precision, cast once for both passes
    for factor in (10, 100):
        rows, cols, offsets = _upsampled_dft_kernels((ny, nx), centre, factor, 8, xp)
        # the taper's overlap is separable: two 1-D products, not a frame-sized one
        overlap = xp.outer(rows @ power_y, power_x @ cols).real
        fine = (rows @ cross @ cols).real / overlap
        iy, ix = np.unravel_index(int(xp.argmax(fine)), fine.shape)
        centre = np.array([centre[0] + offsets[iy], centre[1] + offsets[ix]])
    return float(centre[0]), float(centre[1])


def unseen_by_reference(frame_shape: tuple[int, int], shift_px: tuple[float, float], margin_px: int) -> np.ndarray:
    """Frame pixels (True) whose diffuser, moved by ``shift_px`` = (dy, dx), lay outside the
    reference's frame: strips ceil(|d|) + ``margin_px`` wide on the sides it came in from."""
    ny, nx = frame_shape
    unseen = np.zeros((ny, nx), bool)
    for axis, d in enumerate(shift_px):
        if d == 0:
            continue
        width = min(int(np.ceil(abs(d))) + margin_px, frame_shape[axis])
        strip = slice(0, width) if d > 0 else slice(frame_shape[axis] - width, frame_shape[axis])
        unseen[(strip, slice(None)) if axis == 0 else (slice(None), strip)] = True
    return unseen


def shift_transmission(t, shift_px: tuple[float, float], fft: FFT | None = None):
    """t_r(r - d): the diffuser transmission moved by ``shift_px`` = (dy, dx) pixels, by the
    Fourier shift theorem on its computational grid (the frame wraps into the padding only).
    A zero shift returns ``t`` itself."""
    if shift_px[0] == 0 and shift_px[1] == 0:
        return t
    xp = get_array_module(t)
    fft = fft or FFT.for_module(xp)
    ny, nx = t.shape
    ky = xp.fft.fftfreq(ny)[:, None]
    kx = xp.fft.fftfreq(nx)[None, :]
    ramp = xp.exp(-2j * np.pi * (ky * shift_px[0] + kx * shift_px[1])).astype(t.dtype)
    return fft.ifft2(fft.fft2(t) * ramp).astype(t.dtype, copy=False)
