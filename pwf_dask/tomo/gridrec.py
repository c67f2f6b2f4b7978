"""Gridding filtered back projection: the Fourier slice theorem with a non-uniform FFT.

The direct backprojector (:func:`pwf_dask.tomo.tomography.filtered_back_projection`) visits
every angle for every output pixel: O(N^2 x angles) per slice. Here the same filtered
projections are summed in Fourier space instead, as tomopy's gridrec and tomocupy do. Each
filtered projection q_a (Ram-Lak, angle weight w_a: the same filter and weights) is
transformed along the detector, and its samples Q_a(nu) lie on the line of angle theta_a
through the origin of the slice's 2-D spectrum (the Fourier slice theorem). One type-1
non-uniform FFT (finufft on the host; on the GPU the package's own, :mod:`pwf_dask.tomo.nufft`)
then sums them onto the slice's pixels:

    f(u, v) = sum_a w_a sum_nu Q_a(nu) / M exp(2 pi i nu (u cos theta_a + v sin theta_a - x0) / p),

which is the backprojection with q_a interpolated band-limitedly (by its own Fourier
series) instead of linearly. The cost is O(N^2 log N + angles x N) per slice. Rows of a block
share the points, so each block is one plan with one transform per row.
"""

from __future__ import annotations

import numpy as np

from pwf_dask.backend import FFT
from pwf_dask.tomo.tomography import angle_weights, pad_len, ramp_filtered, sinogram_block

#: finufft's requested relative precision, and its fine grid's oversampling: 1.25 instead of
#: the default 2 spreads onto a 2.6x smaller grid, 4.3x faster at 2560^2 for a change of
#: 7.5e-4 of the slice's maximum (measured; the two FBPs differ by 1e-2 anyway)
NUFFT_EPS = 1e-4
NUFFT_UPSAMPLING = 1.25
#: the device's fine grid: twice the modes (cufinufft's default too), a 5-cell kernel at 1e-4
#: where 1.25 takes 7 (the spreading's atomic additions, not the FFT, are a GPU's larger cost)
DEVICE_NUFFT_UPSAMPLING = 2.0


def _points_and_phases(angles_deg, m: int, center_px: float, n_out: int):
    """The spectrum's sample points (x, y in radians per pixel) for every angle and
    non-negative frequency, and each sample's phase factor: the detector origin (column
    ``center_px`` is the axis) and, for an even output grid, the half pixel between finufft's
    mode 0 (pixel n/2) and the grid's centre ((n - 1) / 2)."""
    half = n_out // 2 - (n_out - 1) / 2
    nu = np.fft.rfftfreq(m)  # cycles per detector pixel, 0 .. 1/2
    theta = np.deg2rad(np.asarray(angles_deg, np.float64))[:, None]
    cos, sin = np.cos(theta), np.sin(theta)
    x = 2 * np.pi * nu * sin  # multiplies the row index (v)
    y = 2 * np.pi * nu * cos  # multiplies the column index (u)
    phase = np.exp(2j * np.pi * nu * center_px + 2j * np.pi * nu * half * (cos + sin))
    # Hermitian symmetry: the negative frequencies are the conjugates, counted by doubling
    # every interior frequency (not 0, nor Nyquist of an even m)
    twice = np.full(nu.size, 2.0)
    twice[0] = 1.0
    if m % 2 == 0:
        twice[-1] = 1.0
    return x.ravel(), y.ravel(), phase * twice / m


def gridrec_back_projection(
    sinogram, angles_deg, pixel_size_m: float, center_offset_m: float = 0.0, n_out=None, fft=None
):
    """FBP of sinograms (angle, row, x) -> slices (row, v, u), values per metre, by gridding.

    The contract of :func:`pwf_dask.tomo.tomography.filtered_back_projection` (the reference):
    ``center_offset_m`` is the rotation axis on the detector's x coordinate (0: the frame
    centre); u, v are centred on the axis, ``n_out`` pixels (default nx).
    """
    xp, fft, sino = sinogram_block(sinogram, fft)
    na, nr, nx = sino.shape
    n_out = n_out or nx
    w = xp.asarray(angle_weights(angles_deg), dtype=xp.float32)
    # twice the detector: a ray beyond the detector reads the zeros of the padding, as in
    # the backprojector, not the other edge of the period
    m = 2 * nx
    spectrum = xp.empty((na, nr, m // 2 + 1), dtype=xp.complex64)
    # filtered in batches of angles, straight into the spectrum (as the backprojector does)
    batch = max(1, 2**21 // max(1, nr * pad_len(2 * nx)))
    for start in range(0, na, batch):
        part = slice(start, min(na, start + batch))
        spectrum[part] = _rfft(xp, ramp_filtered(sino[part], fft, xp) * w[part, None, None], m, fft)
    del sino
    center_px = (nx - 1) / 2 + center_offset_m / pixel_size_m
    x, y, phase = _points_and_phases(angles_deg, m, center_px, n_out)
    spectrum *= xp.asarray(phase.reshape(na, 1, -1), dtype=xp.complex64)
    # (angle, row, freq) -> (row, angle x freq): one transform per row, all on the same points
    c = xp.ascontiguousarray(spectrum.transpose(1, 0, 2)).reshape(nr, -1)
    del spectrum
    out = _nufft2d1(xp, x, y, c, (n_out, n_out), fft.workers)
    out /= pixel_size_m
    return out


def _rfft(xp, q, m: int, fft: FFT):
    if xp is np:
        import scipy.fft

        return scipy.fft.rfft(q, n=m, axis=-1, workers=fft.workers)  # complex64, as q is float32
    return xp.fft.rfft(q, n=m, axis=-1)


def _nufft2d1(xp, x, y, c, shape, threads: int | None = None):
    """The real part (float32) of the type-1 2-D NUFFT of ``c`` (n_trans, points) at points
    (x, y), isign +1, single precision, on ``threads`` CPU threads (the task's FFT budget;
    None: every core)."""
    if xp is np:
        import finufft

        f = finufft.nufft2d1(
            x.astype(np.float32),
            y.astype(np.float32),
            c,
            shape,
            eps=NUFFT_EPS,
            isign=1,
            nthreads=threads or _threads(),
            upsampfac=NUFFT_UPSAMPLING,
            showwarn=0,  # its "more threads than physical cores" note: the budget is the caller's
        )
        return f.real.astype(np.float32)
    from pwf_dask.tomo import nufft

    return nufft.nufft2d1(x, y, c, shape, xp, eps=NUFFT_EPS, upsampling=DEVICE_NUFFT_UPSAMPLING, real=True)


def _threads() -> int:
    from pwf_dask.backend import default_fft_workers

    return max(1, int(default_fft_workers() or 1))


def available(xp=np) -> bool:
    """Whether the gridding backend of ``xp`` is there: finufft on the host; on CuPy always
    (:mod:`pwf_dask.tomo.nufft`, the package's own spreading kernel)."""
    if xp is not np:
        return True
    try:
        import finufft  # noqa: F401
    except ImportError:
        return False
    return True
