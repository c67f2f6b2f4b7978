"""Fused element-wise passes of the PWF iteration (Algorithm S1 and S2), one memory pass each.

Written once in array-module terms (:func:`_generic`: NumPy or CuPy expressions) and, on the
CPU, once more as a compiled loop (numba) that reads each operand once and writes each result
once. NumPy evaluates ``(f - y) * mask`` and its sum of squares as four passes with two
temporaries; at 1024^2 and above each pass costs as much as a fifth of an FFT, and an iteration
had about thirty of them (issue #31). The compiled loops accumulate sums in float64, as
:func:`pwf_dask.backend.inner` does, so they agree with the NumPy expressions to float32
rounding (``tests/test_kernels.py``). On a CUDA device the same loops are written as CuPy
element-wise and reduction kernels (:data:`_CUDA_KERNELS`, compiled on first use; opt-in with
``PWF_DASK_CUDA_KERNELS=1``, :data:`pwf_dask.backend.cuda_kernels`): CuPy runs each NumPy
operation as its own kernel, so ``(f - y) * mask`` and its sum of squares cost four launches and
four memory passes there too, and the launches, not the bandwidth, bound an iteration below
about 1024^2 (issue #31: 1.8 ms at 512^2 against a 0.03 ms FFT on an H100). The tests' CPU
emulator of CuPy (``tests/emulated_cupy.py``) runs these kernels' bodies compiled as C++.

Each function names the paper's quantity it computes:

- :func:`complex_exp` exp(psi), the sample's field (Eq. forwardModel),
- :func:`intensity` |v|^2 (Eq. forwardModel's modulus),
- :func:`residual_and_loss` e = (f - y) M and L = sum e^2 (Eq. lossFunction),
- :func:`times_conj` c conj(x) (the last factor of the Wirtinger derivative, Algorithm S2),
- :func:`weighted_power` sum w |a|^2 (the regularizer's Parseval sum),
- :func:`step_and_norm` psi_k - psi_{k-1} and its squared norm (the stop rule's step),
- :func:`field_correlation` |x|^2 and <x_prev, x> (the paper's stop rule),
- :func:`descent_point` phi = psi - eta d and Re<d, phi - phi_prev> (Algorithm S1, line 12,
  and the gradient restart's test),
- :func:`momentum_point` phi + beta (phi - phi_prev) (Algorithm S1, line 14).

and of the single-material diffuser's fit (:func:`pwf_dask.calibration.single_material_diffuser`,
once per diffuser position, float64):

- :func:`single_material_transmission` t_r = exp(-(kappa + i) theta_r),
- :func:`single_material_gradient` the last factor of the fit's gradient, Re(c conj(back) t),
- :func:`axpy_dot` an update of L-BFGS's two-loop recursion and the next inner product.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pwf_dask import backend
from pwf_dask.backend import elementwise_pool, get_array_module

#: the numba module once imported (on first use: it costs half a second), or None where it is
#: missing (a bare source checkout: NumPy's passes are used); tests set None to compare
numba: Any = ...
_COMPILED: dict = {}


def _numba():
    global numba
    if numba is ...:
        try:
            import numba as module
        except ImportError:  # pragma: no cover
            module = None
        numba = module
    return numba


def _jit(name: str):
    """The compiled loop ``name``, built on first use and cached on disk by numba. Sums may be
    reassociated (``reassoc``: the float64 accumulations vectorize, 2-4x faster than strictly
    in order), but infinities and NaNs keep their meaning: an overflowing trial step must still
    give J = inf."""
    if name not in _COMPILED:
        flags = _FASTMATH.get(name, {"reassoc", "contract"})
        _COMPILED[name] = _numba().njit(_LOOPS[name], nogil=True, cache=True, fastmath=flags)
    return _COMPILED[name]


def _cpu(*arrays) -> bool:
    return all(isinstance(a, np.ndarray) and a.flags.c_contiguous for a in arrays) and _numba() is not None


_CUDA_COMPILED: dict = {}


def _cuda(*arrays):
    """The CuPy module where every array is a CuPy array (of a CUDA device, or of the tests'
    emulator, which compiles the kernels as C++) and the kernels are on, else None."""
    if not backend.cuda_kernels or any(isinstance(a, np.ndarray) for a in arrays):
        return None
    xp = get_array_module(*arrays)
    return xp if xp is not np and hasattr(xp, "ElementwiseKernel") else None


def _cuda_kernel(xp, name: str):
    """The CUDA kernel ``name`` of :data:`_CUDA_KERNELS`, built once per process and CuPy
    module (the tests' emulator is another module). Complex operands are CuPy's
    ``complex<float|double>``; sums are accumulated in double, as the numba loops do."""
    if (xp, name) not in _CUDA_COMPILED:
        kind, *spec = _CUDA_KERNELS[name]
        if kind == "map":
            kernel = xp.ElementwiseKernel(*spec, name=f"pwf_{name}")
        else:
            kernel = xp.ReductionKernel(*spec, name=f"pwf_{name}", reduce_type="double")
        _CUDA_COMPILED[(xp, name)] = kernel
    return _CUDA_COMPILED[(xp, name)]


def _cuda_sum(xp, name: str, *arrays, host: bool = True) -> float:
    """The reduction kernel ``name`` over all of ``arrays``, as a float. CuPy launches one block
    per output element of a reduction kernel: a sum to one scalar ran on one block of one
    multiprocessor, 1-2 ms a pass at 2160 x 2560 (an H200, session 48: the kernels made an
    iteration 3.7 -> 13.1 ms). Each row is reduced by a block of its own, and the row totals
    by CuPy's sum. ``host=False``: the sum stays on the device, a 0-d array."""
    kernel = _cuda_kernel(xp, name)
    total = kernel(*arrays) if arrays[0].ndim < 2 else kernel(*arrays, axis=-1).sum()
    return float(total) if host else total


# --- the compiled loops: flat, contiguous operands --------------------------------------------


def _polar_loop(magnitude, z, out):
    """out = magnitude (cos Im z + i sin Im z), z and out complex64 seen as float32 (Re, Im
    interleaved). sin and cos in float64: the argument reduced to r in [-pi/4, pi/4] by
    n pi/2 in two parts (Cody and Waite; the first has 33 bits, so n times it is exact for
    |n| < 2^20, 1.6e6 rad), then Taylor polynomials to r^11 and r^12 (truncation under 1e-11),
    the quadrant's swap and signs as selects: the loop vectorizes (2.8 ns an element with AVX2,
    against 3.7 for NumPy's float32 cos and sin alone)."""
    for i in range(magnitude.size):
        x = np.float64(z[2 * i + 1])
        n = np.floor(x * 0.6366197723675814 + 0.5)
        r = (x - n * 1.5707963267341256) - n * 6.077100506506192e-11
        # past 2^20 quadrants r holds rounding only: kept on the polynomials' interval, so the
        # result stays bounded as NumPy's is (NaN passes both tests)
        r = 0.8 if r > 0.8 else r
        r = -0.8 if r < -0.8 else r
        r2 = r * r
        s = r + r * r2 * (-1.0 / 6 + r2 * (1.0 / 120 + r2 * (-1.0 / 5040 + r2 * (1.0 / 362880 - r2 / 39916800))))
        c = 1.0 + r2 * (
            -0.5 + r2 * (1.0 / 24 + r2 * (-1.0 / 720 + r2 * (1.0 / 40320 + r2 * (-1.0 / 3628800 + r2 / 479001600))))
        )
        quadrant = np.int32(n) & 3
        sin_x = c if quadrant & 1 else s
        cos_x = s if quadrant & 1 else c
        sin_x = -sin_x if quadrant & 2 else sin_x
        cos_x = -cos_x if (quadrant + 1) & 2 else cos_x
        m = np.float64(magnitude[i])
        out[2 * i] = np.float32(m * cos_x)
        out[2 * i + 1] = np.float32(m * sin_x)


def _intensity_loop(v, out):
    for i in range(v.size):
        z = v[i]
        out[i] = z.real * z.real + z.imag * z.imag


def _residual_loop(f, y, out):
    total = 0.0
    for i in range(f.size):
        e = f[i] - y[i]
        out[i] = e
        total += np.float64(e) * e
    return total


def _residual_masked_loop(f, y, mask, out):
    total = 0.0
    for i in range(f.size):
        e = (f[i] - y[i]) * mask[i]
        out[i] = e
        total += np.float64(e) * e
    return total


def _times_conj_loop(c, x):
    for i in range(c.size):
        c[i] = c[i] * np.conj(x[i])


def _weighted_power_loop(a, w):
    total = 0.0
    for i in range(a.size):
        z = a[i]
        total += np.float64(w[i]) * (np.float64(z.real) * z.real + np.float64(z.imag) * z.imag)
    return total


def _step_loop(psi, last, out):
    total = 0.0
    for i in range(psi.size):
        s = psi[i] - last[i]
        out[i] = s
        total += np.float64(s.real) * s.real + np.float64(s.imag) * s.imag
    return total


def _correlation_loop(x, prev):
    norm = 0.0
    re = 0.0
    im = 0.0
    for i in range(x.size):
        a = x[i]
        b = prev[i]
        norm += np.float64(a.real) * a.real + np.float64(a.imag) * a.imag
        # conj(b) a
        re += np.float64(b.real) * a.real + np.float64(b.imag) * a.imag
        im += np.float64(b.real) * a.imag - np.float64(b.imag) * a.real
    return norm, re, im


def _descent_loop(psi, d, phi_prev, eta, out):
    total = 0.0
    for i in range(psi.size):
        p = psi[i] - eta * d[i]
        out[i] = p
        s = p - phi_prev[i]
        g = d[i]
        total += np.float64(g.real) * s.real + np.float64(g.imag) * s.imag
    return total


def _momentum_loop(phi, phi_prev, beta, out):
    for i in range(phi.size):
        p = phi[i]
        out[i] = p + beta * (p - phi_prev[i])


def _single_material_loop(theta, kappa, out):
    """out = exp(-(kappa + i) theta) = exp(-kappa theta) (cos theta - i sin theta), by the same
    exp, cos and sin as NumPy's complex exp of -(kappa + i) theta (bitwise the same result),
    without the complex argument's array and its strided exp."""
    for i in range(theta.size):
        x = theta[i]
        m = np.exp(-kappa * x)
        out[i] = complex(m * np.cos(x), -(m * np.sin(x)))


def _axpy_dot_loop(q, alpha, x, w):
    total = 0.0
    for i in range(q.size):
        v = q[i] + alpha * x[i]
        q[i] = v
        total += np.float64(w[i]) * v
    return total


def _single_material_gradient_loop(back, t, kappa, scale, out):
    for i in range(back.size):
        b = back[i]
        z = t[i]
        # conj(b) z, then Re(c conj(b) z) with c = -(kappa + i)
        re = b.real * z.real + b.imag * z.imag
        im = b.real * z.imag - b.imag * z.real
        out[i] = scale * (im - kappa * re)


#: the loops above as CUDA kernels: ("map", in, out, body) for ``ElementwiseKernel`` or
#: ("sum", in, out, map_expr, reduce_expr, post_map_expr, identity) for ``ReductionKernel``
_CUDA_KERNELS = {
    "intensity": ("map", "T v", "R power", "power = v.real() * v.real() + v.imag() * v.imag()"),
    "residual_masked": ("map", "T f, T y, M mask", "T e", "e = (f - y) * static_cast<T>(mask)"),
    # a reduction's operand names must not occur inside other words of its expressions: CuPy's
    # CUB path renames a single operand by plain text replacement ("e" of "double" too)
    "sum_sq": ("sum", "T sq_x", "float64 sq_total", "double(sq_x) * double(sq_x)", "a + b", "sq_total = a", "0"),
    "times_conj": ("map", "T x", "T c", "c = c * conj(x)"),
    "weighted_power": (
        "sum",
        "T wp_z, R wp_w",
        "float64 wp_total",
        "double(wp_w) * (double(wp_z.real()) * wp_z.real() + double(wp_z.imag()) * wp_z.imag())",
        "a + b",
        "wp_total = a",
        "0",
    ),
    # scalars are typed by the arrays (T): CuPy infers no placeholder from a scalar alone
    "descent": ("map", "T psi, T d, T eta", "T phi", "phi = psi - eta * d"),
    # Re<d, phi - phi_prev>
    "uphill": (
        "sum",
        "T up_d, T up_phi, T up_prev",
        "float64 up_total",
        "double(up_d.real()) * (up_phi.real() - up_prev.real())"
        " + double(up_d.imag()) * (up_phi.imag() - up_prev.imag())",
        "a + b",
        "up_total = a",
        "0",
    ),
    "momentum": ("map", "T phi, T prev, T beta", "T point", "point = phi + beta * (phi - prev)"),
}

_LOOPS = {
    "polar": _polar_loop,
    "intensity": _intensity_loop,
    "residual": _residual_loop,
    "residual_masked": _residual_masked_loop,
    "times_conj": _times_conj_loop,
    "weighted_power": _weighted_power_loop,
    "step": _step_loop,
    "correlation": _correlation_loop,
    "descent": _descent_loop,
    "momentum": _momentum_loop,
    "single_material": _single_material_loop,
    "axpy_dot": _axpy_dot_loop,
    "single_material_gradient": _single_material_gradient_loop,
}


#: fast-math flags of the loops that differ from the sums' ``reassoc`` and ``contract``: the
#: argument reduction of :func:`_polar_loop` needs its subtractions in the order written
_FASTMATH = {"polar": {"contract"}, "single_material": set()}


def _number(total, host: bool):
    """A 0-d sum as a float, or as it is (on its device) where ``host`` is False."""
    return float(total) if host else total


def _flat(*arrays):
    return [a.reshape(-1) for a in arrays]


# --- the passes ------------------------------------------------------------------------------


#: elements per block of :func:`_complex_exp_into`: its float buffers stay in L2 cache
_EXP_BLOCK = 1 << 16


def _complex_exp_into(z, out) -> None:
    """out = exp(Re z) (cos Im z + i sin Im z), block by block.

    NumPy's SIMD exp/cos/sin loops need contiguous operands: on the interleaved Re/Im views
    they take the strided scalar path (exp 6x, cos 2x slower at 2048^2 here). Each block's
    real part is copied into a small contiguous buffer and exponentiated there, in cache. For
    complex64 the compiled :func:`_polar_loop` then forms cos and sin of the imaginary part and
    both products in one pass (NumPy's float32 cos and sin cost 1.8 ns an element each on an
    AMD EPYC with AVX2; the pass, session 50: 7.6 -> 6.2 ms at 1024^2 and 34 -> 23 ms at 2048^2
    on one thread, 1.7x on two), within 2.5e-7 of exp in complex128 as NumPy's pass is
    (``tests/test_kernels.py``). Otherwise (complex128, or no numba) NumPy's cos and sin on a
    contiguous copy of the imaginary part.
    """
    fz, fo = z.reshape(-1), out.reshape(-1)
    size = min(_EXP_BLOCK, fz.size)
    compiled = z.dtype == np.complex64 and _numba() is not None
    mag = np.empty(size, dtype=z.real.dtype)
    if compiled:
        polar, zf, of = _jit("polar"), fz.view(np.float32), fo.view(np.float32)
    else:
        arg, trig = np.empty_like(mag), np.empty_like(mag)
    for start in range(0, fz.size, size):
        zb, ob = fz[start : start + size], fo[start : start + size]
        m = mag[: zb.size]
        np.copyto(m, zb.real)
        np.exp(m, out=m)
        if compiled:
            polar(m, zf[2 * start : 2 * (start + zb.size)], of[2 * start : 2 * (start + zb.size)])
            continue
        a, c = arg[: zb.size], trig[: zb.size]
        np.copyto(a, zb.imag)
        np.cos(a, out=c)
        np.multiply(m, c, out=ob.real)
        np.sin(a, out=c)
        np.multiply(m, c, out=ob.imag)


def complex_exp(z, workers: int = 1):
    """exp(z) of a complex array: the sample's field exp(psi) of Eq. (forwardModel). NumPy's
    complex64 exp is ~10x slower than exp(Re) (cos, sin) of the float32 parts
    (:func:`_complex_exp_into`); CuPy's fused kernel is used as is.

    On the CPU, ``workers`` > 1 splits the rows over that many threads (NumPy and the compiled
    loop release the GIL): this is the costliest element-wise pass of an iteration and the
    FFTs beside it already use ``workers`` threads. Each element is computed by the same code
    either way, so the result is bitwise the same.
    """
    xp = get_array_module(z)
    if xp is not np:
        return xp.exp(z)
    z = np.ascontiguousarray(z)  # the blocks are runs of the flat array (_complex_exp_into)
    out = np.empty(z.shape, dtype=z.dtype)
    blocks = min(int(workers), z.shape[0]) if z.ndim >= 1 else 1
    if blocks <= 1 or z.size < 1 << 16:
        _complex_exp_into(z, out)
        return out
    edges = [z.shape[0] * i // blocks for i in range(blocks + 1)]
    pool = elementwise_pool()
    jobs = [pool.submit(_complex_exp_into, z[a:b], out[a:b]) for a, b in zip(edges[:-1], edges[1:])]
    for job in jobs:
        job.result()
    return out


def intensity(v):
    """|v|^2 of a complex array, as a real array of its precision."""
    if _cpu(v):
        out = np.empty(v.shape, dtype=v.real.dtype)
        _jit("intensity")(*_flat(v, out))
        return out
    xp = _cuda(v)
    if xp is not None:
        out = xp.empty(v.shape, dtype=v.real.dtype)
        _cuda_kernel(xp, "intensity")(v, out)
        return out
    xp = get_array_module(v)
    out = xp.square(v.real)
    out += xp.square(v.imag)
    return out


def residual_and_loss(f, y, mask=None, host: bool = True):
    """e = (f - y) M (M: 1 on measured pixels, 0 elsewhere; None: all measured) and
    L = sum e^2, summed in float64. This and the other sums below take ``host=False`` to leave
    a device's sum there as a 0-d array (:func:`pwf_dask.backend.host_numbers` fetches an
    iteration's sums at once); on the CPU they are numbers either way."""
    if _cpu(f, y) and (mask is None or _cpu(mask)) and f.dtype == y.dtype:
        out = np.empty(f.shape, dtype=f.dtype)
        if mask is None:
            loss = _jit("residual")(*_flat(f, y, out))
        else:
            loss = _jit("residual_masked")(*_flat(f, y, mask.astype(f.dtype, copy=False), out))
        return out, float(loss)
    xp = _cuda(f, y)
    if xp is not None and f.dtype == y.dtype:
        r = f - y if mask is None else _cuda_kernel(xp, "residual_masked")(f, y, mask)
        return r, _cuda_sum(xp, "sum_sq", r, host=host)
    xp = get_array_module(f)
    r = f - y
    if mask is not None:
        r *= mask
    return r, _number(xp.sum(r * r, dtype=np.float64), host)


def times_conj(c, x):
    """c conj(x), in c's memory."""
    if _cpu(c, x) and c.dtype == x.dtype:
        _jit("times_conj")(*_flat(c, x))
        return c
    xp = _cuda(c, x)
    if xp is not None and c.dtype == x.dtype:
        _cuda_kernel(xp, "times_conj")(x, c)
        return c
    xp = get_array_module(c)
    c *= xp.conj(x)
    return c


def weighted_power(a, w, host: bool = True) -> float:
    """sum w |a|^2 (w real, a's shape), in float64."""
    if _cpu(a, w) and a.shape == w.shape:
        return float(_jit("weighted_power")(*_flat(a, w)))
    xp = _cuda(a, w)
    if xp is not None and a.shape == w.shape:
        return _cuda_sum(xp, "weighted_power", a, w, host=host)
    xp = get_array_module(a)
    power = xp.square(a.real) + xp.square(a.imag)
    power *= w
    return _number(xp.sum(power, dtype=np.float64), host)


def step_and_norm(psi, last, host: bool = True):
    """(psi - last, |psi - last|^2)."""
    if _cpu(psi, last) and psi.dtype == last.dtype:
        out = np.empty_like(psi)
        return out, float(_jit("step")(*_flat(psi, last, out)))
    from pwf_dask.backend import inner

    s = psi - last
    return s, inner(s, s, host).real


def field_correlation(x, prev, host: bool = True) -> tuple[float, complex]:
    """(|x|^2, <prev, x> = sum conj(prev) x), in float64: the stop rule's field correlation."""
    if _cpu(x, prev) and x.dtype == prev.dtype:
        norm, re, im = _jit("correlation")(*_flat(x, prev))
        return float(norm), complex(re, im)
    from pwf_dask.backend import inner

    return inner(x, x, host).real, inner(prev, x, host)


def descent_point(psi, d, phi_prev, eta: float, host: bool = True):
    """(phi = psi - eta d, Re<d, phi - phi_prev>)."""
    if _cpu(psi, d, phi_prev) and psi.dtype == d.dtype == phi_prev.dtype:
        out = np.empty_like(psi)
        uphill = _jit("descent")(*_flat(psi, d, phi_prev), psi.real.dtype.type(eta), _flat(out)[0])
        return out, float(uphill)
    xp = _cuda(psi, d, phi_prev)
    if xp is not None and psi.dtype == d.dtype == phi_prev.dtype:
        phi = _cuda_kernel(xp, "descent")(psi, d, psi.dtype.type(eta))
        return phi, _cuda_sum(xp, "uphill", d, phi, phi_prev, host=host)
    from pwf_dask.backend import inner

    phi = d * (-eta)
    phi += psi
    return phi, inner(d, phi - phi_prev, host).real


def momentum_point(phi, phi_prev, beta: float):
    """phi + beta (phi - phi_prev), a new array."""
    if _cpu(phi, phi_prev) and phi.dtype == phi_prev.dtype:
        out = np.empty_like(phi)
        _jit("momentum")(*_flat(phi, phi_prev), phi.real.dtype.type(beta), _flat(out)[0])
        return out
    xp = _cuda(phi, phi_prev)
    if xp is not None and phi.dtype == phi_prev.dtype:
        return _cuda_kernel(xp, "momentum")(phi, phi_prev, phi.dtype.type(beta))
    out = phi - phi_prev
    out *= beta
    out += phi
    return out


# --- the single-material diffuser's fit (pwf_dask.calibration.diffuser) ------------------------
# Run once per diffuser position, in float64, but an eighth of one projection's retrieval
# before these passes (issue #31's 10 %): NumPy's complex exp of -(kappa + i) theta alone cost
# 1.7 FFT-times of its 1080^2 grid, and the gradient's conj(back) c t three passes.


def single_material_transmission(theta, kappa: float):
    """t = exp(-(kappa + i) theta), the transmission of a single-material object of phase
    delay theta (real) and kappa = beta / delta: :func:`pwf_dask.calibration.single_material_diffuser`."""
    if _cpu(theta) and theta.dtype in (np.float32, np.float64):
        out = np.empty(theta.shape, dtype=np.result_type(theta.dtype, np.complex64))
        _jit("single_material")(_flat(theta)[0], theta.dtype.type(kappa), _flat(out)[0])
        return out
    xp = get_array_module(theta)
    return xp.exp(complex(-kappa, -1.0) * theta)


def single_material_gradient(back, t, kappa: float, scale: float):
    """scale Re(c conj(back) t), c = -(kappa + i): the derivative of a misfit in theta through
    t = exp(c theta), given back = dL/d conj(t) up to ``scale`` (the chain rule's last factor)."""
    if _cpu(back, t) and back.dtype == t.dtype:
        out = np.empty(t.shape, dtype=t.real.dtype)
        real = t.real.dtype.type
        _jit("single_material_gradient")(*_flat(back, t), real(kappa), real(scale), _flat(out)[0])
        return out
    xp = get_array_module(t)
    p = xp.conj(back) * t
    out = p.imag - kappa * p.real
    out *= scale
    return out


def axpy_dot(q, alpha: float, x, w) -> float:
    """q += alpha x in q's memory, then <w, q> in float64, in one pass on the CPU: the two-loop
    recursion of L-BFGS (:func:`pwf_dask.calibration.diffuser._lbfgs`, real arrays) is a chain of
    these, each update followed by the next pair's inner product with q."""
    if _cpu(q, x, w) and q.dtype == x.dtype == w.dtype == np.float64:
        return float(_jit("axpy_dot")(*_flat(q), alpha, *_flat(x, w)))
    xp = get_array_module(q)
    q += alpha * x
    return float(xp.vdot(w, q))
