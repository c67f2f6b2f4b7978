"""The CPU FFT libraries of pwf_dask.backend.FFT: MKL's transforms where mkl_fft imports,
checked against scipy's pocketfft per input layout, pocketfft where they disagree."""

import logging

import numpy as np
import pytest
import scipy.fft

from pwf_dask import backend
from pwf_dask.backend import FFT

mkl = pytest.mark.skipif(backend._mkl_scipy_fft() is None, reason="mkl_fft does not import here")


def _input(name, shape, dtype, rng):
    real = rng.standard_normal(shape).astype(dtype)
    if name == "rfft2":
        return real
    if name == "irfft2":
        return scipy.fft.rfft2(real)
    return (real + 1j * rng.standard_normal(shape).astype(dtype)).astype(np.result_type(dtype, np.complex64))


def _call(fft, name, a, shape, overwrite):
    if name == "rfft2":
        return fft.rfft2(a)
    if name == "irfft2":
        return fft.irfft2(a, shape, overwrite=overwrite)
    return getattr(fft, name)(a, overwrite=overwrite)


@mkl
@pytest.mark.parametrize("name", ["fft2", "ifft2", "rfft2", "irfft2"])
@pytest.mark.parametrize("shape", [(40, 52), (48, 30), (64, 64), (67, 130), (2, 48, 40)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("overwrite", [False, True])
def test_mkl_transforms_give_pocketffts(name, shape, dtype, overwrite):
    """Every transform, on the 40- and 48-row frames where MKL 2026.2 alone is wrong (its rfft2
    and in-place column passes), a stack, both precisions, in place or not."""
    rng = np.random.default_rng(3)
    a = _input(name, shape, dtype, rng)
    want = _call(FFT.for_module(np, 1, "scipy"), name, a.copy(), shape[-2:], False)
    got = _call(FFT.for_module(np, 2, "mkl"), name, a.copy(), shape[-2:], overwrite)
    assert got.dtype == want.dtype and got.shape == want.shape
    tol = 2e-6 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(got, want, rtol=0, atol=tol * np.abs(want).max())


@mkl
def test_mkl_reads_a_broadcast_input_as_pocketfft_does():
    """A zero-stride view (np.broadcast_to), which MKL read wrongly, is copied first."""
    row = np.exp(1j * np.linspace(0, 3, 48))
    a = np.broadcast_to(row[None, :], (48, 48))
    np.testing.assert_allclose(FFT.for_module(np, 1, "mkl").fft2(a), scipy.fft.fft2(a), atol=1e-9)


def test_a_layout_the_library_gets_wrong_falls_back_to_pocketfft(monkeypatch, caplog):
    """The per-layout check is real: a library that returns wrong numbers for one shape is
    replaced there by pocketfft, with one warning, and used elsewhere."""

    class Wrong:
        __name__ = "mkl_fft.interfaces.scipy_fft"

        def __getattr__(self, name):
            fn = getattr(scipy.fft, name)

            def call(a, *args, **kw):
                out = fn(a, *args, **kw)
                return out * 2 if a.shape[-2] == 40 else out

            return call

    monkeypatch.setattr(backend, "_mkl_scipy_fft", lambda: Wrong())
    monkeypatch.setattr(backend, "_MKL_AGREES", {})
    fft = FFT(np, 1, "mkl")
    rng = np.random.default_rng(0)
    a40, a41 = rng.standard_normal((40, 52)), rng.standard_normal((41, 52))
    with caplog.at_level(logging.WARNING, logger="pwf_dask"):
        np.testing.assert_allclose(fft.fft2(a40), scipy.fft.fft2(a40))
        np.testing.assert_allclose(fft.fft2(a40), scipy.fft.fft2(a40))
    assert backend._MKL_AGREES[("fft2", (40, 52), None, a40.dtype.str, 1, False)] is False
    assert sum("disagrees with pocketfft" in r.getMessage() for r in caplog.records) == 1
    np.testing.assert_allclose(fft.fft2(a41), scipy.fft.fft2(a41))
    assert backend._MKL_AGREES[("fft2", (41, 52), None, a41.dtype.str, 1, False)] is True


def test_the_library_is_chosen_by_name_or_environment(monkeypatch):
    monkeypatch.setenv("PWF_DASK_FFT", "scipy")
    assert FFT.for_module(np).library == "scipy"
    monkeypatch.setenv("PWF_DASK_FFT", "fftw")
    with pytest.raises(ValueError, match="FFT library must be one of auto, mkl, scipy, not 'fftw'"):
        FFT.for_module(np)
    monkeypatch.setattr(backend, "cpu_vendor", lambda: "AuthenticAMD")
    # elsewhere than on Intel MKL pays on one thread, and was slower on two on one AMD machine
    assert FFT.for_module(np, 2, library="auto").library == "scipy"
    mkl = "scipy" if backend._mkl_scipy_fft() is None else "mkl"
    assert FFT.for_module(np, 1, library="auto").library == mkl
    monkeypatch.setattr(backend, "cpu_vendor", lambda: "GenuineIntel")
    assert FFT.for_module(np, 2, library="auto").library == mkl
    monkeypatch.setattr(backend, "_mkl_scipy_fft", lambda: None)
    assert FFT.for_module(np, library="auto").library == "scipy"
    with pytest.raises(RuntimeError, match="mkl_fft does not import here"):
        FFT.for_module(np, library="mkl")


@pytest.mark.gpu
def test_each_thread_keeps_its_own_stream(cupy):
    """backend.task_stream: one stream per thread (and device), the same for each of its tasks,
    current inside the block; nothing on NumPy or with task_streams off."""
    import contextlib
    import threading

    assert isinstance(backend.task_stream(np), contextlib.nullcontext)
    mine = backend.task_stream(cupy)
    assert backend.task_stream(cupy) is mine
    with mine:
        assert cupy.cuda.get_current_stream() is mine
        backend.synchronize(cupy)
    assert cupy.cuda.get_current_stream() is not mine
    other = []
    thread = threading.Thread(target=lambda: other.append(backend.task_stream(cupy)))
    thread.start()
    thread.join()
    assert other[0] is not mine
    backend.task_streams = False
    try:
        assert isinstance(backend.task_stream(cupy), contextlib.nullcontext)
    finally:
        backend.task_streams = True


@pytest.mark.gpu
def test_host_numbers_fetches_device_sums_at_once_and_exactly(cupy):
    """Issue #31: an iteration's sums left on the device come back in one transfer, each the
    number a fetch of its own gives (floats stay floats, complex sums complex); host numbers
    pass through."""
    import emulated_cupy

    a = cupy.asarray(np.array([1.1, 2.3, -0.7], np.float32))
    c = cupy.asarray(np.array([1 + 2j, 3 - 1j], np.complex64))
    values = [0.5, cupy.sum(a), cupy.vdot(c, c * 1.3j), 2j, cupy.sum(a, dtype=cupy.float64), cupy.vdot(c, c).real]
    before = emulated_cupy.transfers
    numbers = backend.host_numbers(values)
    if cupy.ndarray is emulated_cupy.ndarray:
        assert emulated_cupy.transfers - before == 1
    one_by_one = [0.5, float(values[1]), complex(values[2]), 2j, float(values[4]), float(values[5])]
    assert numbers == one_by_one
    assert [type(v) for v in numbers] == [float, float, complex, complex, float, float]
    assert backend.host_numbers([1.0, 3j]) == [1.0, 3j]
    assert backend.host_numbers([np.array(2.5, np.float32), np.float32(0.5)]) == [2.5, np.float32(0.5)]  # 0-d host too
