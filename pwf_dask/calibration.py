"""Calibration from the reference speckle (Methods: IOTF; Diffuser transmission function).

* :func:`coherence_lengths` - x_coh, y_coh by the Siegert relation, Eq. (sigert): 1-D
  normalised autocorrelations of the reference along each axis, averaged over the other,
  fitted with the Gaussian 1 + exp(-pi dx^2 / x_coh^2).
* :func:`diffuser_transmission` - t_r: Wiener deconvolution of the reference with the IOTF,
  negatives clipped, square root, zero phase, back-propagation over L2.
"""

from __future__ import annotations

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
    noise = float(np.median(spec[np.broadcast_to(corners, spec.shape)]))
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
        if smooth[i] <= 0.7 * peak:
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
    fft: FFT | None = None,
):
    """Diffuser transmission t_r (Methods, Diffuser transmission function).

    The reference is Wiener-deconvolved with the IOTF (estimating the coherent speckle
    intensity), clipped at 0, square-rooted, given zero phase and back-propagated by -L2. With
    ``pad`` the frame is first extended by reflection to ``shape`` (the computational grid), so
    that light entering the frame from outside is modelled by plausible speckle, not by
    periodic wrap-around.
    """
    xp = get_array_module(reference)
    fft = fft or FFT.for_module(xp)
    ref = xp.asarray(reference, dtype=xp.float64)
    ny, nx = ref.shape
    shape = shape or (ny + 2 * pad, nx + 2 * pad)
    if shape != (ny, nx):
        after = (shape[0] - ny - pad, shape[1] - nx - pad)
        ref = xp.pad(ref, ((pad, after[0]), (pad, after[1])), mode="reflect")
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
