"""The type-1 2-D non-uniform FFT of gridding FBP on CuPy, by spreading onto an oversampled grid.

    f[k1, k2] = sum_j c_j exp(+i (k1 x_j + k2 y_j)),   -N/2 <= k < N/2,   x_j, y_j in [-pi, pi],

as finufft's ``nufft2d1`` (isign +1, modes in increasing order), computed the way finufft does
(Barnett, Magland & af Klinteberg, SIAM J. Sci. Comput. 41, C479 (2019)): each strength c_j is
spread onto a grid ``upsampling`` times finer than the modes by the "exponential of semicircle"
kernel phi(z) = exp(beta (sqrt(1 - (2 z / w)^2) - 1)) of w cells, the grid is transformed by one
FFT, and the N x N central modes are divided by the kernel's Fourier transform. The error is set
by w and beta (:func:`kernel_parameters`, finufft's rule for a requested ``eps``).

Why our own on the GPU: cufinufft's wheels link CUDA 12 and would not load on the CUDA-13
device lent to this project (session 61), so the device fell back to the backprojector (0.27 s a
2560^2 slice of 801 angles: 17-20 min of a scan position's tomography). Spreading is one CUDA
kernel (:data:`SPREAD_KERNEL`, a thread per sample and row, w^2 atomic additions), the rest is
CuPy's FFT and two element-wise passes. The host keeps finufft (:mod:`pwf_dask.tomo.gridrec`).
"""

from __future__ import annotations

import math

import numpy as np

#: the widest kernel :data:`SPREAD_KERNEL` holds (cells; finufft's largest too)
MAX_KERNEL_WIDTH = 16

#: fine-grid elements (complex64) spread at once: rows of a block go in batches of at most this
#: many, 512 MB of grid and as much for its transform
MAX_GRID_ELEMENTS = 1 << 26


def kernel_parameters(eps: float, upsampling: float) -> tuple[int, float]:
    """(w, beta) of the ES kernel for relative precision ``eps`` on a grid ``upsampling`` times
    finer than the modes: w = ceil(ln(1/eps) / (pi sqrt(1 - 1/sigma))), beta = 0.97 pi w
    (1 - 1/(2 sigma)) (finufft's rule; w = 5, beta = 11.4 at eps 1e-4 and sigma 2)."""
    if not (0 < eps < 1) or upsampling <= 1:
        raise ValueError(f"NUFFT: eps in (0, 1) and upsampling > 1, got {eps!r}, {upsampling!r}")
    width = math.ceil(math.log(1.0 / eps) / (math.pi * math.sqrt(1.0 - 1.0 / upsampling)))
    width = min(max(width, 2), MAX_KERNEL_WIDTH)
    return width, 0.97 * math.pi * width * (1.0 - 0.5 / upsampling)


def es_kernel(z, width: int, beta: float):
    """phi(z) of the ES kernel, z in fine-grid cells from the sample (0 outside |z| < w/2)."""
    t = (2.0 * np.asarray(z, np.float64) / width) ** 2
    return np.where(t < 1.0, np.exp(beta * (np.sqrt(np.clip(1.0 - t, 0.0, None)) - 1.0)), 0.0)


def kernel_transform(n_modes: int, n_fine: int, width: int, beta: float) -> np.ndarray:
    """phi_hat(k) = integral phi(z) cos(2 pi k z / n_fine) dz for the modes -N/2 .. N/2 - 1, in
    their order, by Gauss-Legendre quadrature over the kernel's support (float64)."""
    nodes, weights = np.polynomial.legendre.leggauss(max(64, 4 * width))
    z = 0.5 * width * nodes  # [-w/2, w/2]
    k = np.arange(n_modes) - n_modes // 2
    return (0.5 * width * weights * es_kernel(z, width, beta)) @ np.cos(2.0 * np.pi * np.outer(z, k) / n_fine)


def fine_grid_length(n_modes: int, upsampling: float) -> int:
    """The spreading grid's length: the next even, 2-3-5-7-smooth length at upsampling x n."""
    from pwf_dask.pwf.model import fast_len

    return max(fast_len(math.ceil(upsampling * n_modes)), 2 * MAX_KERNEL_WIDTH)


#: Spreading as the body of one CUDA element-wise kernel (``i`` the (row, sample) element): the
#: sample sits at cell ``cell`` + ``frac`` of each fine-grid axis (split on the host in float64,
#: so float32 keeps the position to ~1e-7 cells on any grid), its w x w kernel weights are
#: separable, and each lands by atomic addition on the grid's float32 pairs (periodic indices).
#: Plain C as well: the CPU emulator compiles it in a loop over ``i``.
SPREAD_KERNEL = """
const long long j = i % npts;
const long long r = i / npts;
const float s = 2.0f / (float)width;
float w0[16], w1[16];
const int first0 = (int)ceilf(frac0[j] - 0.5f * (float)width);
const int first1 = (int)ceilf(frac1[j] - 0.5f * (float)width);
for (int k = 0; k < width; ++k) {
    const float z0 = ((float)(first0 + k) - frac0[j]) * s;
    const float z1 = ((float)(first1 + k) - frac1[j]) * s;
    w0[k] = z0 * z0 < 1.0f ? expf(beta * (sqrtf(1.0f - z0 * z0) - 1.0f)) : 0.0f;
    w1[k] = z1 * z1 < 1.0f ? expf(beta * (sqrtf(1.0f - z1 * z1) - 1.0f)) : 0.0f;
}
const float re = c.real(), im = c.imag();
for (int a = 0; a < width; ++a) {
    int g0 = (cell0[j] + first0 + a) % n0;
    if (g0 < 0) g0 += n0;
    const long long base = (r * n0 + g0) * (long long)n1;
    for (int b = 0; b < width; ++b) {
        int g1 = (cell1[j] + first1 + b) % n1;
        if (g1 < 0) g1 += n1;
        const float wt = w0[a] * w1[b];
        atomicAdd(&grid[2 * (base + g1)], wt * re);
        atomicAdd(&grid[2 * (base + g1) + 1], wt * im);
    }
}
"""

#: CuPy module -> its compiled spreading kernel
_SPREAD_KERNELS: dict = {}


def _spread_kernel(xp):
    if xp not in _SPREAD_KERNELS:
        _SPREAD_KERNELS[xp] = xp.ElementwiseKernel(
            "complex64 c, raw int32 cell0, raw float32 frac0, raw int32 cell1, raw float32 frac1, "
            "int64 npts, int32 n0, int32 n1, int32 width, float32 beta",
            "raw float32 grid",
            SPREAD_KERNEL,
            name="pwf_nufft_spread",
        )
    return _SPREAD_KERNELS[xp]


def _cells(points, n_fine: int, xp):
    """(integer cell, fraction) of each point's fine-grid coordinate x n_fine / (2 pi), on xp."""
    g = np.asarray(points, np.float64) * (n_fine / (2.0 * np.pi))
    cell = np.floor(g)
    return xp.asarray(cell.astype(np.int32)), xp.asarray((g - cell).astype(np.float32))


def _modes(n_modes: int, n_fine: int) -> np.ndarray:
    """Indices of the modes -N/2 .. N/2 - 1 in an FFT of length n_fine."""
    return (np.arange(n_modes) - n_modes // 2) % n_fine


def nufft2d1(x, y, c, shape: tuple[int, int], xp, eps: float = 1e-4, upsampling: float = 2.0, real: bool = False):
    """Type-1 NUFFT of strengths ``c`` (n_trans, points; complex64, on ``xp``'s device) at
    points (``x`` along axis 0, ``y`` along axis 1; radians, host arrays): (n_trans, *shape)
    complex64, finufft's ``nufft2d1(x, y, c, shape, isign=1)`` to about ``eps`` of its l2 norm;
    ``real``: its real part alone, float32 (what gridding FBP keeps: half the device memory)."""
    width, beta = kernel_parameters(eps, upsampling)
    c = xp.ascontiguousarray(xp.asarray(c, dtype=xp.complex64).reshape(-1, np.size(x)))
    n_trans, npts = c.shape
    fine = tuple(fine_grid_length(n, upsampling) for n in shape)
    (cell0, frac0), (cell1, frac1) = _cells(x, fine[0], xp), _cells(y, fine[1], xp)
    # sum_l grid[l] exp(+2 pi i k l / n) is n times the inverse FFT: n over the kernel's transform
    phi_hat = np.outer(*(kernel_transform(n, m, width, beta) for n, m in zip(shape, fine)))
    deconvolve = xp.asarray((fine[0] * fine[1] / phi_hat).astype(np.float32))
    rows0, rows1 = (xp.asarray(_modes(n, m)) for n, m in zip(shape, fine))
    out = xp.empty((n_trans, *shape), dtype=xp.float32 if real else xp.complex64)
    batch = max(1, MAX_GRID_ELEMENTS // (fine[0] * fine[1]))
    spread = _spread_kernel(xp)
    for start in range(0, n_trans, batch):
        part = c[start : start + batch]
        grid = xp.zeros((part.shape[0], *fine), dtype=xp.complex64)
        # flat: a raw argument is indexed by its flat index
        spread(part, cell0, frac0, cell1, frac1, npts, fine[0], fine[1], width, beta, grid.view(xp.float32).ravel())
        spectrum = xp.fft.ifft2(grid, axes=(-2, -1))
        del grid
        modes = spectrum[:, rows0][:, :, rows1]
        modes *= deconvolve
        out[start : start + part.shape[0]] = modes.real if real else modes
    return out
