"""Preconditioned Wirtinger flow (PWF): Algorithms S1 and S2 of the paper.

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
see :func:`pwf`), and a halved step when J rises after a plain gradient step
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
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

from pwf_dask.backend import FFT, abs2, complex_dtype, complex_exp, inner, real_dtype
from pwf_dask.physics import optics
from pwf_dask.pwf import kernels

#: The paper's stop rule: normalised correlation of successive fields > 10^-0.00001.
PAPER_TOL = 1.0 - 10.0 ** (-0.00001)

#: Regularization weights of Algorithm S2: the paper's value (``alpha="paper"``), and the
#: default. With the paper's Im(alpha) the phase outside the STF fits the noise and beads of
#: 2-12 coherence lengths overshoot by 30-50 % on the paper's diffuser; Im(alpha) = 0.05 holds
#: them within 5 % from 1e3 to 1e5 ph/px (docs/methods.md, "Regularization"), a choice no
#: data rule tried beat (:func:`discrepancy_alpha` fails at both ends of that range).
PAPER_ALPHA = 0.1 + 0.01j
DEFAULT_ALPHA = 0.1 + 0.05j

#: Im(alpha) tried by :func:`discrepancy_alpha` (Re(alpha) stays the paper's 0.1: raising it
#: damps a small bead's attenuation and the phase overshoots to compensate, docs/methods.md),
#: the rung tried first (the usual answer), and the residual the rule aims at, in units of
#: the photon noise.
ALPHA_IMAG_LADDER = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
ALPHA_LADDER_START = 2
DISCREPANCY_TARGET = 1.0

#: A gradient restart after two steps psi_k - psi_{k-1} this anti-aligned (cosine below it)
#: was caused by a mode too stiff for eta (see :func:`pwf`, "Step"): eta is halved.
STIFF_COSINE = -0.5

#: Hessian-vector products in :func:`largest_curvature`, the rms of their probe step, and
#: the most any pixel of the probe may move psi (exp(psi) linear to ~2.5 %)
CURVATURE_ITERATIONS = 8
CURVATURE_PROBE_RMS = 1e-2
CURVATURE_PROBE_MAX = 5e-2

#: Momentum restart rules of :func:`pwf`; ``"none"`` is plain Algorithm S1.
RESTARTS = ("gradient", "function", "none")


@dataclass
class PWFModel:
    """Everything Algorithm S1 takes besides y and psi, precomputed on the device.

    Build with :func:`build_model`. ``shape`` is the computational grid (the detector
    frame plus ``pad`` pixels each side, rounded to a fast FFT length); ``upsample`` > 1
    forms |v|^2 on a grid that many times finer, so the squared modulus is not aliased.
    ``field_upsample`` s > 1 carries the whole optical chain, exp(psi), P1, t and P2, on an
    s-times finer grid ``field_shape`` (psi and t band-limited-interpolated), so that phase
    gradients up to s pi rad per detector pixel displace the speckle the right way (see
    :func:`build_model`).
    """

    xp: ModuleType
    fft: FFT
    shape: tuple[int, int]
    frame: tuple[slice, slice]
    mask: Any  # None: every computational pixel is measured
    t: Any
    t_conj: Any
    kernel1: Any  # None when L1 = 0
    kernel2: Any
    kernel1_conj: Any  # adjoint propagators P^H = P_{-L}, precomputed once
    kernel2_conj: Any  # conj(P2 kernel) / N_t: the derivative's 1/N_t rides on a multiply it needs anyway
    otf: Any  # intensity transfer (half spectrum) or None (full coherence, no pixel blur)
    upsample: int
    norm: float
    reg_window: Any  # Gamma^2 (half spectrum), None when gamma = 0 or alpha = 0
    precond: Any  # P^-1 (half spectrum), None when the preconditioner is off
    phase_scale: float  # kappa: block scaling of the phase direction (see phase_block_scale)
    alpha: complex
    rdtype: Any
    cdtype: Any
    info: dict = field(default_factory=dict)
    field_upsample: float = 1
    field_shape: tuple[int, int] | None = None  # the field's grid; None: ``shape``
    #: per part of psi (Re, Im): (rfft weights of its value in J, its direction filter
    #: Re/Im(alpha) Gamma^2), or None where that part of alpha is 0; precomputed by build_model
    reg_terms: tuple = (None, None)


def _half_weights(shape, xp, dtype):
    """Multiplicity of each rfft bin in the full spectrum (Parseval on half spectra)."""
    nx = shape[1]
    w = np.full(nx // 2 + 1, 2.0)
    w[0] = 1.0
    if nx % 2 == 0:
        w[-1] = 1.0
    return xp.asarray(w[None, :].astype(dtype))


#: lambda L2 / p^2 of the paper's set-up (10 keV, L2 = 20 mm, 0.65 um): eta = 1 was tuned there.
PAPER_FRESNEL_SCALE = 1.2398419843320026e-10 * 20e-3 / (0.65e-6) ** 2


def phase_block_scale(wavelength: float, diffuser_detector_distance_m: float, pixel_size_m: float) -> float:
    """kappa = (F_paper / F)^2 with F = lambda L2 / p^2: the phase block's metric scale.

    A phase gradient displaces the speckle by lambda L2 / (2 pi p^2) pixels per radian per
    pixel, so the preconditioned phase curvature scales as F^2 while the attenuation block's
    does not. The paper's preconditioner (cycles per pixel) balances the two blocks at its own
    set-up only; at 2 um pixels the phase would converge ~90x slower. Scaling the whole phase
    direction (preconditioned gradient and regularizer term) by kappa is a change of metric:
    J and its minimiser are untouched, and kappa = 1 at the paper's set-up. Opt-in
    (``phase_scale="auto"``): on a 35 pi glass rod at 2 um pixels it moves the phase but into
    a wrong basin (docs/validation.md, "Where PWF fails").
    """
    f = wavelength * diffuser_detector_distance_m / pixel_size_m**2
    return (PAPER_FRESNEL_SCALE / f) ** 2


def fast_len(n: int) -> int:
    import scipy.fft

    return int(scipy.fft.next_fast_len(int(n), real=False))


def field_grid(shape: tuple[int, int], field_upsample: float) -> tuple[int, int]:
    """The field's grid for ``field_upsample`` s: each side s times the computational grid's,
    rounded up to a fast FFT length (exactly s times for an integer s, the grid being fast)."""
    if field_upsample == 1:
        return tuple(shape)
    return tuple(fast_len(math.ceil(n * field_upsample - 1e-9)) for n in shape)


def build_model(
    t,
    *,
    frame_shape: tuple[int, int],
    pixel_size_m: float,
    wavelength: float,
    sample_diffuser_distance_m: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pixel_integration: bool = False,
    gamma: float = 1.0,
    alpha: complex = DEFAULT_ALPHA,
    use_preconditioner: bool = True,
    upsample: int = 1,
    pad: int = 0,
    precision: str = "single",
    normalization: str = "paper",
    phase_scale: float | str = 1.0,
    field_upsample: float = 1,
    bad_pixels=None,
    fft: FFT | None = None,
) -> PWFModel:
    """Precompute the kernels, filters and normalisation of Algorithm S1 for one geometry.

    ``t`` is the diffuser transmission on the computational grid (see
    :func:`pwf_dask.calibration.diffuser_transmission`); its shape fixes the grid, and the
    detector frame of ``frame_shape`` sits ``pad`` pixels from its top-left corner.

    ``field_upsample`` s > 1: the unknown psi stays on the detector grid, but the forward
    model evaluates exp(U psi), with U the band-limited (spectral zero-padding) interpolation
    to an s-times finer grid, and propagates on that grid with U t. On the detector grid a
    phase gradient g > pi rad/pixel aliases to g - 2 pi: exp(psi) then tilts the wave the
    wrong way and the speckle is displaced backwards (the thick-sample failure, docs/validation.md). The
    interpolated unwrapped phase keeps the tilt. The intensity is band-limited back to the
    detector grid as with ``upsample``. Costs about s^2 times the FFT work; s = 1 is the
    paper's model, unchanged. A fractional s (e.g. 1.5) puts the field on the next fast grid
    (:func:`field_grid`), whose pixel differs slightly between the axes.

    ``bad_pixels`` (frame-shaped, True = not a measurement, e.g. a zinger) are left out of
    the data term, as the padding margin is: the residual is masked there.
    """
    from pwf_dask.backend import get_array_module

    xp = get_array_module(t)
    fft = fft or FFT.for_module(xp)
    rdt, cdt = real_dtype(precision), complex_dtype(precision)
    shape = tuple(t.shape)
    ny, nx = frame_shape
    frame = (slice(pad, pad + ny), slice(pad, pad + nx))
    mask = None
    if shape != tuple(frame_shape) or bad_pixels is not None:
        mask = xp.zeros(shape, dtype=rdt)
        mask[frame] = 1
        if bad_pixels is not None:
            if tuple(bad_pixels.shape) != tuple(frame_shape):
                raise ValueError(f"bad_pixels has shape {tuple(bad_pixels.shape)}, the frame {tuple(frame_shape)}")
            mask[frame] *= 1 - xp.asarray(bad_pixels, dtype=rdt)
    t = t.astype(cdt, copy=False)
    field_upsample = int(field_upsample) if float(field_upsample).is_integer() else float(field_upsample)
    if not field_upsample >= 1:
        raise ValueError(f"field_upsample must be >= 1, got {field_upsample}")
    tmax = float(xp.max(t.real**2 + t.imag**2)) or 1.0
    field_shape = field_grid(shape, field_upsample)
    # the fine grid holds the coarse one's frequencies and more: its pixel is L / M per axis
    field_pixel_m = tuple(pixel_size_m * n / m for n, m in zip(shape, field_shape))
    if field_upsample > 1:
        t = interpolate_field(t, field_shape, fft).astype(cdt, copy=False)
        upsample = 1  # |v|^2 is formed on the fine grid already
    k1 = None
    if sample_diffuser_distance_m != 0:
        k1 = optics.angular_spectrum_kernel(field_shape, field_pixel_m, wavelength, sample_diffuser_distance_m, xp, cdt)
    k2 = optics.angular_spectrum_kernel(field_shape, field_pixel_m, wavelength, diffuser_detector_distance_m, xp, cdt)
    otf = optics.iotf(shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, xp, rdt)
    if pixel_integration:
        pix = optics.pixel_transfer_function(shape, pixel_size_m, pixel_size_m, xp, rdt)
        otf = pix if otf is None else otf * pix
    alpha = complex(alpha)
    reg = None
    if gamma > 0 and alpha != 0:
        reg = optics.regularization_window(
            shape, pixel_size_m, coherence_length_x_m, coherence_length_y_m, gamma, xp, rdt
        )
    precond = optics.preconditioner(shape, xp, rdt) if use_preconditioner else None
    reg_phase = None
    if reg is not None:
        reg_phase = reg * optics.laplacian_symbol(shape, xp, rdt) if use_preconditioner else reg
    if normalization == "paper":
        norm = tmax
    elif normalization == "released":
        norm = tmax**2
    else:
        raise ValueError(f"normalization must be 'paper' or 'released', not {normalization!r}")
    return PWFModel(
        xp=xp,
        fft=fft,
        shape=shape,
        frame=frame,
        mask=mask,
        t=t,
        t_conj=xp.conj(t),
        kernel1=k1,
        kernel2=k2,
        kernel1_conj=None if k1 is None else xp.conj(k1),
        kernel2_conj=xp.conj(k2) / norm,
        otf=otf,
        upsample=int(upsample),
        norm=norm,
        reg_window=reg,
        precond=precond,
        phase_scale=(
            phase_block_scale(wavelength, diffuser_detector_distance_m, pixel_size_m)
            if phase_scale == "auto"
            else float(phase_scale)
        ),
        alpha=alpha,
        rdtype=rdt,
        cdtype=cdt,
        info={"pad": pad, "pixel_integration": pixel_integration, "gamma": gamma},
        field_upsample=field_upsample,
        field_shape=field_shape,
        reg_terms=_regularizer_terms(reg, reg_phase, _half_weights(shape, xp, rdt), alpha),
    )


def _regularizer_terms(reg_window, reg_phase_weight, weights, alpha: complex) -> tuple:
    """(value weights, direction filter) for Re psi and Im psi; None where unused.

    ``reg_phase_weight`` is the phase part of J: (u^2+v^2) Gamma^2 with the preconditioner,
    Gamma^2 without (module docstring); ``weights`` are the rfft bin multiplicities of the
    Parseval sum."""
    if reg_window is None:
        return (None, None)
    return tuple(
        None if a == 0 else (a * weights * w, a * reg_window)
        for w, a in ((reg_window, alpha.real), (reg_phase_weight, alpha.imag))
    )


# --- spectral zero-padding between the detector grid and the finer intensity grid --------


def _band_slices(n: int, m: int):
    """Index pairs mapping the fft bins of an n-grid into an m-grid (m > n), Nyquist excluded.

    The Nyquist bin of an even grid stands for +1/2 and -1/2 at once and is weighted
    differently by real transforms of the two grid sizes; leaving it out keeps padding and
    cropping exact adjoints (the IOTF has long removed that frequency in practice).
    """
    pos = (n + 1) // 2
    neg = n // 2 - 1 if n % 2 == 0 else n // 2
    return [(slice(0, pos), slice(0, pos)), (slice(n - neg, n), slice(m - neg, m))]


def _half_columns(n: int):
    """rfft columns of an n-grid kept when changing grid size (Nyquist column left out)."""
    keep = n // 2 if n % 2 == 0 else n // 2 + 1
    return [(slice(0, keep), slice(0, keep))]


def _pad_spectrum(a, fine_shape, half: bool, coarse_nx: int | None = None):
    from pwf_dask.backend import get_array_module

    xp = get_array_module(a)
    m0 = fine_shape[0]
    m1 = fine_shape[1] // 2 + 1 if half else fine_shape[1]
    out = xp.zeros((m0, m1), dtype=a.dtype)
    cols = _half_columns(coarse_nx) if half else _band_slices(a.shape[1], m1)
    for rs, rd in _band_slices(a.shape[0], m0):
        for cs, cd in cols:
            out[rd, cd] = a[rs, cs]
    return out


def _crop_spectrum(a, coarse_shape, half: bool):
    from pwf_dask.backend import get_array_module

    xp = get_array_module(a)
    n0 = coarse_shape[0]
    n1 = coarse_shape[1] // 2 + 1 if half else coarse_shape[1]
    out = xp.zeros((n0, n1), dtype=a.dtype)
    cols = _half_columns(coarse_shape[1]) if half else _band_slices(n1, a.shape[1])
    for rs, rd in _band_slices(n0, a.shape[0]):
        for cs, cd in cols:
            out[rs, cs] = a[rd, cd]
    return out


def interpolate_field(a, fine_shape, fft: FFT):
    """U a: band-limited interpolation of a complex image onto a finer grid (spectral zero
    padding, Nyquist left out); U^H is :func:`restrict_field`."""
    s2 = (fine_shape[0] * fine_shape[1]) / (a.shape[0] * a.shape[1])
    out = fft.ifft2(_pad_spectrum(fft.fft2(a), fine_shape, half=False), overwrite=True)
    out *= s2
    return out


def restrict_field(a, coarse_shape, fft: FFT):
    """U^H a, the adjoint of :func:`interpolate_field` (spectral cropping)."""
    return fft.ifft2(_crop_spectrum(fft.fft2(a), coarse_shape, half=False), overwrite=True)


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
        x = complex_exp(interpolate_field(psi, fine, fft), fft.workers)
        a = x if model.kernel1 is None else _propagate(x, model.kernel1, fft, overwrite=False)
        v = _propagate(model.t * a, model.kernel2, fft, overwrite=True)
        spec_i = _crop_spectrum(fft.rfft2(abs2(v)), model.shape, half=True)
        if model.otf is not None:
            spec_i *= model.otf
        f = fft.irfft2(spec_i, s=model.shape, overwrite=True)
        f *= (model.shape[0] * model.shape[1]) / (fine[0] * fine[1])
        return Evaluation(x=x, v=v, f=f.astype(model.rdtype, copy=False), r=None, loss=math.nan)
    x = complex_exp(psi, fft.workers)
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


def residual(ev: Evaluation, y, model: PWFModel) -> Evaluation:
    """e = f - y on measured pixels (the paper's e_r = y_r - f_r with the sign folded in)."""
    ev.r, ev.loss = kernels.residual_and_loss(ev.f, y, model.mask)
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
    if model.kernel1 is not None:
        c = _propagate(c, model.kernel1_conj, fft, overwrite=True)
    c = kernels.times_conj(c, ev.x)
    g = c if model.field_upsample == 1 else restrict_field(c, model.shape, fft)
    return g.astype(model.cdtype, copy=False)


def _regularizer(psi, model: PWFModel):
    """The regularizer's value in J and the spectra of its direction terms.

    Returns (value, re_term, im_term): value by Parseval on rfft spectra (module docstring),
    re_term = Re(alpha) Gamma^2 rfft(Re psi) and im_term = Im(alpha) Gamma^2 rfft(Im psi), or
    None where that part of alpha is 0 (no FFT is spent on it).
    """
    if model.reg_window is None:
        return 0.0, None, None
    xp, fft = model.xp, model.fft
    n = model.shape[0] * model.shape[1]
    value = 0.0
    terms = []
    for part, term in zip((psi.real, psi.imag), model.reg_terms):
        if term is None:
            terms.append(None)
            continue
        value_weights, direction_filter = term
        sp = fft.rfft2(xp.ascontiguousarray(part))
        value += 0.5 * kernels.weighted_power(sp, value_weights) / n
        sp *= direction_filter
        terms.append(sp)
    return value, terms[0], terms[1]


def regularizer_value(psi, model: PWFModel) -> float:
    """The regularizer's part of J (see the module docstring)."""
    return _regularizer(psi, model)[0]


def objective_and_direction(psi, y, model: PWFModel):
    """J(psi) and the update direction M grad J = Precond(g) + Reg(psi) of Algorithm S1, line 11.

    ``Preconditioner`` filters Im(g) by P^-1; ``Regularizer`` adds Re(alpha) Gamma^2 Re(psi)
    + i Im(alpha) Gamma^2 Im(psi). The phase terms are summed in Fourier space, so one inverse
    FFT serves both.
    """
    xp, fft = model.xp, model.fft
    ev = residual(physical_model(psi, model), y, model)
    g = wirtinger_derivative(ev, model)
    reg_value, re_term, im_term = _regularizer(psi, model)
    j = ev.loss / (4.0 * model.norm) + reg_value
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
    return j, g, ev


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
            _, d, _ = objective_and_direction(psi + h * v, y, model)
        d -= direction
        d *= 1.0 / h
        d_norm = metric_norm(d, model, weights)
        curvature = d_norm / v_norm
        if not (math.isfinite(curvature) and curvature > 0):
            raise FloatingPointError("PWF curvature estimate is not finite at the start")
        # the probe's size stays an rms in radians: it bounds how far exp(psi) is linearised
        v = d
        v *= 1.0 / math.sqrt(inner(d, d).real / d.size)
        v_norm = metric_norm(v, model, weights)
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


# --- Algorithm S1 -----------------------------------------------------------------------


@dataclass
class PWFSolution:
    """The outcome of :func:`pwf`: psi on the computational grid and diagnostics."""

    psi: Any
    evaluation: Evaluation
    iterations: int
    converged: bool
    objective_history: list[float]
    step: float
    restarts: int
    backtracks: int
    stop_reason: str


def _settled(steps: list[float], psi, rtol: float, window: int, xp) -> bool:
    """Extrapolated remaining change of psi below ``rtol`` rms(psi) (see :func:`pwf`).

    ``steps`` are the step sizes of the current momentum run only: a restart drops the step
    by orders of magnitude (3e-2 to 2e-4 rad on a 256 x 256 frame at L1 = 0) while the slow
    modes still have far to go, and two windows either side of it read as a fast linear
    rate (that run stopped at iteration 198 with phase error 0.058; converged 0.040).
    """
    if rtol <= 0:
        return True
    if len(steps) < 2 * window:
        return False
    s1 = sum(steps[-2 * window : -window]) / window
    s2 = sum(steps[-window:]) / window
    if not s2 < s1:
        return False
    rho = (s2 / s1) ** (1.0 / window)
    remaining = s2 * rho / (1.0 - rho)
    scale = float(xp.sqrt(xp.mean(psi.real**2 + psi.imag**2)))
    return remaining < rtol * max(scale, 1e-12)


def _stationary(history: list[float], jtol: float, window: int) -> bool:
    """J's best value fell by less than ``jtol`` (relative) from one ``window`` to the next.

    The psi test of :func:`_settled` cannot pass while a low-frequency phase creeps at a
    constant rate along a direction that neither the data nor Gamma^2 constrain (measured at
    L1 = 0: 0.04 rad rms in 800 iterations, J changing 4e-5). J then no longer moves, and
    the creep does not change the fit.
    """
    if jtol <= 0 or len(history) < 2 * window:
        return False
    before = min(history[-2 * window : -window])
    now = min(history[-window:])
    return before - now < jtol * abs(before)


#: Scales the low-band stop test watches (:func:`_low_band_settled`): phase structure wider
#: than this many pixels, the wide smooth objects whose phase the data fix only weakly
LOW_BAND_PX = 64.0


def low_band_filter(shape: tuple[int, int], xp: ModuleType = np, dtype=np.float32, width_px: float = LOW_BAND_PX):
    """Gaussian low pass exp(-2 pi^2 sigma^2 q^2) with sigma = ``width_px`` / 4 (half spectrum):
    keeps structure wider than ``width_px``, whatever the frame size."""
    v, u = optics.frequency_grid(shape, 1.0, half=True)
    sigma = width_px / 4.0
    return xp.asarray(np.exp(-2.0 * np.pi**2 * sigma**2 * (u * u + v * v)).astype(dtype))


def _low_band_settled(snapshots: list, rtol: float, xp) -> bool:
    """The low band of the phase (:func:`low_band_filter`, one snapshot per stop window) has
    stopped moving: its change over the last window, extrapolated at the rate of the two
    windows before (a geometric tail), is below ``rtol`` times its rms.

    :func:`_stationary` alone lets a run stop while J no longer moves but the phase of wide
    objects still does (issue #27 asks that such a run never be called converged; on the
    simulated strips of that issue the low band had settled when J had, and this test added
    13 iterations). A change that does not shrink from one window to the next is not
    settled unless it is below ``rtol`` / 100 of the rms (rounding)."""
    if rtol <= 0:
        return True
    if len(snapshots) < 3:
        return False
    a, b, c = snapshots[-3:]
    scale = max(float(xp.sqrt(xp.mean(c * c))), 1e-12)
    d1 = float(xp.sqrt(xp.mean((b - a) ** 2)))
    d2 = float(xp.sqrt(xp.mean((c - b) ** 2)))
    if d2 < 0.01 * rtol * scale:
        return True
    if not d2 < d1:
        return False
    rho = d2 / d1
    return d2 * rho / (1.0 - rho) < rtol * scale


@dataclass(frozen=True)
class StopRule:
    """When :func:`pwf` stops: the defaults of every caller (retrieval, pipeline, CLI), defined here once.

    ``tol``: the paper's field-correlation test (Algorithm S1, line 14), met on ``patience``
    consecutive accepted iterations and not before ``min_iter``; ``rtol``: the extrapolated
    remaining change (:func:`_settled`, over ``window``-iteration windows); ``jtol``: J
    stationary (:func:`_stationary`) with the band wider than ``low_band_px`` settled
    (:func:`_low_band_settled`); ``max_iter``: the cap. See :func:`pwf`.
    """

    max_iter: int = 2000
    tol: float = PAPER_TOL
    min_iter: int = 50
    patience: int = 10
    rtol: float = 1e-3
    jtol: float = 1e-5
    window: int = 20
    low_band_px: float = LOW_BAND_PX


#: the stop rule every caller defaults to
STOP_RULE = StopRule()

#: eta of Algorithm S1 in units of 1/L (with the step search), and the width of the
#: regularization window over the STF (Eq. (regularization window)): defaults of every caller
DEFAULT_STEP = 1.0
DEFAULT_GAMMA = 1.0


def pwf(
    y,
    model: PWFModel,
    *,
    step: float = DEFAULT_STEP,
    max_iter: int = STOP_RULE.max_iter,
    tol: float = STOP_RULE.tol,
    min_iter: int = STOP_RULE.min_iter,
    patience: int = STOP_RULE.patience,
    rtol: float = STOP_RULE.rtol,
    jtol: float = STOP_RULE.jtol,
    window: int = STOP_RULE.window,
    low_band_px: float = STOP_RULE.low_band_px,
    psi0=None,
    step_search: bool = True,
    restart: str = "gradient",
    callback=None,
) -> PWFSolution:
    """Algorithm S1 with a safe step and a robust stop.

    Stop rule: 1 - |<x_k, x_{k-1}>| / (|x_k| |x_{k-1}|) < ``tol`` (the paper's field
    correlation; ``tol`` = 1 - 10^-0.00001 by default) on ``patience`` consecutive accepted
    iterations and not before ``min_iter``: a single pass is met inside Nesterov's oscillation
    dips, 10-20 % short of the converged phase. ``tol`` = 0 runs ``max_iter`` iterations.

    The field correlation bounds the change per iteration in radians, not the distance to the
    solution: a phase still creeping at 0.005 rad per iteration passes it while radians short
    (measured: 40 % of the cylinder phase on a 48 x 128 frame, stopped at iteration 67). So
    the stop also needs the extrapolated remaining change, step * rho / (1 - rho), with the
    linear rate rho from the mean rms steps of two successive ``window``-iteration windows of
    the current momentum run (:func:`_settled`), below ``rtol`` times rms(psi) (``rtol`` = 0
    disables this test), or J stationary: its best value lowered by less than ``jtol``
    (relative) from one window to the next (:func:`_stationary`; ``jtol`` = 0 disables it)
    while the phase's structure wider than ``low_band_px`` has settled as well
    (:func:`_low_band_settled`, ``low_band_px`` = 0 leaves it out).

    Step: ``step`` is eta of Algorithm S1; with ``step_search`` it is in units of 1/L, L the
    largest curvature in the metric at psi_0 (:func:`largest_curvature`, power iteration), so
    the default 1 is 1/L. The paper's eta = 1 was tuned for 0.65 um pixels: the curvature
    scales as (lambda L2 / p^2)^2, so at 2 um it is ~100x too short. J rising after a plain
    step halves eta and the rejected point is discarded. Plain steps descend for eta L < 2,
    Nesterov's iteration only for eta L < 4/3 as its momentum factor beta nears 1: between
    the two, the stiffest mode's iteration has a real eigenvalue below -1 once
    beta > (1/(eta L - 1) - 1)/2, so it flips sign every step and grows, the gradient restart
    cuts the run, and the runs shorten as beta's threshold falls (measured with the former
    doubling search along the first direction, which landed anywhere in [1/L, 2/L): runs of
    139, 43, 12, 10, ... down to 4 iterations on a 256 x 256 frame whose beam was 5 % weaker
    than the reference's). Its signature is successive steps pointing opposite ways at the
    restart (cosine < :data:`STIFF_COSINE`, measured -0.65 to -0.95 there, while restarts of
    the slow modes' overshoot have positive cosines); such a restart halves eta, unless eta
    was halved at the restart before (the oscillation that ends the run after a halving grew
    at the longer step). With the curvature estimate this is a safety net for an L that grows
    as the phase builds up.

    Momentum restart (``restart``): ``"gradient"`` (default, O'Donoghue & Candes 2015) drops
    the momentum when it points uphill, Re<d, phi_k - phi_{k-1}> > 0, and tolerates J at the
    extrapolated point oscillating inside a momentum run as long as it stays below J at the
    run's start (above it: discard and restart). ``"function"`` discards and restarts on any
    rise of J. J is evaluated at the extrapolated point, where it oscillates while the
    iterates still converge, so the function rule restarts every few iterations and loses
    the acceleration: on a 256 x 256 frame with coherence lengths 15 % short its relative
    phase error after 500 iterations was 0.48, the gradient rule's 0.10. ``"none"`` is
    Algorithm S1 as printed: J is still evaluated (for the history) but never decides
    anything: no restart, no rejected step, and a non-finite J ends the run (diverged).
    """
    if restart not in RESTARTS:
        raise ValueError(f"restart must be one of {', '.join(RESTARTS)}, got {restart!r}")
    xp = model.xp
    psi = xp.zeros(model.shape, dtype=model.cdtype) if psi0 is None else xp.asarray(psi0, dtype=model.cdtype)
    eta = float(step)
    mu = 1.0
    phi_prev = psi
    last = None  # (psi, J, direction, evaluation) of the last accepted evaluation
    last_x_norm = None
    steps: list[float] = []  # accepted step sizes since the last momentum restart
    momentum_used = False
    history: list[float] = []
    restarts = backtracks = streak = 0
    anchor_j = math.inf
    run_best, stalled = math.inf, 0
    # long on purpose: 20 iterations cut productive runs at 1e3 ph/px (error 0.42 for 0.06)
    stall_limit = 5 * window
    halved = False  # eta was halved at the last momentum restart
    recent_steps: list = []  # the last two accepted steps psi_k - psi_{k-1}
    low_pass = low_band_filter(model.shape, xp, model.rdtype, low_band_px) if low_band_px > 0 else None
    low_band: list = []  # low-passed phase, one snapshot per ``window`` accepted iterations
    accepted = 0

    def restart_momentum():
        """Count a momentum restart; under the gradient rule, halve eta when a stiff mode
        caused it (:data:`STIFF_COSINE`), unless eta was halved at the restart before: that
        run's oscillation grew at the longer step."""
        nonlocal restarts, halved, eta, backtracks
        restarts += 1
        steps.clear()  # the stop's rate estimate starts afresh with the run (_settled)
        if restart != "gradient" or len(recent_steps) < 2:
            return
        if halved:
            halved = False
            return
        before, now = recent_steps
        cosine = inner(before, now).real / math.sqrt(inner(before, before).real * inner(now, now).real or 1.0)
        if cosine < STIFF_COSINE:
            eta *= 0.5
            backtracks += 1
            halved = True

    # J is summed in float64 from residuals rounded to the working precision: a rise
    # smaller than that rounding is noise, not a failed step
    rise_tol = 1e-5 if model.rdtype == np.float32 else 1e-11
    converged = False
    reason = "max_iter"
    k = 0
    while k < max_iter:
        k += 1
        # an over-long trial step may overflow exp(psi); J is then inf and the step is rejected
        with np.errstate(over="ignore", invalid="ignore"):
            j, d, ev = objective_and_direction(psi, y, model)
        if not math.isfinite(j):
            reason = "non-finite objective"
            if last is None:
                raise FloatingPointError("PWF objective is not finite at the first iterate")
            if restart == "none":
                break  # plain Algorithm S1 has no way back: it diverged
            j = math.inf
        # function restart: J above the last accepted value; gradient restart tolerates J(y)
        # oscillating inside a momentum run as long as it stays below the run's start
        rose = False
        if last is not None and restart != "none":
            ref_j = anchor_j if (restart == "gradient" and momentum_used) else last[1]
            rose = j > ref_j * (1.0 + rise_tol)
        if rose:
            if momentum_used:
                restart_momentum()
            else:
                backtracks += 1
                eta *= 0.5
                steps.clear()
            psi, j, d, ev = last
            mu = 1.0
            momentum_used = False
            streak = 0
            if eta < 1e-12 * step:
                reason = "step collapsed"
                break
        else:
            if last is not None:
                dpsi, step_sq = kernels.step_and_norm(psi, last[0])
                recent_steps = [*recent_steps[-1:], dpsi]
                steps.append(math.sqrt(step_sq / dpsi.size))
                x_sq, overlap = kernels.field_correlation(ev.x, last[3].x)
                x_norm = math.sqrt(x_sq)
                corr = abs(overlap) / (x_norm * last_x_norm)
                streak = streak + 1 if 1.0 - corr < tol else 0
                last_x_norm = x_norm
            else:
                last_x_norm = math.sqrt(inner(ev.x, ev.x).real)
            if last is None and step_search:
                eta = step / largest_curvature(psi, y, model, direction=d)
            if not momentum_used:
                anchor_j = j
                run_best, stalled = j, 0
            elif j < run_best:
                run_best, stalled = j, 0
            else:
                stalled += 1
            last = (psi, j, d, ev)
            history.append(j)
            accepted += 1
            if low_pass is not None and accepted % window == 0:
                low_band = [*low_band[-2:], _filter_real(xp.ascontiguousarray(psi.imag), low_pass, model.fft)]
            if callback is not None:
                callback(k, j, psi)
            if (
                tol > 0
                and streak >= patience
                and k >= min_iter
                and (
                    _settled(steps, psi, rtol, window, xp)
                    or (
                        _stationary(history, jtol, window)
                        and (low_pass is None or _low_band_settled(low_band, rtol, xp))
                    )
                )
            ):
                converged = True
                reason = "converged"
                break
        # phi = psi - eta d (line 12) and whether the momentum phi - phi_prev points uphill
        phi, uphill = kernels.descent_point(psi, d, phi_prev, eta)
        mu_prev = mu
        mu = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * mu * mu))
        beta = (mu_prev - 1.0) / mu
        if restart == "gradient" and beta > 0 and (uphill > 0 or stalled >= stall_limit):
            # the momentum points uphill along the (preconditioned) gradient at psi, or has
            # made no new low of J for ``stall_limit`` iterations (the uphill test can stay
            # silent for ever while J oscillates: at L1 = 0, one 1000-iteration run)
            restart_momentum()
            mu, beta = 1.0, 0.0
            stalled = 0
        momentum_used = beta > 0
        psi = kernels.momentum_point(phi, phi_prev, beta) if momentum_used else phi
        phi_prev = phi
    psi_best, _, _, ev_best = last
    return PWFSolution(
        psi=psi_best,
        evaluation=ev_best,
        iterations=k,
        converged=converged,
        objective_history=history,
        step=eta,
        restarts=restarts,
        backtracks=backtracks,
        stop_reason=reason,
    )


@dataclass
class AlphaChoice:
    """What :func:`discrepancy_alpha` chose, the run it chose it from, and every rung tried
    as (alpha, residual rms / noise rms, iterations)."""

    alpha: complex
    result: Any
    trials: list[tuple[complex, float, int]]


def discrepancy_alpha(
    solve: Callable[[complex, Any], tuple[Any, float]],
    noise_pct: float,
    *,
    real: float = PAPER_ALPHA.real,
    ladder: tuple[float, ...] = ALPHA_IMAG_LADDER,
    start: int = ALPHA_LADDER_START,
    target: float = DISCREPANCY_TARGET,
) -> AlphaChoice:
    """Im(alpha) by Morozov's discrepancy principle: the strongest phase regularization whose
    data residual stays at or below the photon noise (``target`` x ``noise_pct``); the rule of
    ``alpha="discrepancy"``.

    The paper fixes alpha = 0.1 + 0.01i (Methods, regularization window). Outside the STF the
    data carry little of psi, and with Im(alpha) that weak the solution fits the noise there: its
    residual falls 7 % below the noise and small beads' phase overshoots by 30-50 % (256^2,
    P3000). At 1e4 ph/px this rule lands on 0.1 + 0.05i; at 1e3 the residual stays below the
    noise up to Im(alpha) = 0.5 (PWF fits part of the noise inside the STF too) and it
    over-regularizes, at 1e5 the model's own error exceeds the noise and it keeps the paper's
    alpha (docs/methods.md, "Regularization"). Not the default for that reason. ``solve(alpha, psi0)`` runs
    Algorithm S1 from ``psi0`` (None: its own start) and returns (result, residual rms in % of
    the mean reference); each rung starts from the previous rung's psi (``result.psi``). The
    search starts at ``ladder[start]`` and walks up while the residual stays at or below the
    target, or down until it does; the paper's rung is the floor.
    """
    trials: list[tuple[complex, float, int]] = []
    runs: dict[int, Any] = {}

    def attempt(i: int, psi0) -> float:
        alpha = complex(real, ladder[i])
        result, rmse_pct = solve(alpha, psi0)
        runs[i] = result
        ratio = rmse_pct / noise_pct
        trials.append((alpha, ratio, int(result.iterations)))
        return ratio

    i = start
    if attempt(i, None) <= target:
        while i + 1 < len(ladder) and attempt(i + 1, runs[i].psi) <= target:
            i += 1
    else:
        while i > 0 and attempt(i - 1, runs[i].psi) > target:
            i -= 1
        i = max(i - 1, 0)
    return AlphaChoice(complex(real, ladder[i]), runs[i], trials)
