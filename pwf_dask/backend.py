"""Array-module lookup: one numerical code for NumPy (CPU) and CuPy (GPU).

Every numerical function takes its arrays as they come and asks :func:`get_array_module`
which module owns them, in the style of CuPy-aware SciPy code. FFTs go through
:class:`FFT`, which is ``scipy.fft`` with a thread budget on the CPU and ``cupy.fft`` on the
GPU, so that a Dask worker pinned to N cores never spawns more FFT threads than it owns.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np


def cupy_or_none() -> ModuleType | None:
    """CuPy if it imports and sees a device, else None (GPU tests skip on None)."""
    try:
        import cupy

        if cupy.cuda.runtime.getDeviceCount() < 1:
            return None
        return cupy
    except Exception:  # ImportError, CUDA driver errors: no usable GPU
        return None


def get_array_module(*arrays: Any) -> ModuleType:
    """The array module (numpy or cupy) that owns ``arrays``; NumPy for plain Python input."""
    for a in arrays:
        mod = type(a).__module__
        if mod.startswith("cupy"):
            import cupy

            return cupy
    return np


def resolve_device(device: str) -> ModuleType:
    """Map ``cpu|gpu|auto`` (CONTRACT §3 ``--device``) to numpy or cupy."""
    if device == "cpu":
        return np
    cp = cupy_or_none()
    if device == "gpu":
        if cp is None:
            raise RuntimeError("--device gpu: CuPy with a CUDA device is not available")
        return cp
    if device == "auto":
        return cp if cp is not None else np
    raise ValueError(f"device must be cpu, gpu or auto, not {device!r}")


def to_numpy(a: Any) -> np.ndarray:
    """Host copy of an array of either module."""
    if type(a).__module__.startswith("cupy"):
        return a.get()
    return np.asarray(a)


def default_fft_workers() -> int:
    """FFT threads for this process: ``PWF_DASK_FFT_WORKERS`` or all cores it may use."""
    env = os.environ.get("PWF_DASK_FFT_WORKERS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


#: inputs of fewer points than this (a stack counts whole, a half spectrum as it is) are
#: transformed on one thread whatever the budget
_THREADED_FFT_MIN_POINTS = 1 << 16


@dataclass(frozen=True)
class FFT:
    """2-D FFTs over the last two axes for one array module, with a CPU thread budget."""

    xp: ModuleType
    workers: int = 1

    @classmethod
    def for_module(cls, xp: ModuleType, workers: int | None = None) -> FFT:
        return cls(xp, default_fft_workers() if workers is None else max(1, int(workers)))

    def _cpu(self) -> bool:
        return self.xp is np

    def _threads(self, points: int) -> int:
        # pocketfft's threads cost more than they save on small grids: measured here with 2
        # threads against 1, c2c/r2c at 84 x 162 took 0.32/0.28 ms against 0.24/0.13, about
        # even at 256 x 256, 1.6-2x faster from 512 x 512 on
        return self.workers if points >= _THREADED_FFT_MIN_POINTS else 1

    # ``overwrite=True`` lets scipy.fft reuse the input's memory (the caller no longer needs
    # it): no fresh output array per transform, which at 2048^2 (32 MB, above glibc's mmap
    # threshold) costs page faults every call, and no defensive input copy in irfft2.
    # cupy.fft has no such flag; it is ignored there.

    def fft2(self, a, s=None, overwrite: bool = False):
        if self._cpu():
            import scipy.fft as sf

            return sf.fft2(a, s=s, workers=self._threads(a.size), overwrite_x=overwrite)
        return self.xp.fft.fft2(a, s=s)

    def ifft2(self, a, s=None, overwrite: bool = False):
        if self._cpu():
            import scipy.fft as sf

            return sf.ifft2(a, s=s, workers=self._threads(a.size), overwrite_x=overwrite)
        return self.xp.fft.ifft2(a, s=s)

    def rfft2(self, a, s=None):
        if self._cpu():
            import scipy.fft as sf

            return sf.rfft2(a, s=s, workers=self._threads(a.size))
        return self.xp.fft.rfft2(a, s=s)

    def irfft2(self, a, s, overwrite: bool = False):
        if self._cpu():
            import scipy.fft as sf

            # two 1-D passes, not pocketfft's 2-D c2r: that allocates its own complex
            # intermediate and measured 1.3-1.4x slower from 2048^2 on (2048^2, 2 threads:
            # 12.6 ms against 8.9; 2200 x 2625: 19.1 against 14.6), even below; the column
            # pass may work in the caller's memory when it no longer needs it
            workers = self._threads(a.size)
            half = sf.ifft(a, n=s[-2], axis=-2, workers=workers, overwrite_x=overwrite)
            return sf.irfft(half, n=s[-1], axis=-1, workers=workers, overwrite_x=True)
        return self.xp.fft.irfft2(a, s=s)


def real_dtype(precision: str):
    """float32 for ``"single"`` (default, complex64 fields), float64 for ``"double"``."""
    if precision in ("single", "float32", "complex64"):
        return np.float32
    if precision in ("double", "float64", "complex128"):
        return np.float64
    raise ValueError(f"precision must be 'single' or 'double', not {precision!r}")


def complex_dtype(precision: str):
    return np.complex64 if real_dtype(precision) == np.float32 else np.complex128


_POOL = None  # threads for element-wise passes, shared by all callers of this process


def _pool():
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max(2, default_fft_workers()), thread_name_prefix="pwf-elementwise")
    return _POOL


def _forget_pool_in_child() -> None:
    # a forked worker inherits the pool object but not its threads: start a fresh one there
    global _POOL
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_in_child)


def _complex_exp_into(z, out) -> None:
    mag = np.exp(z.real)
    np.multiply(mag, np.cos(z.imag), out=out.real)
    np.multiply(mag, np.sin(z.imag), out=out.imag)


def complex_exp(z, workers: int = 1):
    """exp(z) for complex arrays. NumPy's complex64 exp is ~5x slower than exp(Re) (cos, sin)
    of the float32 parts (12.7 vs 2.7 ms at 512^2 here); CuPy's fused kernel is used as is.

    On the CPU, ``workers`` > 1 splits the rows over that many threads (NumPy releases the
    GIL in ufuncs): this is the costliest element-wise pass of an iteration (about one FFT
    time single-threaded) and the FFTs beside it already use ``workers`` threads. Each element
    is computed by the same ufunc either way, so the result is bitwise the same.
    """
    xp = get_array_module(z)
    if xp is not np:
        return xp.exp(z)
    out = np.empty_like(z)
    blocks = min(int(workers), z.shape[0]) if z.ndim >= 1 else 1
    if blocks <= 1 or z.size < 1 << 16:
        _complex_exp_into(z, out)
        return out
    edges = [z.shape[0] * i // blocks for i in range(blocks + 1)]
    jobs = [_pool().submit(_complex_exp_into, z[a:b], out[a:b]) for a, b in zip(edges[:-1], edges[1:])]
    for job in jobs:
        job.result()
    return out


#: elements per partial sum of :func:`inner` on the CPU
_INNER_BLOCK = 1 << 16


def inner(a, b) -> complex:
    """<a, b> = sum conj(a) b, accurate to float64 rounding of float32 partial sums.

    NumPy's vdot on complex64 hands the whole array to a BLAS dot that accumulates in single
    precision: at 2048^2 its <x, x> is 3.7e-5 short relative to float64 (7e-5 at 2600^2),
    more than the paper's stop tolerance 1 - 10^-0.00001 = 2.3e-5, so a field correlation
    built from it never passes on full detector frames. Partial dots over 65536 elements
    summed in float64 keep the error near 1e-7 at any size, at the cost of one pass. CuPy's
    reductions are tree-shaped and accurate as they are.
    """
    xp = get_array_module(a, b)
    if xp is not np:
        return complex(xp.vdot(a, b))
    fa, fb = a.reshape(-1), b.reshape(-1)
    n = fa.size
    total = 0j
    for i in range(0, n, _INNER_BLOCK):
        total += complex(np.vdot(fa[i : i + _INNER_BLOCK], fb[i : i + _INNER_BLOCK]))
    return total


def abs2(z):
    """|z|^2 of a complex array as a real array, without the square root of abs."""
    xp = get_array_module(z)
    out = xp.square(z.real)
    out += xp.square(z.imag)
    return out
