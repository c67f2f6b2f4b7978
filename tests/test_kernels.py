"""The fused passes of the iteration (pwf_dask.pwf.kernels): the compiled loops give the NumPy
expressions they replace, to float32 rounding, and the solver's direction is today's."""

import numpy as np
import pytest

from pwf_dask import backend
from pwf_dask.backend import FFT
from pwf_dask.physics import optics
from pwf_dask.pwf import kernels, solver

pytest.importorskip("numba")


@pytest.fixture
def arrays():
    rng = np.random.default_rng(0)
    shape = (67, 130)

    def c():
        return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)

    def r():
        return rng.normal(size=shape).astype(np.float32)

    return c, r


def both(fn, *args):
    """fn's result with the compiled loops and with the array-module expressions."""
    compiled = fn(*[a.copy() if isinstance(a, np.ndarray) else a for a in args])
    saved = kernels._numba()
    kernels.numba = None
    try:
        generic = fn(*[a.copy() if isinstance(a, np.ndarray) else a for a in args])
    finally:
        kernels.numba = saved
    return compiled, generic


def close(a, b):
    if isinstance(a, tuple):
        for x, y in zip(a, b):
            close(x, y)
    else:
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-6, atol=1e-6)


def test_each_fused_pass_gives_the_numpy_expression(arrays):
    c, r = arrays
    mask = (r() > 0).astype(np.float32)
    x, y, z = c(), c(), c()
    close(*both(kernels.intensity, x))
    close(*both(kernels.residual_and_loss, r(), r(), None))
    close(*both(kernels.residual_and_loss, r(), r(), mask))
    close(*both(kernels.times_conj, x, y))
    close(*both(kernels.weighted_power, x, np.abs(r())))
    close(*both(kernels.step_and_norm, x, y))
    close(*both(kernels.field_correlation, x, y))
    close(*both(kernels.descent_point, x, y, z, 0.37))
    close(*both(kernels.momentum_point, x, y, 0.81))


@pytest.mark.parametrize("phase_scale", [3.0, 300.0, 1e5])
def test_compiled_complex_exp_is_as_exact_as_numpys(phase_scale):
    """exp(psi) in complex64 by the compiled polar loop: within 2.5e-7 of exp in complex128 (as
    NumPy's float32 exp, cos and sin are, 2.4e-7 measured) for phases to 1e5 rad, over
    several blocks and a partial one, and NaN and infinity where NumPy's pass has them."""
    rng = np.random.default_rng(3)
    shape = (301, 517)
    z = (0.5 * rng.normal(size=shape) + 1j * rng.uniform(-phase_scale, phase_scale, shape)).astype(np.complex64)
    exact = np.exp(z.astype(np.complex128))
    compiled, generic = both(kernels.complex_exp, z)
    for out in (compiled, generic):
        assert np.max(np.abs(out - exact) / np.abs(exact)) < 2.5e-7
    np.testing.assert_allclose(compiled, generic, rtol=4e-7)
    odd = np.array([np.nan, 1j * np.nan, np.inf, -np.inf, 1j * np.inf, 100.0 + 1j, 1 + 1e30j], np.complex64)
    compiled, generic = both(kernels.complex_exp, odd[:6])
    assert np.array_equal(np.isnan(compiled), np.isnan(generic))
    assert np.array_equal(np.isinf(compiled), np.isinf(generic))
    # beyond 1.6e6 rad the argument's reduction loses digits, as float32 phases have (ulp 0.125)
    assert np.isfinite(kernels.complex_exp(odd[6:])).all()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_the_diffuser_fits_passes_give_the_numpy_expressions(dtype):
    """The single-material fit's passes (calibration.diffuser): t = exp(-(kappa + i) theta)
    bitwise NumPy's complex exp in float64, its gradient's last factor and the L-BFGS update
    to rounding."""
    rng = np.random.default_rng(5)
    theta = rng.uniform(-40.0, 40.0, (67, 130)).astype(dtype)
    t, t_generic = both(kernels.single_material_transmission, theta, 0.07)
    exact = np.exp(complex(-0.07, -1.0) * theta.astype(np.float64))
    assert t.dtype == np.result_type(dtype, np.complex64)
    if dtype == np.float64:
        assert np.array_equal(t, exact) and np.array_equal(t_generic, exact)
    else:
        np.testing.assert_allclose(t, exact, rtol=2e-6)
    back = (rng.normal(size=theta.shape) + 1j * rng.normal(size=theta.shape)).astype(t.dtype)
    g, g_generic = both(kernels.single_material_gradient, back, t, 0.07, 3.0)
    np.testing.assert_allclose(g, 3.0 * np.real(np.conj(back) * complex(-0.07, -1.0) * t), rtol=1e-5, atol=1e-5)
    close(g, g_generic)
    q, x, w = (rng.normal(size=(67, 130)) for _ in range(3))
    expected = float(np.vdot(w, q - 0.3 * x))
    (q1, d1), (q2, d2) = both(lambda *a: (a[0], kernels.axpy_dot(*a)), q, -0.3, x, w)
    np.testing.assert_allclose(q1, q - 0.3 * x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(q2, q - 0.3 * x, rtol=1e-12, atol=1e-15)
    assert d1 == pytest.approx(expected, rel=1e-12) and d2 == pytest.approx(expected, rel=1e-12)


def test_fused_passes_follow_the_definitions(arrays):
    """Against the definitions written out (not just against the fallback)."""
    c, r = arrays
    x, prev, d = c(), c(), c()
    norm, overlap = kernels.field_correlation(x, prev)
    assert norm == pytest.approx(float(np.sum(np.abs(x.astype(complex)) ** 2)), rel=1e-6)
    assert overlap == pytest.approx(complex(np.vdot(prev.astype(complex), x.astype(complex))), rel=1e-6)
    phi, uphill = kernels.descent_point(x, d, prev, 0.5)
    np.testing.assert_allclose(phi, x - 0.5 * d, rtol=1e-6, atol=1e-6)
    assert uphill == pytest.approx(float(np.vdot(d.astype(complex), (phi - prev).astype(complex)).real), rel=1e-5)


def padded_problem(seed: int):
    """A 64^2 frame padded by 9 px with L1 > 0 (mask, OTF, regularizer): t, y, a start psi,
    and the model built on a given FFT."""
    n, pad = 64, 9
    rng = np.random.default_rng(seed)
    t = np.exp(0.3j * rng.normal(size=(n + 2 * pad, n + 2 * pad))).astype(np.complex64)
    y = np.zeros(t.shape, np.float32)
    y[pad : pad + n, pad : pad + n] = 0.9 + 0.2 * rng.random((n, n))
    psi = (0.01 * rng.normal(size=t.shape) + 0.1j * rng.normal(size=t.shape)).astype(np.complex64)

    def model(fft):
        return solver.build_model(
            t,
            frame_shape=(n, n),
            pixel_size_m=0.65e-6,
            wavelength=optics.wavelength_m(1e4),
            sample_diffuser_distance_m=3e-3,
            diffuser_detector_distance_m=0.02,
            coherence_length_x_m=3.47e-6,
            coherence_length_y_m=4.31e-6,
            pad=pad,
            fft=fft,
        )

    return y, psi, model


def test_the_solver_gives_the_unfused_direction_and_iterates():
    """Issue #31: the fused iteration gives the reference direction (and 30 iterations the same
    psi) to float32 tolerance, on a padded frame with L1 > 0 (mask, OTF, regularizer)."""
    y, psi, build = padded_problem(1)
    model = build(FFT.for_module(np, 1))

    def run():
        j, d, _ = solver.objective_and_direction(psi, y, model)
        return j, d, solver.pwf(y, model, max_iter=30, tol=0).psi

    (j1, d1, p1), (j0, d0, p0) = both(lambda: run())
    assert j1 == pytest.approx(j0, rel=1e-6)
    # exp(psi) differs by a float32 ulp between the two (the compiled sin and cos against
    # NumPy's), and the preconditioner lifts that rounding at the lowest frequencies: 0.9-1.2e-5
    # of the largest entry measured with pocketfft or MKL (4e-6 with one exp for both)
    np.testing.assert_allclose(d1, d0, atol=3e-5 * np.abs(d0).max())
    np.testing.assert_allclose(p1, p0, atol=1e-4 * np.abs(p0).max())


@pytest.mark.skipif(backend._mkl_scipy_fft() is None, reason="mkl_fft does not import here")
def test_the_iteration_on_mkl_transforms_gives_the_pocketfft_direction():
    """Issue #31: with MKL's FFTs (the default on Intel CPUs) the solver gives pocketfft's
    direction to float32 tolerance and, after 30 iterations, the same psi."""
    y, psi, build = padded_problem(2)
    runs = []
    for library in ("mkl", "scipy"):
        model = build(FFT.for_module(np, 1, library))
        j, d, _ = solver.objective_and_direction(psi, y, model)
        runs.append((j, d, solver.pwf(y, model, max_iter=30, tol=0).psi))
    (j1, d1, p1), (j0, d0, p0) = runs
    assert j1 == pytest.approx(j0, rel=1e-6)
    # the preconditioner (an inverse Laplacian) lifts the two libraries' float32 rounding at
    # the lowest frequencies: 1.8e-5 of the largest entry measured, psi 0.9e-5
    np.testing.assert_allclose(d1, d0, atol=3e-5 * np.abs(d0).max())
    np.testing.assert_allclose(p1, p0, atol=1e-4 * np.abs(p0).max())


@pytest.mark.gpu
@pytest.mark.parametrize("cdtype", [np.complex64, np.complex128])
def test_each_cuda_kernel_gives_the_cupy_expression(cupy, cdtype):
    """On a CUDA device each pass runs as one CuPy kernel (``kernels._CUDA_KERNELS``): it gives
    the CuPy expressions it replaces (``backend.cuda_kernels = False``) and the NumPy loops, to
    the precision's rounding (with the kernels on, whatever ``PWF_DASK_CUDA_KERNELS`` says). On
    the CPU emulator the kernels' bodies run compiled as C++ (``tests/emulated_kernels.py``)."""
    cp = cupy
    if not hasattr(cp, "ElementwiseKernel"):
        pytest.skip("no C++ compiler for the emulator's kernels")
    rng = np.random.default_rng(2)
    shape, rdtype = (67, 130), np.dtype(cdtype).type(0).real.dtype

    def c():
        return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(cdtype)

    def r():
        return rng.normal(size=shape).astype(rdtype)

    x, y, z, f, g, w = c(), c(), c(), r(), r(), np.abs(r())
    mask = (r() > 0).astype(rdtype)
    calls = [
        (kernels.intensity, (x,)),
        (kernels.residual_and_loss, (f, g, None)),
        (kernels.residual_and_loss, (f, g, mask)),
        (kernels.times_conj, (x, y)),
        (kernels.weighted_power, (x, w)),
        (kernels.descent_point, (x, y, z, 0.37)),
        (kernels.momentum_point, (x, y, 0.81)),
    ]
    tol = dict(rtol=2e-6, atol=1e-5) if cdtype is np.complex64 else dict(rtol=1e-12, atol=1e-12)

    def host(result):
        return tuple(host(a) for a in result) if isinstance(result, tuple) else cp.asnumpy(cp.asarray(result))

    def on_device(fn, args, fused: bool):
        saved, backend.cuda_kernels = backend.cuda_kernels, fused
        try:
            return host(fn(*[cp.asarray(a) if isinstance(a, np.ndarray) else a for a in args]))
        finally:
            backend.cuda_kernels = saved

    for fn, args in calls:
        fused, plain = on_device(fn, args, True), on_device(fn, args, False)
        on_cpu = fn(*[a.copy() if isinstance(a, np.ndarray) else a for a in args])
        for a, b, h in zip(*(v if isinstance(v, tuple) else (v,) for v in (fused, plain, on_cpu))):
            np.testing.assert_allclose(a, b, **tol, err_msg=fn.__name__)
            np.testing.assert_allclose(a, np.asarray(h), **tol, err_msg=fn.__name__)
        assert type(fused) is type(plain)
