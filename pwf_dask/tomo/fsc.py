"""Fourier shell correlation, Eq. (FSC), and resolution criteria (Methods, FSC).

* ``"1/4"`` - the paper's criterion for two independent reconstructions (Eq. C=0.5 with
  Eq. FSC+SN, no half-set extrapolation);
* ``"1/7"`` - Rosenthal & Henderson's 0.143 for half-set averages;
* ``"half-bit"`` - van Heel & Schatz's half-bit curve, which depends on the shell size;
* ``"1/2"`` - against a known ground truth (Eq. C=0.5 itself).
"""

from __future__ import annotations

import numpy as np

CRITERIA = ("1/4", "1/7", "half-bit", "1/2")


def _shell_slab(shape, spacing_m: float, rows: slice):
    """Shell index of every rfftn bin in rows ``rows`` of the first axis (shells one frequency
    step 1/(N p) wide, N = min(shape); -1 beyond Nyquist), and the bins' weights: rfft keeps
    half the spectrum, so interior columns stand for two bins."""
    grids = [np.fft.fftfreq(n, d=spacing_m) for n in shape[:-1]] + [np.fft.rfftfreq(shape[-1], d=spacing_m)]
    grids[0] = grids[0][rows]
    k2 = np.zeros([len(g) for g in grids])
    for ax, g in enumerate(grids):
        sh = [1] * len(grids)
        sh[ax] = -1
        k2 += g.reshape(sh) ** 2
    step = 1.0 / (min(shape) * spacing_m)
    nshell = min(shape) // 2
    idx = np.floor(np.sqrt(k2) / step + 0.5).astype(np.int32)
    idx[idx >= nshell] = -1
    weight = np.full(k2.shape, 2.0, np.float32)
    weight[..., 0] = 1.0
    if shape[-1] % 2 == 0:
        weight[..., -1] = 1.0
    return idx, weight


def _centred_rfftn(a) -> np.ndarray:
    import scipy.fft

    x = np.array(a, np.float32)  # a copy: the caller's array is left alone
    x -= np.float32(x.mean(dtype=np.float64))
    return scipy.fft.rfftn(x, overwrite_x=True, workers=-1)


def fourier_shell_correlation(a: np.ndarray, b: np.ndarray, spacing_m: float):
    """Eq. (FSC) between two arrays (2-D or 3-D) on the same grid.

    Returns (frequency in cycles/m, fsc, voxels per shell); the DC shell is excluded. The
    transforms are single precision and the shell sums are accumulated in double precision
    over slabs of the first axis: the peak is about 16 bytes per voxel of one volume (two
    complex half-spectra) instead of the ~60 of a double-precision pass (issue #29).
    """
    if np.shape(a) != np.shape(b):
        raise ValueError(f"FSC needs equal shapes, got {np.shape(a)} and {np.shape(b)}")
    shape = np.shape(a)
    fa = _centred_rfftn(a)
    fb = _centred_rfftn(b)
    n = min(shape) // 2
    sums = np.zeros((4, n))
    step = max(1, 2**22 // max(1, int(np.prod(fa.shape[1:]))))  # ~4 M bins per slab
    for start in range(0, shape[0], step):
        rows = slice(start, min(shape[0], start + step))
        idx, weight = _shell_slab(shape, spacing_m, rows)
        ok = idx >= 0
        sa, sb, w = fa[rows][ok], fb[rows][ok], weight[ok].astype(np.float64)
        i = idx[ok]
        sums[0] += np.bincount(i, w * (sa.real.astype(np.float64) * sb.real + sa.imag.astype(np.float64) * sb.imag), n)
        sums[1] += np.bincount(i, w * (sa.real.astype(np.float64) ** 2 + sa.imag.astype(np.float64) ** 2), n)
        sums[2] += np.bincount(i, w * (sb.real.astype(np.float64) ** 2 + sb.imag.astype(np.float64) ** 2), n)
        sums[3] += np.bincount(i, w, n)
    num, da, db, count = sums
    with np.errstate(invalid="ignore", divide="ignore"):
        fsc = num / np.sqrt(da * db)
    freq = np.arange(n) / (min(shape) * spacing_m)
    return freq[1:], np.nan_to_num(fsc[1:]), count[1:]


def threshold(criterion: str, counts: np.ndarray) -> np.ndarray:
    """Threshold curve of a criterion over shells with ``counts`` voxels."""
    if criterion == "1/4":
        return np.full(counts.shape, 0.25)
    if criterion == "1/7":
        return np.full(counts.shape, 1 / 7)
    if criterion == "1/2":
        return np.full(counts.shape, 0.5)
    if criterion == "half-bit":
        r = 1 / np.sqrt(np.maximum(counts, 1))
        return (0.2071 + 1.9102 * r) / (1.2071 + 0.9102 * r)
    raise ValueError(f"unknown FSC criterion {criterion!r}; choose one of {', '.join(CRITERIA)}")


def resolution(freq: np.ndarray, fsc: np.ndarray, counts: np.ndarray, criterion: str) -> float:
    """Resolution (m) = 1 / first frequency where the FSC falls below the criterion
    (linear interpolation); the Nyquist period 2p if it never does."""
    t = threshold(criterion, counts)
    below = np.nonzero(fsc < t)[0]
    if below.size == 0:
        return float(1.0 / freq[-1]) if freq[-1] > 0 else float("nan")
    i = int(below[0])
    if i == 0:
        return float(1.0 / freq[0])
    d0, d1 = fsc[i - 1] - t[i - 1], fsc[i] - t[i]
    f = freq[i - 1] + (freq[i] - freq[i - 1]) * d0 / (d0 - d1)
    return float(1.0 / f)
