"""Algorithms S1/S2 of the paper transcribed line by line, with plain NumPy/CuPy expressions.

The oracle the solver's direction is tested against (tests/test_solver.py) and the "as printed"
baseline the iteration benchmark times beside the solver (:mod:`benchmarks.speed`).
"""

from __future__ import annotations

import math

from pwf_dask.backend import FFT
from pwf_dask.physics import optics
from pwf_dask.pwf import solver


def _filter(a, transfer, fft: FFT):
    """``Filter`` of Algorithm S2: F^-1{F{a} W}, complex FFTs as printed."""
    return fft.ifft2(fft.fft2(a) * transfer)


def algorithm_s1_direction(psi, y, *, t, kernel1, kernel2, iotf, precond, reg_window, alpha, norm, fft: FFT):
    """Algorithm S2 transcribed line by line: ``Preconditioner(g) + Regularizer(psi)``.

    The straightforward port that :func:`iteration_benchmark` times beside the solver: 16
    complex FFTs (14 with L1 = 0) and one unfused array pass per printed operation, as the
    authors' released code does it. Full-plane filters; ``kernel1`` None for L1 = 0. The
    solver gives the same direction (test) with about 12 complex-FFT equivalents (8 with
    L1 = 0: real FFTs for real images, the phase filters summed in one spectrum) and fused
    in-place passes.
    """
    xp = fft.xp
    # PhysicalModel
    x = xp.exp(psi)
    v = x if kernel1 is None else _filter(x, kernel1, fft)
    v = _filter(t * v, kernel2, fft)
    f = _filter(xp.abs(v) ** 2, iotf, fft).real
    e = y - f
    # WirtingerDerivative
    g = _filter(-e, iotf, fft)
    g = _filter(v * g, xp.conj(kernel2), fft)
    g = xp.conj(t) * g
    if kernel1 is not None:
        g = _filter(g, xp.conj(kernel1), fft)
    g = xp.conj(x) * g
    g = g / norm
    # Preconditioner
    g = g.real + 1j * _filter(g.imag, precond, fft).real
    # Regularizer
    rho = _filter(psi, reg_window, fft)
    return g + (alpha.real * rho.real + 1j * alpha.imag * rho.imag)


def algorithm_s1_step(psi, phi_prev, mu: float, eta: float, y, **model) -> tuple:
    """One pass of Algorithm S1's loop (lines 6-14) with :func:`algorithm_s1_direction`."""
    phi = psi - eta * algorithm_s1_direction(psi, y, **model)
    mu_next = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * mu * mu))
    return phi + ((mu - 1.0) / mu_next) * (phi - phi_prev), phi, mu_next


def algorithm_s1_inputs(
    model: solver.PWFModel,
    pixel_size_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    gamma: float = 1.0,
) -> dict:
    """The full-plane inputs of Algorithm S1 for the geometry of a solver ``model``."""
    xp, shape, rdt = model.xp, model.shape, model.rdtype
    return dict(
        t=model.t,
        kernel1=model.kernel1,
        kernel2=model.kernel2,
        iotf=optics.iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, xp, rdt, half=False),
        precond=optics.preconditioner(shape, xp, rdt, half=False),
        reg_window=optics.regularization_window(
            shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, gamma, xp, rdt, half=False
        ),
        alpha=model.alpha,
        norm=model.norm,
        fft=model.fft,
    )
