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


def shell_indices(shape, spacing_m: float):
    """Shell index of every rfftn bin (shells one frequency step 1/(N p) wide, N = min(shape))
    and the shells' centre frequencies in cycles per metre, up to Nyquist."""
    grids = [np.fft.fftfreq(n, d=spacing_m) for n in shape[:-1]] + [np.fft.rfftfreq(shape[-1], d=spacing_m)]
    k2 = np.zeros([len(g) for g in grids])
    for ax, g in enumerate(grids):
        sh = [1] * len(grids)
        sh[ax] = -1
        k2 = k2 + g.reshape(sh) ** 2
    k = np.sqrt(k2)
    step = 1.0 / (min(shape) * spacing_m)
    nshell = min(shape) // 2
    idx = np.floor(k / step + 0.5).astype(np.int64)
    idx[idx >= nshell] = -1
    # rfft keeps half the spectrum: interior columns stand for two bins
    weight = np.full(k.shape, 2.0)
    weight[..., 0] = 1.0
    if shape[-1] % 2 == 0:
        weight[..., -1] = 1.0
    return idx, weight, np.arange(nshell) * step


def fourier_shell_correlation(a: np.ndarray, b: np.ndarray, spacing_m: float):
    """Eq. (FSC) between two arrays (2-D or 3-D) on the same grid.

    Returns (frequency in cycles/m, fsc, voxels per shell); the DC shell is excluded.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"FSC needs equal shapes, got {a.shape} and {b.shape}")
    fa = np.fft.rfftn(a - a.mean())
    fb = np.fft.rfftn(b - b.mean())
    idx, weight, freq = shell_indices(a.shape, spacing_m)
    ok = idx >= 0
    n = len(freq)
    num = np.bincount(idx[ok], (weight * np.real(fa * np.conj(fb)))[ok], n)
    da = np.bincount(idx[ok], (weight * np.abs(fa) ** 2)[ok], n)
    db = np.bincount(idx[ok], (weight * np.abs(fb) ** 2)[ok], n)
    count = np.bincount(idx[ok], weight[ok], n)
    with np.errstate(invalid="ignore", divide="ignore"):
        fsc = num / np.sqrt(da * db)
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
