"""Speckle-tracking baselines: UMPA, LCS, GF and MIST, beside PWF (Table S1 of the paper).

All four return phase (Im psi, rad, negative for matter) and attenuation (-Re psi), like PWF,
so the tomography and FSC stages take them unchanged. Geometry: the sample sits L1 upstream
of the diffuser, so a phase gradient tilts the beam onto the diffuser and, by the memory
effect, displaces the speckle by d = lambda L2 grad(phi) / (2 pi) at the detector (L1 only
moves the illuminated patch of the diffuser). In pixels, d = F grad_px(phi) / (2 pi) with
F = lambda L2 / p^2.

* :func:`umpa` - Zdora et al. 2017: for every pixel, the integer shift minimising a windowed
  least-squares cost between sample and shifted reference (transmission in closed form),
  refined to sub-pixel by a parabola; K >= 1 images.
* :func:`lcs` - Quenot et al. 2021, "low coherence system": per-pixel linear least squares
  over K >= 3 diffuser positions of I_k = T (R_k - d . grad R_k).
* :func:`geometric_flow` - Paganin et al. 2018: one image, no attenuation; the linearised flow
  I_S = I_R - (lambda L2 / 2 pi) div(I_R grad phi), solved by conjugate gradients with an
  inverse-Laplacian preconditioner.
* :func:`mist` - multimodal intrinsic speckle tracking (Pavlov 2020, Alloo 2023) for a single
  material: per-pixel least squares over K >= 4 positions of the evolving Fokker-Planck
  equation (attenuation, phase flow and diffusive dark field), then one Fourier inversion
  that ties attenuation to phase by the sample's delta/beta.
* :func:`integrate_gradient` - Frankot-Chellappa Fourier integration of the displacement field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pwf_dask.backend import FFT, get_array_module


@dataclass
class TrackingResult:
    """Output of a speckle-tracking baseline (displacements in pixels; residual: RMS over the
    K images of measured minus modelled intensity, the paper's LCS residual image)."""

    phase: Any
    attenuation: Any
    dx: Any
    dy: Any
    residual: Any
    dark_field: Any = None  # MIST's b = F D I_ob, the coefficient of lap R_k (pixels^2)


def _box(a, size: int, xp):
    """Box sum over size x size windows (edges reflected), via cumulative sums."""
    r = size // 2
    p = xp.pad(a, ((r + 1, r), (r + 1, r)), mode="reflect")
    c = xp.cumsum(xp.cumsum(p, axis=-2), axis=-1)
    return c[size:, size:] - c[:-size, size:] - c[size:, :-size] + c[:-size, :-size]


def _mirror(a, sign_x: int = 1, sign_y: int = 1, xp=np):
    """Even (sign +1) or odd (-1) extension to 2x size along each axis: the periodic
    extension of the result has no jump at the frame edges."""
    e = xp.concatenate([a, sign_x * a[:, ::-1]], axis=1)
    return xp.concatenate([e, sign_y * e[::-1, :]], axis=0)


def integrate_gradient(gx, gy, fft: FFT | None = None):
    """Frankot-Chellappa: the periodic surface whose gradient (per pixel) best fits (gx, gy).

    Mirror-extended to 2x size so the periodic solution does not see the frame edges."""
    xp = get_array_module(gx)
    fft = fft or FFT.for_module(xp)
    ny, nx = gx.shape
    ex = _mirror(gx, -1, 1, xp)
    ey = _mirror(gy, 1, -1, xp)
    v = xp.asarray(np.fft.fftfreq(2 * ny)[:, None])
    u = xp.asarray(np.fft.fftfreq(2 * nx)[None, :])
    q2 = u * u + v * v
    q2[0, 0] = 1.0
    spec = (-1j * (u * fft.fft2(ex) + v * fft.fft2(ey))) / (2 * np.pi * q2)
    spec[0, 0] = 0
    return fft.ifft2(spec).real[:ny, :nx]


def _phase_from_displacement(dx, dy, fresnel: float):
    # d = F grad(phi) / (2 pi)  =>  grad(phi) = 2 pi d / F
    return integrate_gradient(2 * np.pi * dx / fresnel, 2 * np.pi * dy / fresnel)


def umpa(sample, reference, *, fresnel: float, window: int = 7, max_shift: int = 4):
    """UMPA (Zdora 2017). ``sample``, ``reference``: (K, y, x) or (y, x). Returns a
    :class:`TrackingResult`; displacements in pixels.

    For shift s, cost(s) = sum_k sum_window (I_k - T R_k(r - s))^2 with the window's best T =
    <I R_s> / <R_s R_s>, i.e. cost = <I I> - <I R_s>^2 / <R_s R_s> (box sums over the window).
    """
    xp = get_array_module(sample, reference)
    i_img = xp.asarray(sample, dtype=xp.float64)
    r_img = xp.asarray(reference, dtype=xp.float64)
    if i_img.ndim == 2:
        i_img, r_img = i_img[None], r_img[None]
    ii = sum(_box(i_img[k] ** 2, window, xp) for k in range(i_img.shape[0]))
    shifts = range(-max_shift, max_shift + 1)
    n = len(shifts)
    cost = xp.empty((n, n) + i_img.shape[1:])
    trans = xp.empty_like(cost)
    for a, sy in enumerate(shifts):
        for b, sx in enumerate(shifts):
            rs = xp.roll(r_img, (sy, sx), axis=(1, 2))  # R(r - s)
            ir = sum(_box(i_img[k] * rs[k], window, xp) for k in range(i_img.shape[0]))
            rr = sum(_box(rs[k] ** 2, window, xp) for k in range(i_img.shape[0]))
            cost[a, b] = ii - ir * ir / rr
            trans[a, b] = ir / rr
    flat = cost.reshape(n * n, *cost.shape[2:])
    best = xp.argmin(flat, axis=0)
    by, bx = best // n, best % n
    byc = xp.clip(by, 1, n - 2)
    bxc = xp.clip(bx, 1, n - 2)
    yy, xx = xp.indices(by.shape)

    def parabola(c0, c1, c2):
        den = c0 - 2 * c1 + c2
        return xp.where(den > 0, 0.5 * (c0 - c2) / xp.where(den > 0, den, 1), 0.0)

    fy = parabola(cost[byc - 1, bx, yy, xx], cost[byc, bx, yy, xx], cost[byc + 1, bx, yy, xx])
    fx = parabola(cost[by, bxc - 1, yy, xx], cost[by, bxc, yy, xx], cost[by, bxc + 1, yy, xx])
    dy = (byc - max_shift) + xp.clip(fy, -1, 1)
    dx = (bxc - max_shift) + xp.clip(fx, -1, 1)
    t = trans[by, bx, yy, xx]
    phase = _phase_from_displacement(dx, dy, fresnel)
    attenuation = -0.5 * xp.log(xp.clip(t, 1e-6, None))
    k = i_img.shape[0]
    residual = xp.sqrt(xp.clip(cost[by, bx, yy, xx], 0, None) / (k * window * window))
    return TrackingResult(phase, attenuation, dx, dy, residual)


def _pixel_least_squares(basis, i_img, regularization: float, xp):
    """Per pixel, the coefficients x minimising sum_k (I_k - sum_j x_j basis_kj)^2 plus a
    Tikhonov term scaled to the pixel's normal matrix; ``basis``: (K, J, y, x). Returns the
    (y, x, J) coefficients and the RMS residual over the K images."""
    n = basis.shape[1]
    ata = xp.einsum("kiyx,kjyx->yxij", basis, basis)
    atb = xp.einsum("kiyx,kyx->yxi", basis, i_img)
    scale = xp.trace(ata, axis1=-2, axis2=-1)[..., None, None] / n
    ata = ata + regularization * scale * xp.eye(n)
    sol = xp.linalg.solve(ata, atb[..., None])[..., 0]
    model = xp.einsum("kiyx,yxi->kyx", basis, sol)
    return sol, xp.sqrt(xp.mean((i_img - model) ** 2, axis=0))


#: the fewest diffuser positions a method's per-pixel least squares needs (unknowns per pixel)
MIN_POSITIONS = {"lcs": 3, "mist": 4}


def _stacks(sample, reference, xp, method: str):
    i_img = xp.asarray(sample, dtype=xp.float64)
    r_img = xp.asarray(reference, dtype=xp.float64)
    k = MIN_POSITIONS[method]
    if i_img.ndim != 3 or i_img.shape[0] < k:
        raise ValueError(f"{method.upper()} needs K >= {k} diffuser positions: sample and reference of shape (K, y, x)")
    return i_img, r_img


def lcs(sample, reference, *, fresnel: float, regularization: float = 1e-6):
    """LCS (Quenot 2021): per pixel, least squares over K >= 3 positions of
    I_k = a R_k + b dR_k/dx + c dR_k/dy, with a = T, (b, c) = -T d. Returns a
    :class:`TrackingResult`."""
    xp = get_array_module(sample, reference)
    i_img, r_img = _stacks(sample, reference, xp, "lcs")
    gy, gx = xp.gradient(r_img, axis=(1, 2))
    sol, residual = _pixel_least_squares(xp.stack([r_img, gx, gy], axis=1), i_img, regularization, xp)
    t = sol[..., 0]
    tsafe = xp.where(xp.abs(t) > 1e-6, t, 1e-6)
    dx = -sol[..., 1] / tsafe
    dy = -sol[..., 2] / tsafe
    phase = _phase_from_displacement(dx, dy, fresnel)
    attenuation = -0.5 * xp.log(xp.clip(t, 1e-6, None))
    return TrackingResult(phase, attenuation, dx, dy, residual)


def _laplacian(a, xp):
    """Five-point Laplacian (per pixel^2) of each image of a (K, y, x) stack, edges reflected."""
    p = xp.pad(a, ((0, 0), (1, 1), (1, 1)), mode="reflect")
    return p[:, :-2, 1:-1] + p[:, 2:, 1:-1] + p[:, 1:-1, :-2] + p[:, 1:-1, 2:] - 4 * a


def mist(sample, reference, *, fresnel: float, delta_over_beta: float, regularization: float = 1e-6):
    """MIST for a single-material sample (Pavlov et al. 2020; Alloo et al. 2023). Returns a
    :class:`TrackingResult` with the dark-field coefficient in ``dark_field``.

    The evolving Fokker-Planck equation with the sample's transmission I_ob and an effective
    diffusion D (the dark field), pixel units, F = lambda L2 / p^2,

        I_k = I_ob R_k - (F / 2 pi) div(R_k I_ob grad phi) + F lap(D I_ob R_k),

    becomes, for one material (I_ob grad phi = (g / 2) grad I_ob, g = delta/beta, so the
    phase is phi = (g / 2) ln I_ob) and with G = F g / (4 pi), b = F D I_ob,

        I_k = a R_k + b lap R_k + c . grad R_k,
        a = I_ob - G lap I_ob + lap b,   c = 2 grad b - G grad I_ob.

    Per pixel, (a, b, c) are fitted in least squares over the K >= 4 positions; then
    a - lap b = (1 - G lap) I_ob and c - 2 grad b = -G grad I_ob are solved together for I_ob
    in Fourier space (least squares over both, mirror-extended; the discrete symbols of the
    operators used in the fit). The c equation carries the speckle displacement, the a
    equation the attenuation and intrinsic (propagation) contrast. The attenuation is
    -ln(I_ob) / 2 and the phase -g times it: a second material (glass beads in cellulose)
    gets the right phase where the displacement dominates but an attenuation off by the ratio
    of the two delta/beta, the coupling the paper notes (Table S1).
    """
    xp = get_array_module(sample, reference)
    fft = FFT.for_module(xp)
    i_img, r_img = _stacks(sample, reference, xp, "mist")
    if not delta_over_beta > 0:
        raise ValueError(f"MIST needs the sample's delta/beta > 0, got {delta_over_beta}")
    gy, gx = xp.gradient(r_img, axis=(1, 2))
    basis = xp.stack([r_img, _laplacian(r_img, xp), gx, gy], axis=1)
    sol, residual = _pixel_least_squares(basis, i_img, regularization, xp)
    a, b, cx, cy = (sol[..., j] for j in range(4))
    ny, nx = a.shape
    v = xp.asarray(np.fft.fftfreq(2 * ny)[:, None])
    u = xp.asarray(np.fft.fftfreq(2 * nx)[None, :])
    minus_lap = (2 - 2 * xp.cos(2 * np.pi * u)) + (2 - 2 * xp.cos(2 * np.pi * v))
    grad_x, grad_y = 1j * xp.sin(2 * np.pi * u), 1j * xp.sin(2 * np.pi * v)  # central differences
    big_g = fresnel * delta_over_beta / (4 * np.pi)  # G of the docstring
    b_hat = fft.fft2(_mirror(b, 1, 1, xp))
    a_eq = fft.fft2(_mirror(a, 1, 1, xp)) + minus_lap * b_hat  # = (1 + G |q|^2) I_ob
    cx_eq = fft.fft2(_mirror(cx, -1, 1, xp)) - 2 * grad_x * b_hat  # = -G grad_x I_ob
    cy_eq = fft.fft2(_mirror(cy, 1, -1, xp)) - 2 * grad_y * b_hat
    paganin = 1 + big_g * minus_lap
    numerator = paganin * a_eq - big_g * (xp.conj(grad_x) * cx_eq + xp.conj(grad_y) * cy_eq)
    denominator = paganin**2 + big_g * big_g * (xp.abs(grad_x) ** 2 + xp.abs(grad_y) ** 2)
    i_ob = fft.ifft2(numerator / denominator).real[:ny, :nx]
    attenuation = -0.5 * xp.log(xp.clip(i_ob, 1e-6, None))
    phase = -delta_over_beta * attenuation
    pgy, pgx = xp.gradient(phase)
    d = fresnel / (2 * np.pi)
    return TrackingResult(phase, attenuation, d * pgx, d * pgy, residual, dark_field=b)


def geometric_flow(sample, reference, *, fresnel: float, iterations: int = 200, tol: float = 1e-6):
    """Geometric flow (Paganin 2018): phase from one image, assuming no attenuation.

    Solves div(I_R grad phi) = (2 pi / F) (I_R - I_S) (pixels) by conjugate gradients on the
    negated, symmetric positive operator, preconditioned by the inverse Laplacian scaled by
    mean(I_R). Returns a :class:`TrackingResult` with the phase (mean 0) and zero attenuation,
    which is GF's assumption."""
    xp = get_array_module(sample, reference)
    fft = FFT.for_module(xp)
    i_s = xp.asarray(sample, dtype=xp.float64)
    i_r = xp.asarray(reference, dtype=xp.float64)
    if i_s.ndim == 3:
        i_s, i_r = i_s[0], i_r[0]
    # -div(I_R grad phi) = -(2 pi / F)(I_R - I_S): the operator below is -div(I_R grad .)
    b = -(2 * np.pi / fresnel) * (i_r - i_s)
    b = b - b.mean()

    def grad(f):
        return xp.roll(f, -1, 1) - f, xp.roll(f, -1, 0) - f

    def div(gx, gy):
        return gx - xp.roll(gx, 1, 1) + gy - xp.roll(gy, 1, 0)

    ax = 0.5 * (i_r + xp.roll(i_r, -1, 1))
    ay = 0.5 * (i_r + xp.roll(i_r, -1, 0))

    def op(f):  # -div(I_R grad f): symmetric positive semi-definite
        gx, gy = grad(f)
        return -div(ax * gx, ay * gy)

    ny, nx = i_s.shape
    v = xp.asarray(np.fft.fftfreq(ny)[:, None])
    u = xp.asarray(np.fft.fftfreq(nx)[None, :])
    lap = (2 - 2 * xp.cos(2 * np.pi * u)) + (2 - 2 * xp.cos(2 * np.pi * v))
    lap[0, 0] = 1.0
    mean_r = float(i_r.mean())

    def precond(r):
        s = fft.fft2(r) / (lap * mean_r)
        s[0, 0] = 0
        return fft.ifft2(s).real

    x = xp.zeros_like(b)
    r = b - op(x)
    z = precond(r)
    p = z.copy()
    rz = float(xp.vdot(r, z))
    bnorm = float(xp.linalg.norm(b)) or 1.0
    for _ in range(iterations):
        ap = op(p)
        alpha = rz / float(xp.vdot(p, ap))
        x = x + alpha * p
        r = r - alpha * ap
        if float(xp.linalg.norm(r)) < tol * bnorm:
            break
        z = precond(r)
        rz_new = float(xp.vdot(r, z))
        p = z + (rz_new / rz) * p
        rz = rz_new
    residual = xp.abs(i_s - (i_r - (fresnel / (2 * np.pi)) * op(-x)))
    gx, gy = grad(x)
    d = fresnel / (2 * np.pi)
    return TrackingResult(x - x.mean(), xp.zeros_like(x), d * gx, d * gy, residual)
