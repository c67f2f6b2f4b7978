"""Algorithm S2 of the paper: the physical model, the Wirtinger derivative, the preconditioned
direction and the regularizer of PWF, and the curvature that sets the first step.

The unknown is the complex phase psi = log x of the sample field (Re psi = -attenuation,
Im psi = unwrapped phase). The physical model, Eq. (forwardModel), is

    f(psi) = | P2{ t P1{ exp psi } } |^2 * IPSF,

and PWF minimises Eq. (lossFunction), sum_r (y_r - f_r)^2, by Nesterov-accelerated
Wirtinger flow with the inverse-Laplacian preconditioner on Im(g) and the Tikhonov
regularizer Re(alpha) Gamma^2 Re(psi) + i Im(alpha) Gamma^2 Im(psi) (Algorithm S2).

One observation makes the iteration safe to automate. Algorithm S1's update
``psi <- psi - eta (Precond(g) + Reg(psi))`` is exactly preconditioned gradient descent,
psi <- psi - eta M grad J, with the metric M = diag(1 on Re psi, P^-1 on Im psi) and the objective

    J(psi) = L(psi) / (4 N_t) + 1/2 Re(alpha) <Re psi, Gamma^2 Re psi>
                               + 1/2 Im(alpha) <Im psi, (u^2+v^2) Gamma^2 Im psi>,

because P^-1 (u^2+v^2) = 1 away from DC. (Without the preconditioner the last weight is
Gamma^2 alone.) J is a real objective, so its value at every iterate can decide two things
the paper leaves to hand tuning: an adaptive momentum restart (O'Donoghue & Candes 2015;
see :func:`~pwf_dask.pwf.solver.pwf`), and a halved step when J rises after a plain gradient step
(backtracking). Gradient steps are then monotone in J; the paper's
normalisation 1/max|t|^2 with eta = 1 can no longer run to NaN.

N_t = max_r |t_r|^2 (``normalization="paper"``, Algorithm S2 as printed, the default) or
(max_r |t_r|^2)^2 (``"released"``, the authors' released code). Images are normalised to a
mean reference of 1 first, so either is scale-free. The paper's form with eta = 1 runs to NaN
in ~50 iterations when iterated blindly; here the backtracking halves eta instead. N_t sets
the balance between data and regularizer: on our realistic scenes the released form makes
Re(alpha) = 0.1 damp the attenuation (gain 0.78), the printed form gives gains within 3 %
(docs/validation.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pwf_dask.backend import FFT, host_numbers, inner
from pwf_dask.physics import optics
from pwf_dask.pwf import kernels
from pwf_dask.pwf.model import (
    PWFModel,
    _crop_spectrum,
    _half_weights,
    _pad_spectrum,
    interpolate_field,
    restrict_field,
)

#: Hessian-vector products in :func:`largest_curvature`, the rms of their probe step, and
#: the most any pixel of the probe may move psi (exp(psi) linear to ~2.5 %)
CURVATURE_ITERATIONS = 8
CURVATURE_PROBE_RMS = 1e-2
CURVATURE_PROBE_MAX = 5e-2


# --- Algorithm S2 -----------------------------------------------------------------------


def _propagate(a, kernel, fft: FFT, overwrite: bool):
    """F^-1{F{a} kernel}, in a's memory when ``overwrite`` (the caller no longer needs a)."""
    spec = fft.fft2(a, overwrite=overwrite)
    spec *= kernel
    return fft.ifft2(spec, overwrite=True)


def _filter_real(a, transfer_half, fft: FFT):
    """F^-1{F{a} W} of a real image with a real transfer function on the rfft half plane."""
    spec = fft.rfft2(a)
    spec *= transfer_half
    return fft.irfft2(spec, s=a.shape, overwrite=True)


@dataclass
class Evaluation:
    """Model state at one psi: field x, detector field v, model intensity f, residual r."""

    x: Any
    v: Any
    f: Any
    r: Any
    loss: float


def physical_model(psi, model: PWFModel) -> Evaluation:
    """``PhysicalModel`` of Algorithm S2: f = |P2{t P1{exp psi}}|^2 * IPSF (Eq. forwardModel).

    Returns the intermediate fields the Wirtinger derivative reuses. With ``upsample`` s > 1
    the detector field's spectrum is zero-padded to an s-times finer grid, squared there, and
    band-limited back, which equals the exact |v|^2 filtered by the IOTF (no aliasing).
    """
    fft = model.fft
    if model.field_upsample > 1:
        fine = model.field_shape
        if model.sample_field_grid == "detector":
            x = kernels.complex_exp(psi, fft.workers)
            a = _interpolate_and_propagate(x, model.kernel1, fine, fft)
        else:
            x = kernels.complex_exp(interpolate_field(psi, fine, fft), fft.workers)
            a = x if model.kernel1 is None else _propagate(x, model.kernel1, fft, overwrite=False)
        v = _propagate(model.t * a, model.kernel2, fft, overwrite=True)
        spec_i = _crop_spectrum(fft.rfft2(kernels.intensity(v)), model.shape, half=True)
        if model.otf is not None:
            spec_i *= model.otf
        f = fft.irfft2(spec_i, s=model.shape, overwrite=True)
        f *= (model.shape[0] * model.shape[1]) / (fine[0] * fine[1])
        return Evaluation(x=x, v=v, f=f.astype(model.rdtype, copy=False), r=None, loss=math.nan)
    x = kernels.complex_exp(psi, fft.workers)
    if model.kernel1 is None:
        a = model.t * x
    else:
        a = _propagate(x, model.kernel1, fft, overwrite=False)
        a *= model.t
    spec = fft.fft2(a, overwrite=True)
    spec *= model.kernel2
    s = model.upsample
    if s == 1:
        v = fft.ifft2(spec, overwrite=True)
        intensity = kernels.intensity(v)
        f = intensity if model.otf is None else _filter_real(intensity, model.otf, fft)
    else:
        fine = (model.shape[0] * s, model.shape[1] * s)
        v = fft.ifft2(_pad_spectrum(spec, fine, half=False), overwrite=True)
        v *= s * s
        intensity = kernels.intensity(v)
        spec_i = _crop_spectrum(fft.rfft2(intensity), model.shape, half=True)
        if model.otf is not None:
            spec_i *= model.otf
        f = fft.irfft2(spec_i, s=model.shape, overwrite=True)
        f *= 1.0 / (s * s)
    return Evaluation(x=x, v=v, f=f.astype(model.rdtype, copy=False), r=None, loss=math.nan)


def residual(ev: Evaluation, y, model: PWFModel, host: bool = True) -> Evaluation:
    """e = f - y on measured pixels (the paper's e_r = y_r - f_r with the sign folded in);
    ``host=False`` leaves the loss on psi's device (``kernels.residual_and_loss``)."""
    ev.r, ev.loss = kernels.residual_and_loss(ev.f, y, model.mask, host)
    return ev


def wirtinger_derivative(ev: Evaluation, model: PWFModel):
    """``WirtingerDerivative`` of Algorithm S2: g = conj(x) P1^H{conj(t) P2^H{v IOTF*(f - y)}} / N_t.

    g = dJ_data/dRe(psi) + i dJ_data/dIm(psi) for J_data = L / (4 N_t), L of Eq. (lossFunction).
    """
    fft = model.fft
    r = ev.r
    if model.upsample == 1 and model.field_upsample == 1:
        w = r if model.otf is None else _filter_real(r, model.otf, fft)
        spec = fft.fft2(ev.v * w, overwrite=True)
    else:
        s = model.upsample
        fine = model.field_shape if model.field_upsample > 1 else (model.shape[0] * s, model.shape[1] * s)
        rs = fft.rfft2(r)
        if model.otf is not None:
            rs *= model.otf
        w = fft.irfft2(_pad_spectrum(rs, fine, half=True, coarse_nx=model.shape[1]), s=fine, overwrite=True)
        spec = fft.fft2(ev.v * w, overwrite=True)
        if model.field_upsample == 1:
            spec = _crop_spectrum(spec, model.shape, half=False)
    spec *= model.kernel2_conj
    c = fft.ifft2(spec, overwrite=True)
    c *= model.t_conj
    if model.field_upsample > 1 and model.sample_field_grid == "detector":
        c = _propagate_and_restrict(c, model.kernel1_conj, model.shape, fft)
        return kernels.times_conj(c, ev.x).astype(model.cdtype, copy=False)
    if model.kernel1 is not None:
        c = _propagate(c, model.kernel1_conj, fft, overwrite=True)
    c = kernels.times_conj(c, ev.x)
    g = c if model.field_upsample == 1 else restrict_field(c, model.shape, fft)
    return g.astype(model.cdtype, copy=False)


def _interpolate_and_propagate(x, kernel, fine_shape, fft: FFT):
    """P1 U x: x's detector-grid spectrum zero-padded onto the field grid, times P1's kernel
    (None: L1 = 0), one inverse transform there (``sample_field_grid="detector"``)."""
    spec = fft.fft2(x)
    spec *= (fine_shape[0] * fine_shape[1]) / (x.shape[0] * x.shape[1])  # on the smaller grid
    spec = _pad_spectrum(spec, fine_shape, half=False)
    if kernel is not None:
        spec *= kernel
    return fft.ifft2(spec, overwrite=True)


def _propagate_and_restrict(c, kernel_conj, coarse_shape, fft: FFT):
    """U^H P1^H c, the adjoint of :func:`_interpolate_and_propagate` (c's memory reused)."""
    spec = fft.fft2(c, overwrite=True)
    if kernel_conj is not None:
        spec *= kernel_conj
    return fft.ifft2(_crop_spectrum(spec, coarse_shape, half=False), overwrite=True)


def _regularizer(psi, model: PWFModel):
    """The regularizer's Parseval sums and the spectra of its direction terms.

    Returns (powers, re_term, im_term): powers the sums w |rfft(part)|^2 of psi's parts that
    the regularizer weighs (on psi's device; :func:`_regularizer_sum` makes them J's term, by
    Parseval on rfft spectra: module docstring), re_term = Re(alpha) Gamma^2 rfft(Re psi) and
    im_term = Im(alpha) Gamma^2 rfft(Im psi), or None where that part of alpha is 0 (no FFT is
    spent on it).
    """
    if model.reg_window is None:
        return [], None, None
    xp, fft = model.xp, model.fft
    powers = []
    terms = []
    for part, term in zip((psi.real, psi.imag), model.reg_terms):
        if term is None:
            terms.append(None)
            continue
        value_weights, direction_filter = term
        sp = fft.rfft2(xp.ascontiguousarray(part))
        powers.append(kernels.weighted_power(sp, value_weights, host=False))
        sp *= direction_filter
        terms.append(sp)
    return powers, terms[0], terms[1]


def _regularizer_sum(powers: list[float], model: PWFModel) -> float:
    """The regularizer's part of J from :func:`_regularizer`'s sums, fetched to the host."""
    n = model.shape[0] * model.shape[1]
    value = 0.0
    for power in powers:
        value += 0.5 * power / n
    return value


def regularizer_value(psi, model: PWFModel) -> float:
    """The regularizer's part of J (see the module docstring)."""
    return _regularizer_sum(host_numbers(_regularizer(psi, model)[0]), model)


def objective_and_direction(psi, y, model: PWFModel):
    """J(psi) and the update direction M grad J = Precond(g) + Reg(psi) of Algorithm S1, line 11
    (:func:`objective_sums_and_direction`, its sums fetched)."""
    sums, g, ev = objective_sums_and_direction(psi, y, model)
    sums = host_numbers(sums)
    ev.loss = sums[0]
    return objective_of_sums(sums, model), g, ev


def objective_of_sums(sums: list[float], model: PWFModel) -> float:
    """J from the sums of :func:`objective_sums_and_direction` fetched to the host: the data
    term L / (4 N_t) plus the regularizer's."""
    loss, *powers = sums
    return loss / (4.0 * model.norm) + _regularizer_sum(powers, model)


def objective_sums_and_direction(psi, y, model: PWFModel):
    """J's sums and the update direction M grad J = Precond(g) + Reg(psi) of Algorithm S1, line 11.

    Returns (sums, g, ev): sums = [L, the regularizer's Parseval sums], left on psi's device
    (:func:`objective_of_sums` makes J of them once fetched), g the direction and ev the
    model's fields. ``Preconditioner`` filters Im(g) by P^-1; ``Regularizer`` adds
    Re(alpha) Gamma^2 Re(psi) + i Im(alpha) Gamma^2 Im(psi). The phase terms are summed in
    Fourier space, so one inverse FFT serves both.
    """
    xp, fft = model.xp, model.fft
    ev = residual(physical_model(psi, model), y, model, host=False)
    g = wirtinger_derivative(ev, model)
    powers, re_term, im_term = _regularizer(psi, model)
    # the direction is written in place into g: Re(g) plus the regularizer, then the
    # preconditioned Im(g) plus the phase regularizer (summed in Fourier space)
    if re_term is not None:
        g.real += fft.irfft2(re_term, s=model.shape, overwrite=True)
    if model.precond is not None:
        im_spec = fft.rfft2(xp.ascontiguousarray(g.imag))
        im_spec *= model.precond
        if im_term is not None:
            im_spec += im_term
        g.imag = fft.irfft2(im_spec, s=model.shape, overwrite=True)
    elif im_term is not None:
        g.imag += fft.irfft2(im_term, s=model.shape, overwrite=True)
    if model.phase_scale != 1.0:
        g.imag *= model.phase_scale
    return [ev.loss, *powers], g, ev


def objective(psi, y, model: PWFModel) -> float:
    """J(psi) alone (no gradient): the data term L / (4 N_t) plus the regularizer."""
    ev = residual(physical_model(psi, model), y, model)
    return ev.loss / (4.0 * model.norm) + regularizer_value(psi, model)


def largest_curvature(psi, y, model: PWFModel, direction=None, iterations: int = CURVATURE_ITERATIONS) -> float:
    """L, the largest eigenvalue of the metric's Hessian M H of J at ``psi``, by power iteration.

    The iteration matrix of psi <- psi - eta M grad J is I - eta M H: plain steps descend for
    eta L < 2, Nesterov's iteration only for eta L < 4/3 as its momentum factor nears 1, and
    1/L is the textbook step. Each product M H v is a finite difference of the direction
    along v (rms 1e-2 and at most 5e-2 in any pixel, where exp(psi) is still linear to a few %), one evaluation of
    :func:`objective_and_direction`. Power iteration approaches L from below (measured on the
    paper's 256 x 256 scene: 3.83, 4.09, 4.24 after 5, 8, 12 products, 4.49 after 100), so
    1/L from 8 products keeps eta L near 1.1, inside 4/3. The start vector is seeded: the step is reproducible.

    Why not a search along the first direction: that direction is dominated by the slow,
    smooth modes, whose curvature changes with the beam while the stiffest mode's does not
    (the same frame 10 % darker: L 3.29 against 3.41; the doubling search's step 0.5 against
    1.0). A step past 4/(3 L) grows the stiffest mode until a restart cuts it, and on the way
    it can throw the phase into a wrong basin (a +35 rad bump on a 2 % darker frame).

    Lengths are measured in the metric M^-1 (:func:`metric_norm`), in which M H is
    self-adjoint: the power iteration then rises monotonically to L. In the plain norm, the
    float32 rounding of the two directions whose difference gives M H v (white, ~1e-7 of
    their size) is amplified by the preconditioner's 1/(u^2+v^2), up to 6.7e6 on a 2592 px
    wide grid; on a 32 x 2560 strip of a thick sample the estimate then jumped between 0.7
    and 9.6 from one product to the next and ended 3.25 or 6.70 depending on the rounding
    of one element-wise kernel (numba or NumPy), and with it the run: 2000 iterations
    unconverged or 280 converged. In M^-1 the same products read 3.21, 3.58, 3.76, ...,
    4.05 after 8 in single and double precision alike.
    """
    xp = model.xp
    if direction is None:
        _, direction, _ = objective_and_direction(psi, y, model)
    rng = np.random.default_rng(0)
    v = xp.asarray(rng.standard_normal(model.shape) + 1j * rng.standard_normal(model.shape)).astype(model.cdtype)
    v /= math.sqrt(inner(v, v).real / v.size)
    weights = metric_phase_weights(model) if model.precond is not None else None
    v_norm = metric_norm(v, model, weights)
    curvature = 0.0
    for _ in range(iterations):
        # the iterate localises on the stiffest pixels (bright spots of |t|^2); an rms step
        # then moves those pixels by units, exp(psi) is far from linear, and the "curvature"
        # explodes (issue #27's 430 x 700 strip: 2.4 -> 542 -> 8.8e7, a step of 1e-8 that
        # never moved the phase): the probe is capped per pixel too
        h = min(CURVATURE_PROBE_RMS, CURVATURE_PROBE_MAX / max(float(xp.abs(v).max()), 1e-30))
        with np.errstate(over="ignore", invalid="ignore"):
            _, d, _ = objective_sums_and_direction(psi + h * v, y, model)  # J's sums not fetched
        d -= direction
        d *= 1.0 / h
        d_norm = metric_norm(d, model, weights)
        curvature = d_norm / v_norm
        if not (math.isfinite(curvature) and curvature > 0):
            raise FloatingPointError("PWF curvature estimate is not finite at the start")
        # the probe's size stays an rms in radians: it bounds how far exp(psi) is linearised
        rms = math.sqrt(inner(d, d).real / d.size)
        v = d
        v *= 1.0 / rms
        v_norm = d_norm / rms  # the metric norm scales with v: no second transform
    return curvature


def metric_norm(w, model: PWFModel, phase_weights=None) -> float:
    """rms of ``w`` in the metric M^-1 of the preconditioned iteration, M = diag(1, kappa
    P^-1): sqrt((|Re w|^2 + <Im w, (u^2+v^2) Im w> / kappa) / N), the phase part summed on
    its half spectrum (Parseval). M H is self-adjoint in it (:func:`largest_curvature`).
    Without the preconditioner M^-1's phase block is 1 / kappa. ``phase_weights``:
    :func:`metric_phase_weights` of the model, computed once by a caller that asks often."""
    n = w.size
    re, im = model.xp.ascontiguousarray(w.real), model.xp.ascontiguousarray(w.imag)
    if model.precond is None:
        phase_part = inner(im, im).real
    else:
        weights = metric_phase_weights(model) if phase_weights is None else phase_weights
        phase_part = kernels.weighted_power(model.fft.rfft2(im), weights) / n
    return math.sqrt((inner(re, re).real + phase_part / model.phase_scale) / n)


def metric_phase_weights(model: PWFModel):
    """(u^2+v^2) times each rfft bin's multiplicity: M^-1's phase block on a half spectrum."""
    q2 = optics.laplacian_symbol(model.shape, model.xp, model.rdtype)
    return q2 * _half_weights(model.shape, model.xp, model.rdtype)
