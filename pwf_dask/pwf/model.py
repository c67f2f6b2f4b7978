"""The PWF model of one projection: the diffuser, propagators, coherence, preconditioner and
regularization window on the computational grid (Eq. (forwardModel), Methods), built once per
diffuser position, and the spectral interpolation between the detector grid and a finer
field grid. Algorithm S2's functions (:mod:`pwf_dask.pwf.operators`) read it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

from pwf_dask.backend import FFT, complex_dtype, real_dtype
from pwf_dask.physics import optics

#: Regularization weights of Algorithm S2: the paper's value (``alpha="paper"``), and the
#: default where the data see the phase as the paper's scene does (the default rule,
#: ``alpha="sensitivity"``, lowers its Im where they see it more weakly). With the paper's
#: Im(alpha) the phase outside the STF fits the noise and beads of 2-12 coherence lengths
#: overshoot by 30-50 % on the paper's diffuser; Im(alpha) = 0.05 holds them within 5 % from
#: 1e3 to 1e5 ph/px (docs/methods.md, "Regularization"), where the discrepancy rule
#: (:func:`pwf_dask.pwf.solver.discrepancy_alpha`) fails at both ends of that range.
PAPER_ALPHA = 0.1 + 0.01j
DEFAULT_ALPHA = 0.1 + 0.05j


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
    #: where the sample's field exp(psi) is formed on a field grid: "field" (exp(U psi)) or
    #: "detector" (U exp(psi), folded into P1's spectrum: :func:`build_model`)
    sample_field_grid: str = "field"


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


#: prime factors of a fast FFT length (:func:`fast_len`)
FAST_LEN_PRIMES = (2, 3, 5, 7)
#: what a fast FFT length must be divisible by (:func:`fast_len`)
FAST_LEN_MULTIPLE = 4


def fast_len(n: int) -> int:
    """The smallest FFT length >= ``n`` with no prime factor above 7 and divisible by 4: the
    padded frame's and the field grid's sides.

    scipy's ``next_fast_len`` admits the factor 11 and odd lengths, which pocketfft handles
    well and MKL (and cuFFT, whose fast radices are 2, 3, 5 and 7) less so. Timed on an AMD
    EPYC (session 52, one thread, 2-D c2c and r2c of every 11-smooth side from 200 to 4100,
    weighed as an iteration's transforms and element-wise work; ``fft_lengths_sizes.md``) this
    rule costs 0.89-0.90 of scipy's choice on MKL on average and 0.96-0.98 on pocketfft. Whole
    iterations, one thread (``benchmarks/results/fft_lengths.md``): a 512^2 frame on 560^2 instead of 550^2
    (2 x 5^2 x 11) 0.69x the time with MKL, its 1.5x field grid 840^2 instead of 825^2 0.76x,
    the camera's 2160 x 2560 frame on 2240 x 2688 instead of 2200 x 2625 0.62x (0.90x on its
    field grid); pocketfft 0.70-1.04x. The set is closed under doubling, so an integer field
    grid is exactly s times a fast grid.

    The longer sides also widen the margin, and the stop rule watches the whole grid: the
    camera frame's margin of 80 x 128 px (40 x 65 under scipy's rule) settles late and holds
    the paper preset's projection to 587 iterations against 284, for the same phase to 0.2 %
    (session 61; docs/validation.md, "Why a grid's size moves a retrieval"), under J's test
    alone; the default stop since session 67 also passes on J's data term and stops it at 300.
    """
    m = max(FAST_LEN_MULTIPLE, -(-int(n) // FAST_LEN_MULTIPLE) * FAST_LEN_MULTIPLE)
    while not _smooth(m):
        m += FAST_LEN_MULTIPLE
    return m


def _smooth(n: int, primes=FAST_LEN_PRIMES) -> bool:
    """Whether ``n`` has no prime factor outside ``primes``."""
    for p in primes:
        while n % p == 0:
            n //= p
    return n == 1


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
    detector_halo_fraction: float = 0.0,
    detector_halo_radius_m: float = 0.0,
    gamma: float = 1.0,
    alpha: complex = DEFAULT_ALPHA,
    use_preconditioner: bool = True,
    upsample: int = 1,
    pad: int = 0,
    precision: str = "single",
    normalization: str = "paper",
    phase_scale: float | str = 1.0,
    field_upsample: float = 1,
    sample_field_grid: str = "field",
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

    ``sample_field_grid="detector"`` forms the sample's field on the detector grid instead,
    U exp(psi), and folds U into P1's spectrum: exp(psi) is transformed on the detector grid,
    zero-padded, multiplied by P1's kernel and transformed back once on the field grid. Six
    complex transforms of the field grid per iteration instead of ten (U and P1's forward
    transform, and their adjoints, merge), at the price of the tilt argument above: exp(psi)
    on the detector grid holds phase gradients below pi rad/pixel only, so the field grid
    then serves t's own spectrum (the aliasing diffuser) and not steep samples.
    Measured: docs/methods.md, "The diffuser estimate and its field grid". With s = 1 the two
    are the same model.

    ``bad_pixels`` (frame-shaped, True = not a measurement, e.g. a zinger) are left out of
    the data term, as the padding margin is: the residual is masked there.

    ``detector_halo_fraction`` and ``detector_halo_radius_m``: the detector spreads that fraction
    of the light over an exponential halo of that 1/e radius (scattered scintillation light), a
    filter beside the IOTF (:func:`pwf_dask.physics.optics.intensity_transfer_function`); not in
    the paper's model, and none by default.
    """
    from pwf_dask.backend import get_array_module

    xp = get_array_module(t)
    fft = fft or FFT.for_module(xp)
    rdt, cdt = real_dtype(precision), complex_dtype(precision)
    shape = tuple(t.shape)
    ny, nx = frame_shape
    frame = (slice(pad, pad + ny), slice(pad, pad + nx))
    mask = _data_mask(shape, frame_shape, frame, bad_pixels, xp, rdt)
    t = t.astype(cdt, copy=False)
    field_upsample = int(field_upsample) if float(field_upsample).is_integer() else float(field_upsample)
    if not field_upsample >= 1:
        raise ValueError(f"field_upsample must be >= 1, got {field_upsample}")
    check_sample_field_grid(sample_field_grid)
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
    otf = optics.intensity_transfer_function(
        shape,
        pixel_size_m,
        coherence_length_x_m,
        coherence_length_y_m,
        detector_halo_fraction,
        detector_halo_radius_m,
        xp,
        rdt,
    )
    if pixel_integration:
        pix = optics.pixel_transfer_function(shape, pixel_size_m, pixel_size_m, xp, rdt)
        otf = pix if otf is None else otf * pix
    alpha = complex(alpha)
    coherence_m = (coherence_length_x_m, coherence_length_y_m)
    reg, reg_phase, precond = _filters(shape, pixel_size_m, coherence_m, gamma, alpha, use_preconditioner, xp, rdt)
    norm = _normalization(tmax, normalization)
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
        sample_field_grid=sample_field_grid if field_upsample > 1 else "field",
    )


#: where :func:`build_model` forms the sample's field exp(psi) on a field grid
SAMPLE_FIELD_GRIDS = ("field", "detector")


def check_sample_field_grid(sample_field_grid: str) -> str:
    """``sample_field_grid`` if it is one of :data:`SAMPLE_FIELD_GRIDS`; else a one-line ValueError."""
    if sample_field_grid not in SAMPLE_FIELD_GRIDS:
        raise ValueError(f"sample_field_grid must be one of {', '.join(SAMPLE_FIELD_GRIDS)}, got {sample_field_grid!r}")
    return sample_field_grid


def _data_mask(shape, frame_shape, frame, bad_pixels, xp, rdt):
    """The data term's weights on the computational grid (1 on measured pixels, 0 on the
    padding and on ``bad_pixels``), or None where every grid pixel is a measurement."""
    if shape == tuple(frame_shape) and bad_pixels is None:
        return None
    mask = xp.zeros(shape, dtype=rdt)
    mask[frame] = 1
    if bad_pixels is not None:
        if tuple(bad_pixels.shape) != tuple(frame_shape):
            raise ValueError(f"bad_pixels has shape {tuple(bad_pixels.shape)}, the frame {tuple(frame_shape)}")
        mask[frame] *= 1 - xp.asarray(bad_pixels, dtype=rdt)
    return mask


def _filters(shape, pixel_size_m, coherence_m, gamma, alpha, use_preconditioner, xp, rdt):
    """(regularization window, its phase weight, preconditioner), None where unused: the window
    (Methods, Regularization window) only with gamma > 0 and alpha != 0; its phase weight
    carries the Laplacian symbol where the preconditioner (Methods, Preconditioning filter) is on."""
    reg = None
    if gamma > 0 and alpha != 0:
        reg = optics.regularization_window(shape, pixel_size_m, *coherence_m, gamma, xp, rdt)
    precond = optics.preconditioner(shape, xp, rdt) if use_preconditioner else None
    reg_phase = None
    if reg is not None:
        reg_phase = reg * optics.laplacian_symbol(shape, xp, rdt) if use_preconditioner else reg
    return reg, reg_phase, precond


def _normalization(tmax: float, normalization: str) -> float:
    """The gradient's normalisation: max |t|^2 as Algorithm S1 prints it ("paper"), or its
    square as the authors' released code has it ("released")."""
    if normalization == "paper":
        return tmax
    if normalization == "released":
        return tmax**2
    raise ValueError(f"normalization must be 'paper' or 'released', not {normalization!r}")


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
