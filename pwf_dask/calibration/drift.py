"""Diffuser drift between the reference and a sample frame, measured and followed (not in the paper).

:func:`speckle_drift_px`, :func:`shift_transmission`, :func:`unseen_by_reference`
(docs/validation.md, "Diffuser drift").
"""

from __future__ import annotations

import math

import numpy as np

from pwf_dask.backend import FFT, get_array_module, to_numpy

#: Tukey taper of the frame before correlating: the frame edges do not move with the
#: diffuser, and an untapered edge pulls the peak towards zero shift (0.45 px for 1.3 px).
DRIFT_TAPER = 0.2

#: How far above the correlation surface's noise the peak must stand, beyond the largest
#: value pure noise reaches on that many lags (:func:`drift_peak_significance`)
DRIFT_SIGNIFICANCE_MARGIN = 2.0


def drift_peak_significance(raw_correlation, window_correlation, peak) -> tuple[float, float]:
    """(significance, threshold) of the cross-correlation's peak at ``peak`` (both surfaces
    on the correlation's device).

    The raw correlation's noise at lag d grows as the root of the tapers' overlap there, so
    raw / sqrt(overlap) is white where the frames do not correlate; the significance is the
    peak's value of it above the surface's median, in robust (MAD) sigmas. N independent
    normal lags reach about sqrt(2 ln N) by chance (4.4 on a 128^2 frame, 5.6 on the
    camera's 2160 x 2560), so the peak must pass that plus :data:`DRIFT_SIGNIFICANCE_MARGIN`.
    Measured: speckle frames 8.9-132 (40 random geometries, 64-260 px, 1e2-1e6 ph/px; the
    paper's scene 42 at any dose), Poisson noise of 100 photons 3.9-4.0.
    """
    xp = get_array_module(raw_correlation)
    score = raw_correlation / xp.sqrt(window_correlation)
    sample = score[::2, ::2]  # a quarter of the lags gives the spread as well, 4x sooner
    median = float(xp.median(sample))
    sigma = 1.4826 * float(xp.median(xp.abs(sample - median))) or 1.0
    threshold = math.sqrt(2.0 * math.log(score.size)) + DRIFT_SIGNIFICANCE_MARGIN
    return (float(score[peak]) - median) / sigma, threshold


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
    1.5 pixels ruined it (docs/validation.md, "Diffuser drift"). Cross-correlation of the mean-normalised,
    Tukey-tapered frames divided by the tapers' own correlation (the overlap of the two
    windows falls with the shift and would pull the peak towards zero), refined by
    upsampled DFTs around the integer peak (1/10, then 1/100 px). Not whitened: phase
    correlation weighs the noise-only frequencies beyond the speckle band like the rest and
    scattered by 0.07 px between two references. The sample's refraction moves the speckle
    only locally.

    Where no peak stands out of the noise (:func:`drift_peak_significance`: frames of photon
    noise, speckle washed out), no drift is measurable and (0.0, 0.0) is returned: the
    largest of the noise would otherwise read as a drift of tens of pixels.
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
    window_correlation = xp.asarray(np.maximum(window_correlation, floor), dtype=xp.float32)
    raw = fft.ifft2(cross).real
    correlation = raw / window_correlation
    peak = np.unravel_index(int(xp.argmax(correlation)), correlation.shape)
    significance, threshold = drift_peak_significance(raw, window_correlation, peak)
    if not significance >= threshold:
        return 0.0, 0.0
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
