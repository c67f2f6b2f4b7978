"""Array-module lookup: one numerical code for NumPy (CPU) and CuPy (GPU).

Every numerical function takes its arrays as they come and asks :func:`get_array_module`
which module owns them, in the style of CuPy-aware SciPy code. FFTs go through
:class:`FFT`, which is ``scipy.fft`` with a thread budget on the CPU and ``cupy.fft`` on the
GPU, so that a Dask worker pinned to N cores never spawns more FFT threads than it owns.
"""

from __future__ import annotations

import contextlib
import numbers
import os
import threading
from dataclasses import dataclass
from functools import cache
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
    """Map ``cpu|gpu|auto`` (docs/scan-format.md §3 ``--device``) to numpy or cupy."""
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


def ndimage(xp) -> ModuleType:
    """The ``scipy.ndimage`` of ``xp``'s device: SciPy's for NumPy, ``cupyx.scipy.ndimage`` for CuPy
    (filters and morphology of the same names and boundary modes)."""
    if xp is np:
        from scipy import ndimage as host

        return host
    from cupyx.scipy import ndimage as device

    return device


def to_numpy(a: Any) -> np.ndarray:
    """Host copy of an array of either module."""
    if type(a).__module__.startswith("cupy"):
        return a.get()
    return np.asarray(a)


#: whether CuPy arrays go through the package's CUDA kernels (``PWF_DASK_CUDA_KERNELS=1``): the
#: PWF iteration's element-wise passes (``pwf_dask.pwf.kernels._CUDA_KERNELS``) and the
#: backprojector (``pwf_dask.tomo.tomography``). Off by default until the device tests have run
#: with them on: on an H200 every iteration kernel gives the CuPy expressions' numbers
#: (``tests/test_kernels.py`` passed on the device, sessions 48 and 61); session 48's sums to a
#: scalar ran on one block (3.5x slower at 2160 x 2560), and with rows reduced first a
#: full-frame iteration is 1.06-1.16x faster with them (session 61: 5.54 against 6.45 ms on the
#: 1.5x field grid; 0.91-1.23x below 2048^2, where launches bound it). The backprojection
#: kernel (session 63) has not met a device yet. Off: the array-module forms
cuda_kernels = os.environ.get("PWF_DASK_CUDA_KERNELS", "0") == "1"

#: whether each thread's device work runs on a CUDA stream of its own (:func:`task_stream`);
#: False: every thread on CuPy's null stream (``benchmarks/gpu_checks.py`` times the two)
task_streams = True
_THREAD_STREAMS = threading.local()


def task_stream(xp):
    """The calling thread's own CUDA stream, to enter for one task's device work; a context
    that does nothing on NumPy.

    Tasks that share one GPU from a worker's threads (``--device gpu``) otherwise all run on
    the null stream, where each kernel waits for every other thread's and each host round trip
    (the solver's J, its stop statistics) drains the GPU of all tasks at once. The stream is
    made once per thread and device and kept: CuPy's memory pool gives a freed block again only
    to the stream that freed it. It synchronizes with the null stream, so arrays made there
    before are complete when a task reads them.
    """
    if xp is np or not task_streams:
        return contextlib.nullcontext()
    streams = _THREAD_STREAMS.__dict__.setdefault("streams", {})
    key = (id(xp), xp.cuda.Device().id)  # the module too: tests run CuPy and its CPU emulator
    if key not in streams:
        streams[key] = xp.cuda.Stream(non_blocking=False)
    return streams[key]


def synchronize(xp) -> None:
    """Wait for the current stream's work (device arrays that other threads' streams will read)."""
    if xp is not np:
        xp.cuda.get_current_stream().synchronize()


def default_fft_workers() -> int:
    """FFT threads for this process: ``PWF_DASK_FFT_WORKERS`` or all cores it may use."""
    env = os.environ.get("PWF_DASK_FFT_WORKERS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


#: arrays up to this size are recycled by the C allocator instead of mapped afresh
#: (:func:`recycle_large_arrays`)
_RECYCLED_ARRAY_BYTES = 1 << 30
_recycling: bool | None = None  # None: not tried yet in this process


def recycle_large_arrays() -> bool:
    """Let glibc's malloc reuse freed arrays of up to 1 GiB; True when it is in effect.

    glibc serves an allocation above its mmap threshold (128 kB, raised as large blocks are
    freed, but never past 32 MB) with fresh pages from the kernel and returns them when it is
    freed, so every temporary of a 2048^2 complex64 field (32 MB) pays a page fault and a
    zeroing per 4 kB page. Measured here at 2048^2, 2 threads: a complex-by-real product
    7.6 -> 4.7 ms, |v|^2 8.3 -> 3.4 ms, one whole PWF iteration 380-400 -> 276-280 ms
    (iteration / FFT 20.5 -> 16.4); 1024^2 and below barely move. The cost: memory a task
    freed stays with the process for the next task instead of going back to the system, so
    a worker's resident size stays at its peak (the peak itself is unchanged). Called once
    per process by :meth:`FFT.for_module` for NumPy; ``PWF_DASK_RECYCLE_ARRAYS=0`` leaves the
    allocator alone, and so does any C library without glibc's ``mallopt``.
    """
    global _recycling
    if _recycling is None:
        _recycling = os.environ.get("PWF_DASK_RECYCLE_ARRAYS", "1") != "0" and _raise_mmap_threshold()
    return _recycling


def _raise_mmap_threshold() -> bool:
    try:
        import ctypes

        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError, TypeError):  # no mallopt: macOS, Windows
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's <malloc.h>
    return bool(mallopt(m_mmap_threshold, _RECYCLED_ARRAY_BYTES) and mallopt(m_trim_threshold, _RECYCLED_ARRAY_BYTES))


#: inputs of fewer points than this (a stack counts whole, a half spectrum as it is) are
#: transformed on one thread whatever the budget
_THREADED_FFT_MIN_POINTS = 1 << 16


#: CPU FFT libraries of :class:`FFT`: ``auto`` takes Intel MKL's (``mkl_fft``) where it imports
#: on an Intel CPU, and on other CPUs for one thread; else scipy's pocketfft
CPU_FFT_LIBRARIES = ("auto", "mkl", "scipy")


def default_fft_library() -> str:
    """``PWF_DASK_FFT`` (auto, mkl or scipy), ``auto`` when unset."""
    return os.environ.get("PWF_DASK_FFT", "auto").strip().lower() or "auto"


@cache
def _mkl_scipy_fft() -> ModuleType | None:
    # Intel's OpenMP lets a thread spin 200 ms after each threaded transform, taking a core
    # from the process's other tasks and from the other workers of a node; 0 lets it sleep
    # (2 threads at 1024^2 and 2048^2: the same speed). A value the user set is kept.
    os.environ.setdefault("KMP_BLOCKTIME", "0")
    try:
        from mkl_fft.interfaces import scipy_fft
    except ImportError:  # no wheel for this platform (not x86-64), or MKL's runtime missing
        return None
    return scipy_fft


@cache
def cpu_vendor() -> str:
    """The CPU's vendor string (``GenuineIntel``, ``AuthenticAMD``, ...), "" where unknown."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    import platform

    return "GenuineIntel" if "intel" in platform.processor().lower() else ""


def resolve_fft_library(library: str | None = None, workers: int | None = None) -> str:
    """The CPU FFT library :class:`FFT` uses for ``workers`` threads (default
    :func:`default_fft_workers`): ``"mkl"`` or ``"scipy"``.

    ``None`` reads ``PWF_DASK_FFT``. ``"auto"`` takes MKL (``mkl_fft.interfaces.scipy_fft``:
    scipy's signatures, ``workers`` honoured per call and per thread) where it imports, on an
    Intel CPU, and on other CPUs for single-threaded transforms (a scan task's, where tasks
    share the cores); pocketfft elsewhere. Measured with complex64 (docs/benchmarks.md): on an
    Intel Xeon with AVX-512 MKL was 2.5-2.9x faster than pocketfft at 1024^2 and 2048^2 on one
    thread, 2.0-2.5x on two (real transforms 1.5-2.2x), a PWF iteration 1.4-1.7x. On two AMD
    EPYCs with AVX2 it was faster on one thread (session 38: 1.08-1.5x a transform; session 50:
    a PWF iteration 1.13x at 1024^2 and 1.35x at 2048^2) and on two threads slower on one
    machine (session 38), 1.10-1.27x faster on the other (session 50). Session 107's EPYC ran
    an iteration 0.82-1.44x as fast with MKL on two threads, median 1.15x
    (``benchmarks/fft_library.py``), but there MKL's two-thread 2-D transforms of 2048 x 2048
    came out wrong (relative error 1):
    the fft2 of a float32 image every time, and an ifft2 of complex64 depending on the calls
    before it, which a check once per layout (:func:`_mkl_agrees`) cannot catch. One thread
    agreed on every call tried, so threaded FFTs off Intel stay pocketfft's.
    """
    library = default_fft_library() if library is None else str(library).strip().lower()
    if library not in CPU_FFT_LIBRARIES:
        raise ValueError(f"FFT library must be one of {', '.join(CPU_FFT_LIBRARIES)}, not {library!r}")
    workers = default_fft_workers() if workers is None else max(1, int(workers))
    if library == "scipy" or (library == "auto" and cpu_vendor() != "GenuineIntel" and workers > 1):
        return "scipy"
    if _mkl_scipy_fft() is None:
        if library == "mkl":
            raise RuntimeError("FFT library 'mkl': mkl_fft does not import here (pip install mkl-fft mkl-service)")
        return "scipy"
    return "mkl"


def _cpu_transform(module: ModuleType, name: str, a, s, workers: int, overwrite: bool):
    """``name`` (fft2, ifft2, rfft2 or irfft2) over the last two axes by a scipy.fft-like module."""
    if name == "rfft2":
        return module.rfft2(a, s=s, workers=workers)
    if name == "irfft2":
        # two 1-D passes, not a 2-D c2r, for both libraries. pocketfft's allocates its own
        # complex intermediate and measured 1.3-1.4x slower from 2048^2 on (2048^2, 2 threads:
        # 12.6 ms against 8.9; 2200 x 2625: 19.1 against 14.6), even below. MKL's took 3.3 ms
        # inside a 1024^2 iteration (one thread), its r2c 2.1: the two passes made the whole
        # iteration 7-8 % faster (81.9 -> 75.5 ms with L1 > 0, 65.3 -> 60.3 with L1 = 0; session
        # 43). The column pass may work in the caller's memory when it no longer needs it
        # (:func:`_mkl_agrees` checks MKL's in-place column pass per layout)
        half = module.ifft(a, n=s[-2], axis=-2, workers=workers, overwrite_x=overwrite)
        return module.irfft(half, n=s[-1], axis=-1, workers=workers, overwrite_x=True)
    return getattr(module, name)(a, s=s, workers=workers, overwrite_x=overwrite)


#: (transform, shape, s, dtype, workers, overwrite) -> whether MKL agrees with pocketfft there
_MKL_AGREES: dict[tuple, bool] = {}


def _mkl_agrees(name: str, a, s, workers: int, overwrite: bool) -> bool:
    """Whether MKL's ``name`` gives pocketfft's transform for this input layout, checked once
    per process on random numbers of the same shape and type.

    MKL 2026.2 (mkl_fft 2.3.2) returns wrong numbers, with no error, for a column pass of
    length 40 or 48 done in place: its rfft2 of any 40- or 48-row image and its in-place
    column FFTs (found by comparing every length from 2 to 2999 with pocketfft; every other
    length and every 2-D complex transform tried agreed to rounding). A layout where the two
    disagree is transformed by pocketfft from then on, with one warning.
    """
    key = (name, a.shape, s, a.dtype.str, workers, overwrite)
    agrees = _MKL_AGREES.get(key)
    if agrees is None:
        import scipy.fft

        rng = np.random.default_rng(0)
        if name == "irfft2":  # a real image's half spectrum: c2r transforms read no other
            x = scipy.fft.rfft2(rng.standard_normal(a.shape[:-2] + s).astype(a.real.dtype))
        else:
            x = rng.standard_normal(a.shape).astype(a.real.dtype)
            if np.iscomplexobj(a):
                x = x + 1j * rng.standard_normal(a.shape).astype(a.real.dtype)
        want = _cpu_transform(scipy.fft, name, x.copy(), s, workers, False)
        got = _cpu_transform(_mkl_scipy_fft(), name, x.copy(), s, workers, overwrite)
        tol = 1e-3 if x.real.dtype == np.float32 else 1e-9
        agrees = bool(np.max(np.abs(got - want)) <= tol * np.max(np.abs(want)))
        _MKL_AGREES[key] = agrees
        if not agrees:
            from pwf_dask.log import logger

            logger.warning(
                "MKL's %s of a %s %s array disagrees with pocketfft; pocketfft transforms it instead",
                name,
                "x".join(map(str, a.shape)),
                a.dtype,
            )
    return agrees


@dataclass(frozen=True)
class FFT:
    """2-D FFTs over the last two axes for one array module, with a CPU thread budget."""

    xp: ModuleType
    workers: int = 1
    #: the CPU's transforms (:func:`resolve_fft_library`): ``"mkl"`` or ``"scipy"``
    library: str = "scipy"

    @classmethod
    def for_module(cls, xp: ModuleType, workers: int | None = None, library: str | None = None) -> FFT:
        """``workers`` FFT threads (default :func:`default_fft_workers`); ``library`` on the CPU
        (default ``PWF_DASK_FFT``, else MKL where it imports and pays: :func:`resolve_fft_library`)."""
        if xp is np:
            recycle_large_arrays()
        workers = default_fft_workers() if workers is None else max(1, int(workers))
        return cls(xp, workers, resolve_fft_library(library, workers) if xp is np else xp.__name__)

    def _threads(self, points: int) -> int:
        # pocketfft's threads cost more than they save on small grids: measured here with 2
        # threads against 1, c2c/r2c at 84 x 162 took 0.32/0.28 ms against 0.24/0.13, about
        # even at 256 x 256, 1.6-2x faster from 512 x 512 on
        return self.workers if points >= _THREADED_FFT_MIN_POINTS else 1

    def _cpu(self, name: str, a, s, overwrite: bool):
        import scipy.fft

        workers = self._threads(a.size)
        s = None if s is None else tuple(int(n) for n in s)
        module = scipy.fft
        if self.library == "mkl":
            if not a.flags.c_contiguous:
                # MKL read a broadcast (zero-stride) input wrongly; a copy is the layout checked
                a, overwrite = np.ascontiguousarray(a), True
            if _mkl_agrees(name, a, s, workers, overwrite):
                module = _mkl_scipy_fft()
        return _cpu_transform(module, name, a, s, workers, overwrite)

    # ``overwrite=True`` lets the transform reuse the input's memory (the caller no longer needs
    # it): no fresh output array per transform, which at 2048^2 (32 MB, above glibc's mmap
    # threshold) costs page faults every call, and no defensive input copy in irfft2.
    # cupy.fft has no such flag; it is ignored there.

    def fft2(self, a, s=None, overwrite: bool = False):
        if self.xp is np:
            return self._cpu("fft2", a, s, overwrite)
        return self.xp.fft.fft2(a, s=s)

    def ifft2(self, a, s=None, overwrite: bool = False):
        if self.xp is np:
            return self._cpu("ifft2", a, s, overwrite)
        return self.xp.fft.ifft2(a, s=s)

    def rfft2(self, a, s=None):
        if self.xp is np:
            return self._cpu("rfft2", a, s, False)
        return self.xp.fft.rfft2(a, s=s)

    def irfft2(self, a, s, overwrite: bool = False):
        if self.xp is np:
            return self._cpu("irfft2", a, s, overwrite)
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


def elementwise_pool():
    """This process's threads for element-wise passes (:func:`pwf_dask.pwf.kernels.complex_exp`),
    started on first use, at least two."""
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


#: elements per partial sum of :func:`inner` on the CPU
_INNER_BLOCK = 1 << 16


def inner(a, b, host: bool = True) -> complex:
    """<a, b> = sum conj(a) b, accurate to float64 rounding of float32 partial sums.

    NumPy's vdot on complex64 hands the whole array to a BLAS dot that accumulates in single
    precision: at 2048^2 its <x, x> is 3.7e-5 short relative to float64 (7e-5 at 2600^2),
    more than the paper's stop tolerance 1 - 10^-0.00001 = 2.3e-5, so a field correlation
    built from it never passes on full detector frames. Partial dots over 65536 elements
    summed in float64 keep the error near 1e-7 at any size, at the cost of one pass. CuPy's
    reductions are tree-shaped and accurate as they are. ``host=False`` leaves CuPy's sum on
    the device, a 0-d array for :func:`host_numbers` to fetch with others (NumPy's is a number).
    """
    xp = get_array_module(a, b)
    if xp is not np:
        total = xp.vdot(a, b)
        return complex(total) if host else total
    fa, fb = a.reshape(-1), b.reshape(-1)
    n = fa.size
    total = 0j
    for i in range(0, n, _INNER_BLOCK):
        total += complex(np.vdot(fa[i : i + _INNER_BLOCK], fb[i : i + _INNER_BLOCK]))
    return total


def host_numbers(values: list) -> list:
    """``values`` (Python numbers, or 0-d device arrays left there by ``host=False``) as Python
    numbers, the device's in one transfer: on a GPU each fetch of a scalar is a synchronisation
    that drains the queue of launched kernels and leaves the device idle while the host launches
    the next ones, so an iteration fetches all its sums at once (:func:`pwf_dask.pwf.solver.pwf`).
    Float sums stay floats and complex ones complex, exactly (widened to complex128 for the
    transfer by the copies that gather them: CuPy copies each array in a kernel of its own below
    nine arrays, and a cast before each would be a second kernel)."""
    on_device = [i for i, v in enumerate(values) if not isinstance(v, numbers.Number)]
    if not on_device:
        return list(values)
    xp = get_array_module(values[on_device[0]])
    gathered = xp.concatenate([values[i].reshape(1) for i in on_device], dtype=xp.complex128)
    fetched = to_numpy(gathered)
    out = list(values)
    for i, number in zip(on_device, fetched):
        complex_sum = values[i].dtype.kind == "c"
        out[i] = complex(number) if complex_sum else float(number.real)
    return out
