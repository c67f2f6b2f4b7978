"""One projection, end to end: calibration, PWF, background (docs/scan-format.md §4).

:func:`retrieve_projection` is the public entry point every later stage maps over.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from pwf_dask import calibration
from pwf_dask.backend import FFT, get_array_module, to_numpy
from pwf_dask.calibration import sensitivity
from pwf_dask.options import DEFAULTS, RetrievalOptions
from pwf_dask.physics import background as bg
from pwf_dask.physics import optics
from pwf_dask.physics.detector import DEFAULT_OUTLIER_SIGMA, repair_outliers
from pwf_dask.physics.geometry import Geometry
from pwf_dask.physics.materials import delta_beta
from pwf_dask.physics.single_material import paganin_length_m, single_material_phase
from pwf_dask.pwf import solver
from pwf_dask.pwf.model import check_sample_field_grid

logger = logging.getLogger(__name__)

METHODS = ("pwf", "umpa", "lcs", "gf", "mist")

#: The choices of the authors' released MATLAB code (kyeoreh/preconditioned_Wirtinger_flow,
#: ``PWF.m``), as options of :func:`retrieve_projection`, for side-by-side runs: zero-phase
#: diffuser, N_t = (max|t|^2)^2, eta = 1 fixed, Nesterov never restarted, stop at the first
#: pass of the field-correlation rule (the released code tests every 10th iteration), at most
#: 5000 iterations, psi on the detector grid. Not reproduced: its resampling of the images to
#: a pixel of 1/(6 sigma_I) and the Tukey taper of the data term over its padding.
AUTHORS_RELEASE: dict[str, Any] = dict(
    diffuser_model="zero-phase",
    normalization="released",
    step=1.0,
    step_search=False,
    restart="none",
    min_iter=1,
    patience=1,
    rtol=0.0,
    jtol=0.0,
    max_iter=5000,
    field_upsample=1,
)


#: ``alpha`` spelled by name: "sensitivity" scales the default Im(alpha) to the
#: data's phase sensitivity (:func:`pwf_dask.pwf.solver.sensitivity_alpha`), "discrepancy"
#: chooses it by the residual (:func:`pwf_dask.pwf.solver.discrepancy_alpha`), "paper" is the
#: paper's 0.1 + 0.01i.
ALPHA_RULES = ("sensitivity", "discrepancy", "paper")


def parse_alpha(alpha) -> complex | str:
    """``alpha`` as "sensitivity", "discrepancy" or a complex number; one line naming the option
    otherwise."""
    if isinstance(alpha, str):
        text = alpha.replace(" ", "").lower()
        if text in ("discrepancy", "sensitivity"):
            return text
        if text == "paper":
            return solver.PAPER_ALPHA
        try:
            alpha = complex(text)
        except ValueError:
            raise ValueError(
                f"alpha must be 'sensitivity', 'discrepancy', 'paper' or a complex number like 0.1+0.01j, got {alpha!r}"
            ) from None
    alpha = complex(alpha)
    if not (np.isfinite(alpha.real) and np.isfinite(alpha.imag)) or alpha.real < 0 or alpha.imag < 0:
        raise ValueError(f"alpha must have finite, non-negative real and imaginary parts, got {alpha}")
    return alpha


def residual_rmse_pct(sol, model, excluded=None) -> float:
    """RMS of the data residual over the frame's fitted pixels, in % of the mean reference."""
    res = to_numpy(abs(sol.evaluation.r[model.frame])) * 100.0
    fitted = res[~to_numpy(excluded)] if excluded is not None else res
    return float(np.sqrt(np.mean(fitted.astype(np.float64) ** 2)))


@dataclass
class RetrievalResult:
    """Phase and attenuation of one projection (arrays of the input's kind and shape)."""

    phase: Any  # Im(psi), rad, background ~ 0
    attenuation: Any  # -Re(psi), >= 0 for matter
    iterations: int
    converged: bool
    residual: Any  # |y - f| in % of the mean reference, per pixel
    residual_rmse: float  # RMS of ``residual`` (%)
    loss_history: list[float]
    coherence_length_x_m: float
    coherence_length_y_m: float
    parameters: dict = field(default_factory=dict)
    background: Any = None  # boolean mask of the pixels the plane was fitted on


def _check_real(name: str, a) -> None:
    """Intensities are real numbers: a complex image (its imaginary part would be dropped with
    a warning) or a boolean mask is refused in one line."""
    kind = a.dtype.kind
    if kind not in "uif":
        raise ValueError(f"{name} must hold real intensities, got dtype {a.dtype}")


def _unmasked(name: str, a):
    """``a``, refused where it is a masked array with masked pixels: ``asarray`` would drop the
    mask and the masked pixels would be fitted as measured."""
    if isinstance(a, np.ma.MaskedArray) and np.ma.is_masked(a):
        hint = "its filled data and, for PWF, the mask as bad_pixels" if name == "sample" else "unmasked frames"
        raise ValueError(f"{name} is a masked array: pass {hint}")
    return a


def _check_image(name: str, a, xp) -> Any:
    if a is None:
        raise ValueError(f"{name} is missing")
    a = xp.asarray(_unmasked(name, a))
    _check_real(name, a)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D image, got {a.ndim} dimensions")
    if min(a.shape) < 16:
        raise ValueError(f"{name} is {a.shape}: at least 16 x 16 pixels are needed")
    if not bool(xp.all(xp.isfinite(a))):
        hint = ": fill them, and for PWF pass them as bad_pixels (left out of the fit)" if name == "sample" else ""
        raise ValueError(f"{name} has non-finite values (NaN or inf){hint}")
    if bool(xp.any(a < 0)):
        raise ValueError(f"{name} has negative values: pass flat/dark-corrected intensities")
    return a


def auto_pad(pixel_size_m: float, wavelength: float, l2_m: float, x_coh_m: float, y_coh_m: float) -> int:
    """Margin (px) that holds what enters the frame from outside: the diffraction spread
    lambda L2 / (2 p) of the finest detector frequency plus two coherence lengths of blur."""
    spread = wavelength * l2_m / (2 * pixel_size_m)
    blur = 2 * max(x_coh_m, y_coh_m)
    return int(math.ceil((spread + blur) / pixel_size_m))


def auto_upsample(pixel_size_m: float, x_coh_m: float, y_coh_m: float, threshold: float = 0.02) -> int:
    """2 when |v|^2 on the detector grid would alias into the IOTF's passband, else 1.

    A field band-limited to the detector Nyquist 1/(2p) has |v|^2 up to 1/p; on the detector
    grid the part above 1/(2p) folds back onto 1/p - q. It matters where the IOTF still
    passes the folded frequencies: IOTF(1/(2p)) (the least folded) above ``threshold``.
    """
    if x_coh_m == 0 and y_coh_m == 0:
        return 2
    c = max(x_coh_m, y_coh_m) if min(x_coh_m, y_coh_m) == 0 else min(x_coh_m, y_coh_m)
    q = 0.5 / pixel_size_m
    return 2 if math.exp(-0.5 * math.pi * q * q * c * c) > threshold else 1


#: The authors' released code resamples every image to a working pixel of 1/(6 sigma_I), sigma_I =
#: sqrt(2/pi) / x_coh the intensity bandwidth (the Nyquist frequency at 3 sigma_I), i.e.
#: sqrt(pi/2)/6 = 0.209 of the shorter coherence length: 0.72-0.79 um at the paper's 3.47-3.78 um,
#: just above its 0.65 um detector pixel, so the paper's scenes ran on their detector grid.
WORKING_PIXEL_PER_COHERENCE_LENGTH = math.sqrt(math.pi / 2) / 6


def auto_field_upsample(pixel_size_m: float, x_coh_m: float, y_coh_m: float, max_factor: int = 4) -> int:
    """The field grid's refinement s that brings its pixel to at most the released code's
    working pixel (:data:`WORKING_PIXEL_PER_COHERENCE_LENGTH` x the shorter coherence length);
    1 (the detector grid, nothing computed) at the paper's geometry and finer pixels.

    Coarser detector pixels sample the diffuser's field (grains below the pixel) too coarsely
    for its product with the sample's field: on the detector grid the product aliases and the
    phase does not move. Measured on 256^2 scenes, seed 1 (relative phase error, detector grid
    -> s): 1.3 um pixels (s = 2) 0.93 -> 0.17; 15 keV, 1 um pixels, L2 = 50 mm (s = 2) 0.18 ->
    0.057, each in 0.5x the time (the detector grid ran to its 2000-iteration cap).
    """
    lengths = [c for c in (x_coh_m, y_coh_m) if c > 0]
    if not lengths:
        return 1  # full coherence: no intensity bandwidth to scale the grid by
    ratio = pixel_size_m / (WORKING_PIXEL_PER_COHERENCE_LENGTH * min(lengths))
    return int(min(max(math.ceil(ratio - 1e-9), 1), max_factor))


#: Robust maximum of |grad phase| (rad per detector pixel, :func:`phase_gradient_rad_per_px`)
#: of the detector-grid solution above which ``field_upsample="auto"`` goes on with the field
#: on a 2x finer grid. The detector-grid model aliases gradients above pi and its own
#: solution undershoots them, so the threshold sits at pi / 2. Measured on the stability
#: map's rod (256^2, 1e4 ph/px; the statistic of the detector-grid solution): 10 pi 0.94
#: (the finer grid changes nothing there: phase error 0.061 against 0.060), 30 pi 2.63 (error
#: 0.47 -> 0.17), 100 pi 3.01 (0.78 -> 0.57); noise stays below: 1e2 ph/px 0.83.
FIELD_UPSAMPLE_GRADIENT_RAD_PER_PX = math.pi / 2


#: Share of the diffuser transmission's power above :data:`DIFFUSER_ALIASING_FREQUENCY` (cycles
#: per pixel) from which ``field_upsample="auto"`` puts the field on a finer grid
#: (:data:`DIFFUSER_FIELD_UPSAMPLE`). A
#: single-material fit to coarse grains (P3000 at 0.65 um pixels) is a phase screen whose
#: gradients reach ~pi rad/px: its spectrum runs to the Nyquist frequency, and the sample's
#: tilt wraps that part around the detector grid, moving it the wrong way. Measured (256^2,
#: true lengths; share, phase gain on the detector grid -> 2x grid): grains of 1.2 um radius
#: 0.038, 0.964 -> 0.968; 2.0 um 0.079, 0.888 -> 0.943; 3.25 um 0.103, 0.822 -> 0.971;
#: 4.5 um 0.117, 0.861 -> 1.004. The paper's zero-phase estimate is band-limited (~0.01).
DIFFUSER_ALIASING_FRACTION = 0.06
DIFFUSER_ALIASING_FREQUENCY = 0.35
#: The field grid ``"auto"`` takes for an aliasing diffuser. Its Nyquist frequency, 0.75
#: cycles per detector pixel, holds t's spectrum (to 0.5) tilted by sample gradients up to
#: pi/2 rad/px. Measured (P3000, calibrated lengths, 1e4 ph/px; phase gain at 1 / 1.25 / 1.5 /
#: 2x): 256^2 seeds 1-3 0.907-0.882-0.889 / 1.002-0.998-0.986 / 1.008-1.001-0.993 /
#: 1.008-1.000-0.992; 512^2 0.896 / 0.991 / 0.994 / 0.994, the largest bead's contrast +4.2 %
#: at 1.5x and 2x. 1.5x costs 2.25x the detector grid's pixels against 2x's 4x: 38.7 against
#: 62.0 FFT-times per iteration at 1024^2 (benchmarks/results/field_grid.md).
DIFFUSER_FIELD_UPSAMPLE: float = 1.5


def field_gradient_limit(field_upsample: float, diffuser_aliases: bool) -> float:
    """The solution's phase gradient (rad per detector pixel) above which ``"auto"`` goes on
    with a field grid twice as fine: pi/2 per step of the grid, and for an aliasing diffuser
    (whose spectrum fills the detector band) the tilt that wraps it, pi (s - 1)."""
    limit = FIELD_UPSAMPLE_GRADIENT_RAD_PER_PX * field_upsample
    return min(limit, math.pi * (field_upsample - 1)) if diffuser_aliases else limit


def check_field_upsample(field_upsample) -> int | float | str:
    """``"auto"`` or a number >= 1 (an integer where it is one); else a one-line ValueError."""
    if field_upsample == "auto":
        return field_upsample
    try:
        s = float(field_upsample)
    except (TypeError, ValueError):
        s = math.nan
    if not (1 <= s <= 8):
        raise ValueError(f"field_upsample must be 'auto' or a number from 1 to 8, got {field_upsample!r}")
    return int(s) if s.is_integer() else s


def diffuser_aliasing(t, fft: FFT | None = None) -> float:
    """Share of |t_k|^2 above :data:`DIFFUSER_ALIASING_FREQUENCY` cycles per pixel (one FFT)."""
    xp = get_array_module(t)
    fft = fft or FFT.for_module(xp)
    power = xp.abs(fft.fft2(t)) ** 2
    v, u = optics.frequency_grid(tuple(t.shape))
    high = xp.asarray((u * u + v * v) > DIFFUSER_ALIASING_FREQUENCY**2)
    return float(xp.sum(power[high]) / xp.sum(power))


def phase_gradient_rad_per_px(phase, percentile: float = 99.0, smooth_px: float = 2.0) -> float:
    """A robust maximum of |grad phase| in rad per pixel: the ``percentile`` of the gradient
    magnitude (central differences) of the phase smoothed by a Gaussian of ``smooth_px``, so
    that noise (pixel-scale) does not count and refraction (the speckle-moving scale) does."""
    from scipy import ndimage

    phi = np.asarray(to_numpy(phase), dtype=np.float64)
    if smooth_px > 0:
        phi = ndimage.gaussian_filter(phi, smooth_px)
    gy, gx = np.gradient(phi)
    return float(np.percentile(np.hypot(gx, gy), percentile))


def computational_shape(frame_shape: tuple[int, int], pad: int) -> tuple[int, int]:
    """The FFT grid of a frame padded by ``pad`` pixels each side (fast FFT lengths)."""
    ny, nx = frame_shape
    return (solver.fast_len(ny + 2 * pad), solver.fast_len(nx + 2 * pad)) if pad else (ny, nx)


def diffuser_grid(
    frame_shape: tuple[int, int],
    *,
    energy_eV: float,
    pixel_size_m: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pad: int | str = "auto",
    diffuser_upstream_m: float = 0.0,
) -> tuple[int, tuple[int, int]]:
    """(pad, computational grid shape) of :func:`estimate_diffuser` for a frame: "auto" pads
    by the speckle's spread over the diffuser's whole distance to the detector."""
    if pad == "auto":
        pad = auto_pad(
            pixel_size_m,
            optics.wavelength_m(energy_eV),
            diffuser_detector_distance_m + diffuser_upstream_m,
            coherence_length_x_m,
            coherence_length_y_m,
        )
    return int(pad), computational_shape(tuple(frame_shape), int(pad))


def estimate_diffuser(
    reference,
    *,
    energy_eV: float,
    pixel_size_m: float,
    diffuser_detector_distance_m: float,
    coherence_length_x_m: float,
    coherence_length_y_m: float,
    pad: int | str = DEFAULTS.pad,
    diffuser_model: str = DEFAULTS.diffuser_model,
    diffuser_material: str = DEFAULTS.diffuser_material,
    diffuser_beta_over_delta: float | None = DEFAULTS.diffuser_beta_over_delta,
    diffuser_refine_iter: int = DEFAULTS.diffuser_refine_iter,
    diffuser_nsr_floor: float | str = DEFAULTS.diffuser_nsr_floor,
    sample=None,
    phase_screen_iter: int = DEFAULTS.phase_screen_iter,
    diffuser_upstream_m: float = DEFAULTS.diffuser_upstream_m,
    detector_halo_fraction: float = DEFAULTS.detector_halo_fraction,
    detector_halo_radius_m: float = DEFAULTS.detector_halo_radius_m,
    fft_workers: int | None = None,
):
    """The diffuser t_r exactly as :func:`retrieve_projection` estimates it with the same
    options, for passing as its ``diffuser``: a scan computes it once per diffuser position.
    ``sample``: a sample image of the position, whose photon noise sets the Wiener filters'
    floor under ``diffuser_nsr_floor="sample"`` (:func:`calibration.diffuser.resolved_nsr_floor`;
    none given: the reference's own ratio)."""
    xp = get_array_module(reference)
    ref = _check_image("reference", reference, xp)
    nsr_floor, sample_noise_var = calibration.diffuser.resolved_nsr_floor(diffuser_nsr_floor, sample)
    wavelength = optics.wavelength_m(energy_eV)
    pad, shape = diffuser_grid(
        ref.shape,
        energy_eV=energy_eV,
        pixel_size_m=pixel_size_m,
        diffuser_detector_distance_m=diffuser_detector_distance_m,
        coherence_length_x_m=coherence_length_x_m,
        coherence_length_y_m=coherence_length_y_m,
        pad=pad,
        diffuser_upstream_m=diffuser_upstream_m,
    )
    diffuser_model, kappa = chosen_diffuser_model(
        diffuser_model, diffuser_material, diffuser_beta_over_delta, energy_eV
    )
    scale = float(xp.mean(ref))
    if not scale > 0:
        raise ValueError("reference has zero mean intensity")
    return calibration.diffuser_transmission(
        ref / scale,
        pixel_size_m=pixel_size_m,
        wavelength=wavelength,
        diffuser_detector_distance_m=diffuser_detector_distance_m,
        coherence_length_x_m=coherence_length_x_m,
        coherence_length_y_m=coherence_length_y_m,
        pad=pad,
        shape=shape,
        phase_screen_iter=phase_screen_iter,
        diffuser_model=diffuser_model,
        beta_over_delta=kappa,
        refine_iter=diffuser_refine_iter,
        nsr_floor=nsr_floor,
        sample_noise_var=sample_noise_var,
        upstream_m=diffuser_upstream_m,
        detector_halo_fraction=detector_halo_fraction,
        detector_halo_radius_m=detector_halo_radius_m,
        fft=FFT.for_module(xp, fft_workers),
    )


def choose_diffuser(
    sample,
    reference,
    *,
    energy_eV: float,
    pixel_size_m: float,
    sample_diffuser_distance_m: float,
    diffuser_detector_distance_m: float,
    options: RetrievalOptions | None = None,
    bad_pixels=None,
    **keywords,
) -> DiffuserChoice:
    """The diffuser model and t_r that :func:`retrieve_projection` would take on this pair with
    these options, ``"auto"``'s probe included (:func:`probes_diffuser`), and its giving up the
    fit for zero phase under the alpha rule (:func:`alpha_rule_gives_up`): a scan chooses once
    per diffuser position and passes ``diffuser=choice.transmission`` with
    ``diffuser_model=choice.model`` to every projection of it.

    Parameters
    ----------
    sample, reference
        One flat/dark-corrected projection and its reference, as :func:`retrieve_projection`
        takes them.
    energy_eV, pixel_size_m, sample_diffuser_distance_m, diffuser_detector_distance_m
        The geometry.
    options, bad_pixels, **keywords
        As :func:`retrieve_projection`'s.

    Returns
    -------
    DiffuserChoice
        The model, t_r where the reference was taken (not moved by a drift), kappa, and each
        model's probe residual in % ({} where nothing was probed).
    """
    opts = RetrievalOptions.from_keywords(options, **keywords)
    geometry = Geometry(
        energy_eV, pixel_size_m, sample_diffuser_distance_m, diffuser_detector_distance_m, opts.diffuser_upstream_m
    )
    pair, opts, _, kappa = _prepared_pair(sample, reference, opts, geometry, bad_pixels)
    t = _transmission(pair.ref, pair.y, None, opts, geometry, pair.coherence, pair.fft)
    if probes_diffuser(pair.requested, opts.diffuser_model):
        return _probed_diffuser(t, pair, opts, geometry)
    guarded, residuals = _guarded_alpha(opts, pair, t, None, geometry)
    if guarded.diffuser_model != opts.diffuser_model:  # "auto" gave the fit up for zero phase
        t = _transmission(pair.ref, pair.y, None, guarded, geometry, pair.coherence, pair.fft)
        return DiffuserChoice(guarded.diffuser_model, t, None, residuals)
    return DiffuserChoice(opts.diffuser_model, t, kappa, {})


def probe_diffuser_models(
    sample, reference, geometry: Geometry, *, options: RetrievalOptions | None = None, bad_pixels=None, **keywords
) -> dict:
    """Each diffuser model's data residual (% of the mean reference) after
    :data:`DIFFUSER_PROBE_ITER` iterations on this pair's :func:`probe_window`, as
    ``"auto"``'s probe and the alpha rule's check (:func:`alpha_rule_holds`) read them: a scan
    checks the rule once on one projection. ``geometry`` less the upstream distance, which the
    options give; the rest as :func:`choose_diffuser`'s."""
    opts = RetrievalOptions.from_keywords(options, **keywords)
    geometry = replace(geometry, diffuser_upstream_m=opts.diffuser_upstream_m)
    pair, opts, _, _ = _prepared_pair(sample, reference, opts, geometry, bad_pixels)
    return _probe_residuals(pair, opts, geometry, {})[0]


def sample_delta_over_beta_of(material: str, delta_over_beta: float | None, energy_eV: float) -> float:
    """The one delta/beta MIST and PWF's ``single_material`` assume: the given value, else the
    material's at the energy."""
    if delta_over_beta is not None:
        if not (math.isfinite(delta_over_beta) and delta_over_beta > 0):
            raise ValueError(f"sample_delta_over_beta must be positive, got {delta_over_beta}")
        return float(delta_over_beta)
    delta, beta = delta_beta(material, energy_eV)
    return delta / beta


def check_single_material(single_material: bool, method: str) -> None:
    """``single_material`` is PWF's option (MIST assumes one material by construction)."""
    if single_material and method != "pwf":
        raise ValueError(f"single_material applies to method 'pwf', not {method!r}")


def _single_material_prior(on: bool, material: str, delta_over_beta: float | None, geometry: Geometry) -> dict:
    """What ``single_material`` records: the ratio and Paganin's filter width, checked before
    any work."""
    if not on:
        return {"single_material": False}
    ratio = sample_delta_over_beta_of(material, delta_over_beta, geometry.energy_eV)
    length = paganin_length_m(geometry.wavelength_m, geometry.sample_detector_distance_m, ratio)
    return {"single_material": True, "sample_delta_over_beta": ratio, "paganin_length_m": length}


def chosen_diffuser_model(
    model: str, material: str, beta_over_delta: float | None, energy_eV: float
) -> tuple[str, float | None]:
    """The diffuser model that ``model`` asks for (``"auto"`` resolved by the diffuser's linear
    attenuation coefficient 2 k delta kappa, :func:`pwf_dask.calibration.choose_diffuser_model`)
    and its kappa = beta/delta (the one given, else its material's at the energy), None for
    zero phase."""
    if model == "zero-phase":
        return model, None
    if beta_over_delta is not None and not beta_over_delta >= 0:
        raise ValueError(f"diffuser_beta_over_delta must be >= 0, got {beta_over_delta}")
    delta, beta = delta_beta(material, energy_eV)
    kappa = beta / delta if beta_over_delta is None else float(beta_over_delta)
    mu = 2 * (2 * math.pi / optics.wavelength_m(energy_eV)) * delta * kappa
    model = calibration.choose_diffuser_model(model, mu)
    return model, (kappa if model == "single-material" else None)


#: Smallest measured drift (pixels, either axis) that ``diffuser_drift="auto"`` corrects on a
#: large frame: 0.05 px moves the phase error less than a new noise draw does, so a still
#: diffuser leaves the model exactly the paper's. Small frames hold fewer grains and the
#: estimate scatters more (measured at most ~4 / sqrt(pixels): 0.02 at 256^2, 0.08 at 32 x 64),
#: so the threshold is twice that where larger (:func:`drift_threshold_px`).
DRIFT_MIN_PX = 0.05
#: Frame strips the drift brought in from outside the reference are left out of the data term,
#: widened by this many pixels: the speckle there also depends on its neighbours' t_r (L2's
#: Fresnel spread, sqrt(lambda L2) = 2.4 px at the paper's set-up).
DRIFT_MARGIN_PX = 2


def check_solver_options(
    max_iter,
    tol,
    gamma,
    step,
    phase_scale=1.0,
    stationary_terms=solver.STOP_RULE.stationary_terms,
    low_band_atol_rad=solver.STOP_RULE.low_band_atol_rad,
) -> None:
    """Algorithm S1's numbers, each in its range, refused in one line naming the option
    (issue #28: ``--max-iter -5`` crashed deep in the solver, ``--tol -1`` never stopped)."""
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be a whole number >= 1, got {max_iter!r}")
    checks = (
        ("tol", tol, 0.0, True),
        ("gamma", gamma, 0.0, True),
        ("step", step, 0.0, False),
        ("low_band_atol_rad", low_band_atol_rad, 0.0, True),
    )
    for name, value, low, inclusive in checks:
        v = float(value)
        if not math.isfinite(v) or v < low or (v == low and not inclusive):
            raise ValueError(f"{name} must be {'>=' if inclusive else '>'} {low:g} and finite, got {value!r}")
    if phase_scale != "auto" and not (math.isfinite(float(phase_scale)) and float(phase_scale) > 0):
        raise ValueError(f"phase_scale must be 'auto' or a number > 0, got {phase_scale!r}")
    solver.check_stationary_terms(stationary_terms)


def drift_threshold_px(frame_shape: tuple[int, int]) -> float:
    """The drift ``diffuser_drift="auto"`` corrects from: :data:`DRIFT_MIN_PX`, or twice the
    estimate's scatter on a frame of this many pixels where that is larger."""
    return max(DRIFT_MIN_PX, 8.0 / float(np.sqrt(frame_shape[0] * frame_shape[1])))


def check_diffuser_drift(diffuser_drift) -> tuple[float, float] | None:
    """A given (dy, dx) drift as floats (also from "DY,DX"), None for "auto" and "off";
    anything else is refused with one line."""
    if isinstance(diffuser_drift, str) and diffuser_drift in ("auto", "off"):
        return None
    values = diffuser_drift.split(",") if isinstance(diffuser_drift, str) else diffuser_drift
    try:
        dy, dx = (float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(
            f"diffuser_drift must be 'auto', 'off' or a (dy, dx) pair in pixels, got {diffuser_drift!r}"
        ) from None
    if not (np.isfinite(dy) and np.isfinite(dx)):
        raise ValueError(f"diffuser_drift must be finite, got ({dy}, {dx})")
    return dy, dx


def measured_drift(sample, reference, diffuser_drift, fft: FFT | None = None) -> tuple[tuple[float, float], Any]:
    """The diffuser's drift (dy, dx) px between ``reference`` and ``sample`` as
    ``diffuser_drift`` asks ("auto": measured by :func:`pwf_dask.calibration.speckle_drift_px`;
    "off": none; or given), and the frame pixels whose grains the reference never saw, or
    None where the drift is not corrected ("auto" below :func:`drift_threshold_px`, "off",
    or a given (0, 0)). A drift that brings in most of the frame is refused with one line."""
    given = check_diffuser_drift(diffuser_drift)
    drift = (0.0, 0.0)
    if given is not None:
        drift = given
    elif diffuser_drift == "auto":
        drift = calibration.speckle_drift_px(sample, reference, fft=fft)
    largest = max(abs(drift[0]), abs(drift[1]))
    if not (largest > 0 if given is not None else largest >= drift_threshold_px(tuple(sample.shape))):
        return drift, None
    unseen = calibration.unseen_by_reference(tuple(sample.shape), drift, DRIFT_MARGIN_PX)
    if unseen.mean() > 0.5:
        raise ValueError(
            f"the diffuser drifted ({drift[0]:.2f}, {drift[1]:.2f}) px since the reference: most of the "
            "frame's speckle was never in it; take a new reference"
        )
    return drift, unseen


def retrieve_projection(
    sample,
    reference,
    *,
    energy_eV: float,
    pixel_size_m: float,
    sample_diffuser_distance_m: float,
    diffuser_detector_distance_m: float,
    options: RetrievalOptions | None = None,
    diffuser=None,
    background_mask=None,
    bad_pixels=None,
    **keywords,
) -> RetrievalResult:
    """Retrieve phase and attenuation from one flat/dark-corrected speckle image (docs/scan-format.md §4).

    Parameters
    ----------
    sample, reference : 2-D NumPy or CuPy arrays
        Flat/dark-corrected speckle images with and without the sample, of one shape.
    energy_eV, pixel_size_m : float
        Photon energy and detector pixel size.
    sample_diffuser_distance_m, diffuser_detector_distance_m : float
        L1 and L2 of Eq. (forwardModel); L1 = 0 skips the first propagation.
    options : RetrievalOptions, optional
        The options below as one object (:class:`pwf_dask.options.RetrievalOptions`, defaults
        :data:`pwf_dask.options.DEFAULTS`, each defined there once); keywords given beside it
        replace its fields.
    **keywords
        The options one by one, as named below; a name that is no option is refused in one
        line naming the nearest option.
    method : {"pwf", "umpa", "lcs", "gf", "mist"}
        PWF, or a speckle-tracking baseline (:func:`retrieve_tracking`; ``tracking_options``,
        ``sample_material`` and ``sample_delta_over_beta`` (MIST) go to it).
    max_iter, tol, min_iter, patience, rtol, jtol, low_band_atol_rad, stationary_terms : stop rule
        :class:`pwf_dask.pwf.solver.StopRule`: ``tol`` is 1 - the field correlation of
        successive iterates (the paper's 1 - 10^-0.00001), ``tol=0`` runs ``max_iter``;
        ``low_band_atol_rad`` (0: off): the phase's wide structure is not settled while it
        moved that much (rms, rad) over the last window (0.05 holds a deep rod's cold crop that
        stops early otherwise; docs/user-guide.md);
        ``stationary_terms="j-or-data"`` (the default) lets J's data term pass the J test too
        (large frames whose padding margin settles late: the camera frame 300 iterations for
        587); ``"j"`` watches J alone (the rule before session 67).
    gamma, alpha : float, complex or str
        Regularization window width over the STF and weights, Eq. (regularization window) and
        Algorithm S2: ``"sensitivity"`` (the default: 0.1+0.05j, its imaginary part lowered
        where the data see the phase weakly, :func:`pwf_dask.pwf.solver.sensitivity_alpha`),
        a complex number, ``"paper"`` (0.1+0.01j) or ``"discrepancy"`` (:func:`parse_alpha`);
        ``gamma=0`` or ``alpha=0``: no regularizer.
    step, step_search, restart : float, bool, str
        eta of Algorithm S1 (in units of 1/L with ``step_search``) and the momentum restart of
        :func:`pwf_dask.pwf.solver.pwf` (``"none"``: Algorithm S1 as printed).
    coherence_length_x_m, coherence_length_y_m : float, optional
        Coherence lengths of the IOTF, Eq. (IOTF); calibrated from the reference when not given
        (:func:`pwf_dask.calibration.fit_coherence_lengths` by ``coherence_method``,
        ``"template"`` or ``"gaussian"``, the paper's Siegert fit). The model integrates over the
        pixel on top of the IOTF unless ``coherence_includes_pixel_blur`` (the Gaussian fit's do).
    preconditioner : bool
        The inverse-Laplacian preconditioner of the phase, Eq. (preconditioner) (ablation switch).
    precision : {"single", "double"}
        complex64 or complex128 iterations.
    upsample, pad, field_upsample : int, float or "auto"
        |v|^2 on a finer grid where it would alias; the computational grid extended by ``pad``
        pixels each side; exp(psi), t and both propagations on a grid ``field_upsample`` times
        finer (Notes).
    phase_screen_iter, diffuser_model, diffuser_material, diffuser_beta_over_delta, diffuser_refine_iter
        The diffuser estimate t_r (Notes); ``diffuser`` passes one computed before
        (:func:`estimate_diffuser`), on the computational grid.
    diffuser_upstream_m : float
        Not in the paper; needs L1 = 0: the diffuser that far upstream of the sample.
    background_mask, zero_background : array of bool, bool
        Sample-free pixels (True) that override the detected background; whether the phase and
        attenuation are zeroed there by a fitted plane (:mod:`pwf_dask.physics.background`).
    bad_pixels : array of bool, optional
        Not in the paper; PWF only: sample pixels that are no measurement (True), such as raw
        counts saturated at the detector's full scale (the workflow finds those); left out of
        the data term, as the detector test's spikes are.
    normalization, phase_scale : str, float or "auto"
        The objective's scale (the paper's) and the metric scale kappa of the phase block.
    fft_workers : int, optional
        FFT threads of this call (default: the process's budget).
    initial : {"zero", "umpa"} or complex array
        Start of Algorithm S1: zero (the paper), UMPA's one-image estimate, or a given psi.
    outlier_sigma : float or None
        Zingers and hot pixels beyond this many sigma are repaired first
        (:mod:`pwf_dask.physics.detector`); None leaves the images untouched.
    diffuser_drift : {"auto", "off"} or (dy, dx)
        Not in the paper: t_r moved to where the diffuser was for the sample frame (Notes).
    single_material : bool
        Not in the paper: the sample is one material, ``sample_material`` (xraydb) or
        ``sample_delta_over_beta``; the phase's low spatial frequencies are then taken from the
        attenuation through Paganin's filter (:mod:`pwf_dask.physics.single_material`), for
        thick samples whose sharp edges PWF's pixel grid cannot hold. Off by default: wrong
        for a sample of several materials.

    Returns
    -------
    RetrievalResult
        ``phase`` (Im psi, rad) and ``attenuation`` (-Re psi) of the input's kind and shape,
        ``iterations``, ``converged``, the per-pixel ``residual`` and its ``residual_rmse`` (% of
        the mean reference), ``loss_history``, the coherence lengths used, and ``parameters``
        (every choice made, e.g. the field grid and the diffuser fit; ``background_planes``:
        the planes the background fit subtracted, [constant, row slope, column slope] per frame
        height and width, or None).

    Raises
    ------
    ValueError
        A bad image, option or geometry, in one line naming it.

    Notes
    -----
    The diffuser t_r is estimated from the reference (:mod:`pwf_dask.calibration.diffuser`):
    ``diffuser_model="single-material"`` fits exp(-(kappa + i) theta) with kappa =
    ``diffuser_beta_over_delta`` or, when None, beta/delta of ``diffuser_material`` at the
    energy (xraydb) in ``diffuser_refine_iter`` L-BFGS iterations; ``"zero-phase"`` is the
    paper's estimate; ``"auto"`` (default) takes the single material where the diffuser's
    linear attenuation coefficient reaches :data:`pwf_dask.calibration.AUTO_MIN_ATTENUATION_PER_M`
    (5 /mm: silicon carbide up to ~11 keV), else zero phase unless a probe of
    :data:`DIFFUSER_PROBE_ITER` iterations of each model on this sample leaves the single
    material under :data:`DIFFUSER_PROBE_RATIO` of zero phase's data residual
    (``parameters["diffuser_probe_residual_pct"]``; :func:`choose_diffuser` makes the choice
    once for many projections), and records the choice (``parameters["diffuser_model"]``,
    beside ``"diffuser_model_requested"``). A ``diffuser`` given is used as given, unprobed.
    With ``diffuser_upstream_m`` t_r is the fitted diffuser's field at the
    sample plane (:func:`pwf_dask.calibration.diffuser_transmission`).

    ``field_upsample="auto"`` starts on the grid of :func:`auto_field_upsample` (the detector
    grid unless the pixel is coarser than the authors' working pixel), on a
    :data:`DIFFUSER_FIELD_UPSAMPLE` (1.5x) grid at least when the diffuser estimate aliases
    there (:func:`diffuser_aliasing` above :data:`DIFFUSER_ALIASING_FRACTION`: coarse grains),
    and goes on with one twice as fine when the solution's phase gradient exceeds
    :func:`field_gradient_limit` (thick samples); 1 is the paper's model, and a number >= 1
    (fractional too) fixes the grid (:func:`pwf_dask.pwf.solver.build_model`).
    :data:`AUTHORS_RELEASE` holds the choices of the authors' released code.

    ``diffuser_drift="auto"`` measures the speckle's global shift against the reference
    (:func:`pwf_dask.calibration.speckle_drift_px`) and moves t_r when it reaches
    :func:`drift_threshold_px` (0.05 px on frames from 160^2), leaving out of the data term the
    strips whose grains came from outside the reference; ``"off"`` never; a (dy, dx) pair in
    pixels moves it by that.

    References
    ----------
    The PWF paper (single-shot speckle-based X-ray phase microtomography by preconditioned
    Wirtinger flow): Eq. (forwardModel), Methods (IOTF, Diffuser transmission function,
    Preconditioning filter, Regularization window) and Algorithms S1/S2; docs/methods.md maps
    each to its function.
    """
    opts = RetrievalOptions.from_keywords(options, **keywords)
    if opts.method not in METHODS:
        raise ValueError(f"unknown method {opts.method!r}: choose one of {', '.join(METHODS)}")
    check_single_material(opts.single_material, opts.method)
    if opts.method != "pwf":
        if bad_pixels is not None:
            raise ValueError(f"bad_pixels: only PWF leaves pixels out of its fit, not {opts.method}")
        return _retrieve_by_tracking(
            sample, reference, opts, energy_eV, pixel_size_m, diffuser_detector_distance_m, background_mask
        )
    geometry = Geometry(
        energy_eV, pixel_size_m, sample_diffuser_distance_m, diffuser_detector_distance_m, opts.diffuser_upstream_m
    )
    pair, opts, prior, kappa = _prepared_pair(sample, reference, opts, geometry, bad_pixels, background_mask)
    y, ref, scale, excluded, fft, coherence = pair.y, pair.ref, pair.scale, pair.excluded, pair.fft, pair.coherence
    xp = get_array_module(y)
    background_mask = pair.background_mask
    drift, unseen, moved = pair.drift, pair.unseen, pair.unseen is not None
    t = _transmission(ref, y, diffuser, opts, geometry, coherence, fft)
    probe = None
    if diffuser is None and probes_diffuser(pair.requested, opts.diffuser_model):
        probe = _probed_diffuser(t, pair, opts, geometry)
        t, kappa = probe.transmission, probe.beta_over_delta
        opts = replace(opts, diffuser_model=probe.model)
    guard = None
    if diffuser is None:  # a given diffuser is used as given, unprobed
        fitted = opts.diffuser_model
        opts, guard = _guarded_alpha(opts, pair, t, probe, geometry)
        if opts.diffuser_model != fitted:  # "auto" gave the fit up for zero phase
            t, kappa = _transmission(ref, y, None, opts, geometry, coherence, fft), None
    if moved:
        t = calibration.shift_transmission(t, drift, fft=fft)
    build = _model_builder(t, y.shape, geometry, coherence, opts, excluded, fft)
    grid = _first_field_grid(
        opts.field_upsample, t, pixel_size_m, coherence.x_m, coherence.y_m, fft, opts.sample_field_grid
    )
    model = build(field_upsample=grid.field_upsample, sample_field_grid=grid.sample_field_grid)
    y_full = xp.zeros(model.shape, dtype=model.rdtype)
    y_full[model.frame] = y / scale
    # a UMPA start follows the drift measured above rather than measuring it again
    start_options = {**(opts.tracking_options or {}), "diffuser_drift": drift if moved else "off"}
    psi0 = _initial_psi(
        opts.initial, y, ref, model, energy_eV, pixel_size_m, diffuser_detector_distance_m, start_options
    )
    solved = _solve(build, _solver_run(y_full, opts), model, grid, opts.alpha, psi0, y, scale, excluded)
    phase, attenuation = _phase_and_attenuation(solved, opts.single_material, prior, geometry)
    mask, planes = None, None
    if opts.zero_background:
        mask, phase, attenuation, planes = _zeroed_background(
            phase, attenuation, background_mask, unseen if moved else None
        )
    residual_pct = to_numpy(xp.abs(solved.sol.evaluation.r[solved.model.frame])) * 100.0
    res = RetrievalResult(
        phase=xp.asarray(phase.astype(model.rdtype)),
        attenuation=xp.asarray(attenuation.astype(model.rdtype)),
        iterations=solved.iterations,
        converged=solved.sol.converged,
        residual=xp.asarray(residual_pct.astype(model.rdtype)),
        residual_rmse=residual_rmse_pct(solved.sol, solved.model, excluded),
        loss_history=solved.history,
        coherence_length_x_m=float(coherence.x_m),
        coherence_length_y_m=float(coherence.y_m),
        parameters=_parameters(
            opts,
            solved,
            grid,
            coherence,
            prior,
            kappa,
            diffuser_given=diffuser is not None,
            diffuser_model_requested=pair.requested,
            diffuser_probe=probe,
            drift=drift,
            moved=moved,
            outliers=pair.outliers,
            reference_outliers=pair.reference_outliers,
            bad_pixels=pair.bad_pixels,
        )
        # what the background fit took from the solver's psi: a scan's warm start adds it back
        | {"background_planes": planes}
        | _alpha_rule_record(
            pair.phase_sensitivity, guard, pair.requested, pair.attenuation_contrast, pair.phase_sensitivity_bound
        ),
        background=mask,
    )
    hint = sensitivity.misfit_hint(sample_diffuser_distance_m, opts.diffuser_upstream_m)
    return _with_sensitivity(
        res,
        ref,
        energy_eV,
        pixel_size_m,
        diffuser_detector_distance_m,
        intensity=y / scale,
        excluded=excluded,
        misfit_hint=hint,
    )


def _alpha_rule_record(
    phase_sensitivity: float | None,
    guard: dict | None = None,
    requested: str = "auto",
    attenuation_contrast: float | None = None,
    noise_bound: float | None = None,
) -> dict:
    """The rule's entries where ``alpha="sensitivity"`` set alpha (:func:`_resolved_alpha`):
    the sensitivity, its noise bound where it read none, and the attenuation contrast, and
    where the diffuser models' probe decided whether its lower Im(alpha) stands with the
    single-material fit (:func:`_guarded_alpha`), their residual ratio and what gave way where
    it did not (:func:`alpha_rule_gives_up` of ``diffuser_model=requested``): the alpha, kept
    at the default, or ``"auto"``'s fit, for zero phase."""
    if phase_sensitivity is None:
        return {}
    record = {"alpha_rule": "sensitivity", "phase_sensitivity": phase_sensitivity}
    if attenuation_contrast is not None:
        record["attenuation_contrast"] = attenuation_contrast
    if noise_bound is not None:
        record["phase_sensitivity_noise_bound"] = noise_bound
    if guard is not None:
        ratio = model_probe_ratio(guard)
        gave_up = None if alpha_rule_holds(ratio) else alpha_rule_gives_up(requested)
        record["alpha_rule_model_ratio"] = ratio
        record["alpha_rule_kept_default"] = gave_up == "alpha"
        record["alpha_rule_took_zero_phase"] = gave_up == "model"
    return record


def _with_sensitivity(
    res: RetrievalResult,
    reference,
    energy_eV,
    pixel_size_m,
    diffuser_detector_distance_m,
    intensity=None,
    excluded=None,
    misfit_hint: str = "",
):
    """``res`` with what the speckle could carry in its parameters
    (:func:`pwf_dask.calibration.sensitivity.assess`: the speckle's visibility and grain, the
    phase's speckle shift, the fit's misfit in the sample against its background where the
    measured ``intensity`` is given, and a warning where the data carry little of the phase or
    the model does not fit the sample). PWF's only: its limits were chosen on PWF's phase, and
    a tracker's noisier phase reads steeper."""
    xp = get_array_module(res.phase)
    found = sensitivity.assess(
        res.phase,
        reference,
        wavelength_m=optics.wavelength_m(energy_eV),
        diffuser_detector_distance_m=diffuser_detector_distance_m,
        pixel_size_m=pixel_size_m,
        background=None if res.background is None else xp.asarray(res.background),
        residual=None if intensity is None else res.residual,
        intensity=intensity,
        excluded=excluded,
        misfit_hint=misfit_hint,
    )
    res.parameters.update(found.parameters())
    return res


@dataclass
class _Pair:
    """The sample and reference as the solver reads them, and what was measured on them."""

    y: Any  # the sample, spikes repaired (and left out of the data term through ``excluded``)
    ref: Any  # the reference, spikes repaired: the diffuser estimate reads every pixel
    scale: float  # the reference's mean: the data term's unit
    excluded: Any  # pixels out of the data term (spikes, bad_pixels, unseen grains), or None
    drift: tuple[float, float]
    unseen: Any  # frame pixels whose grains the reference never saw, or None (t_r not moved)
    coherence: _Coherence
    fft: FFT
    requested: str  # the diffuser model asked for, before "auto" was resolved
    outliers: int
    reference_outliers: int
    bad_pixels: int
    background_mask: Any = None
    phase_sensitivity: float | None = None  # measured for alpha="sensitivity" only
    attenuation_contrast: float | None = None  # the same
    phase_sensitivity_bound: float | None = None  # where that S reads none: its noise bound

    def rule_sensitivity(self) -> float | None:
        """The S the alpha rule used (:func:`pwf_dask.pwf.solver.rule_sensitivity`); None where
        alpha was not the rule's."""
        if self.phase_sensitivity is None:
            return None
        return solver.rule_sensitivity(self.phase_sensitivity, self.phase_sensitivity_bound)


def _prepared_pair(
    sample, reference, opts: RetrievalOptions, geometry: Geometry, bad_pixels=None, background_mask=None
) -> tuple[_Pair, RetrievalOptions, dict, float | None]:
    """Every check of a PWF retrieval before any work, then the pair repaired, the coherence
    lengths (given or calibrated), the grids resolved and the drift measured; with the checked
    options, the single-material prior and the diffuser's kappa (:func:`_checked_pwf_options`)."""
    xp = get_array_module(sample, reference)
    y, ref = _check_pair(sample, reference, xp)
    background_mask = _checked_background_mask(background_mask, tuple(y.shape))
    requested = opts.diffuser_model
    opts, prior, kappa = _checked_pwf_options(opts, y.shape, geometry)
    # spikes: the reference is repaired (the diffuser estimate needs every pixel), the
    # sample's are left out of the data term (and repaired for the statistics that read it)
    ref, ref_outliers = repair_outliers(ref, opts.outlier_sigma)
    y, outliers = repair_outliers(y, opts.outlier_sigma)
    n_outliers = int(outliers.sum())
    bad = _checked_bad_pixels(bad_pixels, y.shape, xp)
    coherence = _coherence(ref, geometry, opts)
    opts = _resolved_grids(opts, geometry, coherence)
    opts, phase_s, contrast, phase_s_bound = _resolved_alpha(opts, y, ref, geometry)
    fft = FFT.for_module(xp, opts.fft_workers)
    scale = float(xp.mean(ref))
    if not scale > 0:
        raise ValueError("reference has zero mean intensity")
    drift, unseen = measured_drift(y, ref, opts.diffuser_drift, fft)
    excluded = outliers if n_outliers else None
    if bad is not None:
        excluded = bad if excluded is None else excluded | bad
    if unseen is not None:
        # the grains that drifted into the frame were never in the reference
        unseen = xp.asarray(unseen)
        excluded = unseen if excluded is None else excluded | unseen
    pair = _Pair(
        y,
        ref,
        scale,
        excluded,
        drift,
        unseen,
        coherence,
        fft,
        requested,
        n_outliers,
        int(ref_outliers.sum()),
        0 if bad is None else int(bad.sum()),
        background_mask,
        phase_s,
        contrast,
        phase_s_bound,
    )
    return pair, opts, prior, kappa


def _resolved_alpha(
    opts: RetrievalOptions, y, ref, geometry: Geometry
) -> tuple[RetrievalOptions, float | None, float | None, float | None]:
    """``alpha="sensitivity"`` as a number, from the reference's phase sensitivity and the
    sample's attenuation contrast (:func:`pwf_dask.pwf.solver.sensitivity_alpha`), and those
    two and, where S reads none, its noise bound (:func:`pwf_dask.pwf.solver.rule_sensitivity`);
    other alphas as given (and None, None, None)."""
    if opts.alpha != "sensitivity":
        return opts, None, None, None
    optics_args = (
        optics.wavelength_m(geometry.energy_eV),
        geometry.diffuser_detector_distance_m,
        geometry.pixel_size_m,
    )
    s = sensitivity.phase_sensitivity(ref, *optics_args)
    # where S reads none, whether the photon noise hides it (solver.rule_sensitivity)
    bound = sensitivity.phase_sensitivity_noise_bound(ref, *optics_args) if s <= 0 else None
    contrast = sensitivity.attenuation_contrast(y, ref)
    alpha = solver.sensitivity_alpha(solver.rule_sensitivity(s, bound), attenuation_contrast=contrast)
    return replace(opts, alpha=alpha), s, contrast, bound


#: Iterations of each diffuser model that ``diffuser_model="auto"`` runs on the sample where
#: the absorption rule gives zero phase (:func:`_probed_diffuser`): 20 choose as 40 did on
#: every probed random scene and strip, true or calibrated lengths, at about 0.6x the cost; 10
#: lose one (benchmarks/probe_iterations.py).
DIFFUSER_PROBE_ITER = 20
#: ``"auto"`` takes the single-material fit over zero phase where its data residual after
#: :data:`DIFFUSER_PROBE_ITER` iterations is below this fraction of zero phase's.
DIFFUSER_PROBE_RATIO = 0.5
#: The alpha rule keeps its lower Im(alpha) with the single-material diffuser fit only where
#: the fit's probe residual is at most this multiple of zero phase's (:func:`alpha_rule_holds`):
#: the fit then explains the sample's data at least as well as the paper's estimate. 1 is the
#: natural bound, not a tuned one: on the 80 random geometries 1.02-1.2 would hold the fit on
#: 33-34 scenes for 1's 35 (docs/validation.md, "The alpha rule's model probe").
ALPHA_RULE_MAX_MODEL_RATIO = 1.0
#: Frame pixels the probe reads at most: a larger frame is probed on its centred window of
#: about this many (:func:`probe_window`), as a frame of its own. The probe picks a model, not
#: the phase: probed whole with 40 iterations it took a quarter of the issue's 430 x 2220
#: frame's retrieval; on its window, with its own diffuser estimates and 20 iterations, 5 %.
DIFFUSER_PROBE_MAX_PX = 512 * 512


@dataclass(frozen=True)
class DiffuserChoice:
    """The diffuser model ``"auto"`` chose by its probe, its t_r, and what decided it."""

    model: str
    transmission: Any  # t_r on the computational grid, where the reference was taken
    beta_over_delta: float | None  # kappa of the single-material fit, None for zero phase
    residuals_pct: dict  # each model's data residual after the probe, % of the mean reference


def probes_diffuser(requested: str, resolved: str) -> bool:
    """Whether ``diffuser_model=requested``, resolved by the absorption rule to ``resolved``
    (:func:`chosen_diffuser_model`), probes both models on the sample: only "auto" where the
    absorption rule chose zero phase, the direction benchmarks/diffuser_models.py found worth
    it (where the grains absorb, zero phase's lower residual did not mean a better phase)."""
    return requested == "auto" and resolved == "zero-phase"


def probe_window(frame_shape: tuple[int, int], max_px: int | None = None) -> tuple[slice, slice]:
    """The frame's centred window the diffuser probe reads: the whole frame up to ``max_px``
    pixels (default :data:`DIFFUSER_PROBE_MAX_PX`); beyond, as many whole rows as fit up to a
    square's (a wide strip keeps its height) and the columns the pixel count leaves. Centred,
    as a scan's rotation axis puts the sample."""
    max_px = DIFFUSER_PROBE_MAX_PX if max_px is None else int(max_px)
    ny, nx = frame_shape
    if ny * nx <= max_px:
        return slice(0, ny), slice(0, nx)
    rows = min(ny, max(math.isqrt(max_px), max_px // nx))
    columns = min(nx, max_px // rows)
    y0, x0 = (ny - rows) // 2, (nx - columns) // 2
    return slice(y0, y0 + rows), slice(x0, x0 + columns)


def _probe_residual(t, pair: _Pair, opts: RetrievalOptions, geometry: Geometry) -> float:
    """The data residual (% of the mean reference) after :data:`DIFFUSER_PROBE_ITER`
    iterations of Algorithm S1 from zero with diffuser ``t``, on the first field grid, at the
    default alpha whatever the solve's: the residual ratio depends on the regularizer (scene 68
    of benchmarks/diffuser_models.py, calibrated lengths, 40 iterations: 0.39 at 0.1 + 0.05i,
    0.71 at the paper's 0.1 + 0.01i) and :data:`DIFFUSER_PROBE_RATIO` was measured at the
    default."""
    if pair.unseen is not None:
        t = calibration.shift_transmission(t, pair.drift, fft=pair.fft)
    grid = _first_field_grid(
        opts.field_upsample,
        t,
        geometry.pixel_size_m,
        pair.coherence.x_m,
        pair.coherence.y_m,
        pair.fft,
        opts.sample_field_grid,
    )
    build = _model_builder(t, pair.y.shape, geometry, pair.coherence, opts, pair.excluded, pair.fft)
    model = build(
        field_upsample=grid.field_upsample, alpha=solver.DEFAULT_ALPHA, sample_field_grid=grid.sample_field_grid
    )
    y_full = model.xp.zeros(model.shape, dtype=model.rdtype)
    y_full[model.frame] = pair.y / pair.scale
    # exactly DIFFUSER_PROBE_ITER iterations, whatever the stop rule asked of the solve
    probe = replace(opts, max_iter=DIFFUSER_PROBE_ITER, min_iter=DIFFUSER_PROBE_ITER, tol=0.0, rtol=0.0, jtol=0.0)
    sol = _solver_run(y_full, probe)(model, psi0=None)
    return residual_rmse_pct(sol, model, pair.excluded)


def _probe_pair(pair: _Pair) -> _Pair:
    """The pair the probe reads: the whole frame up to :data:`DIFFUSER_PROBE_MAX_PX`, beyond it
    the :func:`probe_window` crop as a frame of its own (its mean the data term's unit)."""
    rows, columns = probe_window(tuple(pair.y.shape))
    if (rows.stop - rows.start, columns.stop - columns.start) == tuple(pair.y.shape):
        return pair
    ref = pair.ref[rows, columns]
    return replace(
        pair,
        y=pair.y[rows, columns],
        ref=ref,
        scale=float(get_array_module(ref).mean(ref)),
        excluded=None if pair.excluded is None else pair.excluded[rows, columns],
        unseen=None if pair.unseen is None else pair.unseen[rows, columns],
        background_mask=None,
    )


def _probe_residuals(pair: _Pair, opts: RetrievalOptions, geometry: Geometry, known: dict) -> tuple[dict, dict]:
    """Each diffuser model's data residual (%) after :data:`DIFFUSER_PROBE_ITER` iterations on
    the pair's :func:`probe_window`, and the models' t_r of the whole frame where the window is
    the whole frame (else {}). ``known``: {model: t_r of the whole frame} already estimated,
    used rather than estimated again where the window is the whole frame."""
    probed = _probe_pair(pair)
    whole = probed is pair
    residuals, estimates = {}, {}
    for model in ("zero-phase", "single-material"):
        o = replace(opts, diffuser_model=model)
        t = known.get(model) if whole else None
        if t is None:
            t = _transmission(probed.ref, probed.y, None, o, geometry, probed.coherence, probed.fft)
        residuals[model] = _probe_residual(t, probed, o, geometry)
        if whole:
            estimates[model] = t
    return residuals, estimates


def _probed_diffuser(t_zero_phase, pair: _Pair, opts: RetrievalOptions, geometry: Geometry) -> DiffuserChoice:
    """``diffuser_model="auto"`` where the grains hardly absorb: zero phase (the paper's
    estimate, ``t_zero_phase``), unless a short run with the single-material fit leaves under
    :data:`DIFFUSER_PROBE_RATIO` of zero phase's data residual. On 80 random scenes this
    switched 4 (their phase error 1.28 -> 0.09 at best) and none the wrong way
    (docs/validation.md, "Which diffuser model, scene by scene"). A frame over
    :data:`DIFFUSER_PROBE_MAX_PX` is probed on its :func:`probe_window` as a frame of its own,
    both diffuser estimates of the window's reference; the whole frame's single-material fit
    is made only where it is chosen."""
    single = replace(opts, diffuser_model="single-material")
    kappa = chosen_diffuser_model(
        "single-material", opts.diffuser_material, opts.diffuser_beta_over_delta, geometry.energy_eV
    )[1]
    residuals, estimates = _probe_residuals(pair, opts, geometry, {"zero-phase": t_zero_phase})
    if residuals["single-material"] < DIFFUSER_PROBE_RATIO * residuals["zero-phase"]:
        t = estimates.get("single-material")
        if t is None:
            t = _transmission(pair.ref, pair.y, None, single, geometry, pair.coherence, pair.fft)
        return DiffuserChoice("single-material", t, kappa, residuals)
    return DiffuserChoice("zero-phase", t_zero_phase, None, residuals)


def guards_alpha_rule(phase_sensitivity: float | None, diffuser_model: str) -> bool:
    """Whether the alpha rule's Im(alpha) waits on the diffuser models' probe
    (:func:`alpha_rule_holds`): the rule lowered it (``phase_sensitivity`` under
    :data:`pwf_dask.pwf.solver.TUNED_PHASE_SENSITIVITY`) and the diffuser is the
    single-material fit. ``phase_sensitivity`` None: alpha was not the rule's."""
    return (
        phase_sensitivity is not None
        and phase_sensitivity < solver.TUNED_PHASE_SENSITIVITY
        and diffuser_model == "single-material"
    )


def alpha_rule_holds(model_ratio: float) -> bool:
    """Whether the rule's lowered Im(alpha) stands with the single-material diffuser fit: its
    probe residual at most :data:`ALPHA_RULE_MAX_MODEL_RATIO` of zero phase's
    (``model_ratio``, :func:`model_probe_ratio`). Where the fit leaves more of the sample's data
    unexplained than the paper's estimate, the misfit is the fit's model error, and the lighter
    phase penalty lets the phase follow it: on the 80 random geometries the rule raised the
    fit's phase error by a median 0.046 where this ratio reached 1.05 and lowered it by 0.132
    under 1 (docs/validation.md, "The alpha rule's model probe")."""
    return model_ratio <= ALPHA_RULE_MAX_MODEL_RATIO


def model_probe_ratio(residuals_pct: dict | None) -> float | None:
    """The single-material fit's probe residual over zero phase's, None where not probed."""
    if not residuals_pct:
        return None
    return float(residuals_pct["single-material"] / residuals_pct["zero-phase"])


def _guarded_alpha(
    opts: RetrievalOptions, pair: _Pair, t, probe: DiffuserChoice | None, geometry: Geometry
) -> tuple[RetrievalOptions, dict | None]:
    """The options with the rule's alpha and the single-material fit ``t`` where the fit earns
    the rule's lower Im(alpha) (:func:`alpha_rule_holds`); where it does not, what gives way
    (:func:`alpha_rule_gives_up`): under ``"auto"`` the fit, for zero phase at the rule's alpha;
    with a fit the user named, the alpha, :data:`pwf_dask.pwf.solver.DEFAULT_ALPHA`. Also the
    residuals that decided (None where nothing did: the rule's alpha not lowered, zero phase).
    ``"auto"``'s probe, where it ran, decides: it took the fit for a residual under half zero
    phase's."""
    if not guards_alpha_rule(pair.rule_sensitivity(), opts.diffuser_model):
        return opts, None
    residuals = probe.residuals_pct if probe else _probe_residuals(pair, opts, geometry, {"single-material": t})[0]
    if alpha_rule_holds(model_probe_ratio(residuals)):
        return opts, residuals
    if alpha_rule_gives_up(pair.requested) == "model":
        return replace(opts, diffuser_model="zero-phase"), residuals
    # the default Im(alpha); Re(alpha) as the sample's attenuation set it
    return replace(opts, alpha=complex(complex(opts.alpha).real, solver.DEFAULT_ALPHA.imag)), residuals


def alpha_rule_gives_up(requested: str) -> str:
    """What gives way where the single-material fit does not earn the rule's lower Im(alpha)
    (:func:`alpha_rule_holds` false) with ``diffuser_model=requested``: ``"model"`` under
    ``"auto"``, whose absorption rule took the fit unprobed (zero phase is then taken, at the
    rule's alpha: on the 7 such random scenes, session 101, phase error 0.24 -> 0.13,
    0.33 -> 0.24, 0.63 -> 0.41, 0.69 -> 0.50 and 0.39 -> 0.34 with calibrated lengths,
    0.23 -> 0.13 and 0.32 -> 0.22 with the true ones; docs/validation.md, "The alpha rule's
    model probe"); ``"alpha"`` for a fit the user named, kept at the default alpha."""
    return "model" if requested == "auto" else "alpha"


def _checked_bad_pixels(bad_pixels, frame_shape: tuple[int, int], xp):
    """``bad_pixels`` as a boolean array of the frame's shape on the images' device, None where
    none is given or none is set; one line for another shape or a non-boolean map."""
    if bad_pixels is None:
        return None
    bad = xp.asarray(bad_pixels)
    if bad.dtype != bool or tuple(bad.shape) != tuple(frame_shape):
        raise ValueError(
            f"bad_pixels must be a boolean map of the frame's shape {frame_shape}, got {bad.dtype} {bad.shape}"
        )
    return bad if bool(bad.any()) else None


def _checked_background_mask(background_mask, frame_shape: tuple[int, int]):
    """``background_mask`` as a boolean NumPy map of the frame's shape, or None; one line for
    another shape, values other than True/False (or 1/0), or fewer sample-free pixels than a fitted surface needs."""
    if background_mask is None:
        return None
    mask = to_numpy(background_mask)
    binary = mask.dtype == bool or (mask.dtype.kind in "iuf" and bool(np.isin(mask, (0, 1)).all()))
    if not binary or tuple(mask.shape) != tuple(frame_shape):
        raise ValueError(
            f"background_mask must be a boolean (or 0/1) map of the frame's shape {frame_shape}, "
            f"got {mask.dtype} {mask.shape}"
        )
    mask = mask.astype(bool, copy=False)
    if int(mask.sum()) < bg.MIN_BACKGROUND_PIXELS:
        raise ValueError(
            f"background_mask marks {int(mask.sum())} sample-free pixels; a background plane needs at least "
            f"{bg.MIN_BACKGROUND_PIXELS}"
        )
    return mask


def _check_pair(sample, reference, xp):
    """The sample and reference images, each checked, of one shape."""
    y = _check_image("sample", sample, xp)
    ref = _check_image("reference", reference, xp)
    if y.shape != ref.shape:
        raise ValueError(f"sample {y.shape} and reference {ref.shape} differ in shape")
    return y, ref


def _check_start(initial, image_shape: tuple[int, int], restart: str) -> None:
    """psi_0 ("zero", "umpa" or an array of the image's shape) and the Nesterov restart rule."""
    if isinstance(initial, str) and initial not in ("zero", "umpa"):
        raise ValueError(f"unknown initial {initial!r}: choose 'zero', 'umpa' or pass psi")
    if not isinstance(initial, str) and tuple(initial.shape) != tuple(image_shape):
        raise ValueError(f"initial psi has shape {tuple(initial.shape)}, the image {tuple(image_shape)}")
    if restart not in solver.RESTARTS:
        raise ValueError(f"unknown restart {restart!r}: choose one of {', '.join(solver.RESTARTS)}")


@dataclass(frozen=True)
class _Coherence:
    """The coherence lengths the model uses and where they came from."""

    x_m: float
    y_m: float
    fit: Any  # calibration.CoherenceFit, None where both lengths were given
    pixel_integration: bool

    def parameters(self) -> dict:
        fit = self.fit
        return {
            "coherence_calibrated": fit is not None,
            "coherence_method": fit.method if fit else "given",
            "coherence_template": fit.template if fit else "",
            "coherence_grain_radius_m": fit.grain_radius_m if fit else None,
            "coherence_reference_photons_per_px": fit.reference_photons_per_px if fit else None,
            "pixel_integration": self.pixel_integration,
        }


def _coherence(ref, geometry: Geometry, opts: RetrievalOptions) -> _Coherence:
    """The given lengths, or those calibrated on the reference speckle (Methods, "IOTF")
    for each one not given."""
    x_m, y_m = opts.coherence_length_x_m, opts.coherence_length_y_m
    includes_pixel_blur = opts.coherence_includes_pixel_blur
    fit = None
    if x_m is None or y_m is None:
        fit = calibration.fit_coherence_lengths(
            ref,
            geometry.pixel_size_m,
            energy_eV=geometry.energy_eV,
            diffuser_detector_distance_m=geometry.speckle_distance_m,
            diffuser_material=opts.diffuser_material,
            method=opts.coherence_method,
        )
        x_m = fit.x_m if x_m is None else x_m
        y_m = fit.y_m if y_m is None else y_m
        includes_pixel_blur = fit.includes_pixel_blur
    # the source's lengths (given, or the template fit's) leave the pixel's own blur to the model
    return _Coherence(x_m, y_m, fit, pixel_integration=not includes_pixel_blur)


@dataclass(frozen=True)
class _FieldGrid:
    """The field grid the solver starts on, and what ``"auto"`` measured to choose it."""

    field_upsample: float
    auto: bool
    aliasing: float | None  # diffuser_aliasing(t), measured for "auto" only
    sample_field_grid: str = "field"  # where exp(psi) is formed on it (:func:`sample_field_grid_on`)

    @property
    def diffuser_aliases(self) -> bool:
        return self.auto and self.aliasing > DIFFUSER_ALIASING_FRACTION


def sample_field_grid_on(requested: str, pixel_field_upsample: int | None) -> str:
    """Where exp(psi) is formed: as ``requested``, but on the field grid where
    ``field_upsample="auto"`` took a grid for the pixel (``pixel_field_upsample``, the
    coherence's :func:`auto_field_upsample`, 2 or more; None for a given factor).

    exp(psi) on the detector grid serves the aliasing diffuser's grid
    (:data:`DIFFUSER_FIELD_UPSAMPLE`), where it reads as the field grid. Where the pixel is
    coarse for the coherence the sample's own field is too (benchmarks/results/field_grid.md,
    the random geometries, calibrated lengths, every default; scenes holding on the field grid
    -> on the detector grid, and the detector grid's error higher / lower by over 0.01): 1.5x
    4 -> 4 of 6, 0 / 0; 2x 13 -> 10 of 21, 11 / 4; 3x 8 -> 7 of 15, 11 / 1; 4x 9 -> 3 of 13,
    13 / 0, for 0.77-0.89x the wall time. A given factor is taken as asked."""
    check_sample_field_grid(requested)
    return "field" if pixel_field_upsample is not None and pixel_field_upsample > 1 else requested


def _first_field_grid(
    field_upsample, t, pixel_size_m: float, cx: float, cy: float, fft: FFT, sample_field_grid: str = "field"
) -> _FieldGrid:
    """The given factor, or for "auto" the coherence's (:func:`auto_field_upsample`), at
    least :data:`DIFFUSER_FIELD_UPSAMPLE` where the diffuser aliases on the detector grid;
    with where exp(psi) is formed on it (:func:`sample_field_grid_on`)."""
    if field_upsample != "auto":
        return _FieldGrid(field_upsample, False, None, sample_field_grid_on(sample_field_grid, None))
    aliasing = diffuser_aliasing(t, fft)
    pixel = auto_field_upsample(pixel_size_m, cx, cy)
    first = max(pixel, DIFFUSER_FIELD_UPSAMPLE) if aliasing > DIFFUSER_ALIASING_FRACTION else pixel
    return _FieldGrid(first, True, aliasing, sample_field_grid_on(sample_field_grid, pixel))


@dataclass
class _Solved:
    """The solver's run on the final model, with totals over every leg that led to it."""

    model: Any
    sol: Any
    alpha: complex
    alpha_trials: list | None
    gradient: float | None
    iterations: int
    history: list[float]
    restarts: int
    backtracks: int


def _solve(build, run, model, grid: _FieldGrid, alpha, psi0, y, scale: float, excluded) -> _Solved:
    """Algorithm S1 on the first field grid (with ``alpha`` chosen by the discrepancy rule
    where asked), then, for ``field_upsample="auto"``, on a grid twice as fine from its psi
    where the solution's phase gradients alias on the first (:func:`field_gradient_limit`)."""
    trials = None
    if alpha == "discrepancy":
        noise_pct = calibration.photon_noise_pct(to_numpy(y), scale)

        def solve(a, start):
            trial = build(field_upsample=grid.field_upsample, alpha=a, sample_field_grid=grid.sample_field_grid)
            sol = run(trial, psi0=psi0 if start is None else start)
            return sol, residual_rmse_pct(sol, trial, excluded)

        choice = solver.discrepancy_alpha(solve, noise_pct)
        alpha, sol, trials = choice.alpha, choice.result, choice.trials
        model = build(field_upsample=grid.field_upsample, alpha=alpha, sample_field_grid=grid.sample_field_grid)
    else:
        sol = run(model, psi0=psi0)
    # only "auto" needs the statistic: a smoothing pass and a percentile over the frame
    gradient = phase_gradient_rad_per_px(sol.psi[model.frame].imag) if grid.auto else None
    solved = _Solved(
        model,
        sol,
        alpha,
        trials,
        gradient,
        sol.iterations,
        list(sol.objective_history),
        sol.restarts,
        sol.backtracks,
    )
    if grid.auto and gradient > field_gradient_limit(grid.field_upsample, grid.diffuser_aliases):
        # past the first grid's limit the tilt itself needs the field grid: exp(U psi) there
        model = build(field_upsample=2 * grid.field_upsample, sample_field_grid="field")
        sol = run(model, psi0=sol.psi)
        solved.model, solved.sol = model, sol
        solved.iterations += sol.iterations
        solved.history += list(sol.objective_history)
        solved.restarts += sol.restarts
        solved.backtracks += sol.backtracks
    return solved


def _retrieve_by_tracking(
    sample, reference, opts: RetrievalOptions, energy_eV, pixel_size_m, diffuser_detector_distance_m, background_mask
) -> RetrievalResult:
    """A speckle-tracking baseline with the options it shares with PWF (MIST: the material)."""
    material = {}
    if opts.method == "mist":
        ratio = sample_delta_over_beta_of(opts.sample_material, opts.sample_delta_over_beta, energy_eV)
        material = {"delta_over_beta": ratio}
    return retrieve_tracking(
        sample,
        reference,
        method=opts.method,
        energy_eV=energy_eV,
        pixel_size_m=pixel_size_m,
        diffuser_detector_distance_m=diffuser_detector_distance_m,
        background_mask=background_mask,
        zero_background=opts.zero_background,
        outlier_sigma=opts.outlier_sigma,
        diffuser_drift=opts.diffuser_drift,
        **(opts.tracking_options or {}),
        **material,
    )


def _checked_pwf_options(
    opts: RetrievalOptions, image_shape: tuple[int, int], geometry: Geometry
) -> tuple[RetrievalOptions, dict, float | None]:
    """PWF's options checked before any work, one line naming the first bad one: the options
    with ``alpha`` and ``field_upsample`` parsed, the single-material prior's parameters and
    the diffuser's kappa = beta/delta."""
    optics.check_plausible_geometry(
        coherence_length_x_m=opts.coherence_length_x_m, coherence_length_y_m=opts.coherence_length_y_m
    )
    check_solver_options(
        opts.max_iter, opts.tol, opts.gamma, opts.step, opts.phase_scale, opts.stationary_terms, opts.low_band_atol_rad
    )
    alpha = parse_alpha(opts.alpha)
    _check_start(opts.initial, image_shape, opts.restart)
    check_diffuser_drift(opts.diffuser_drift)
    optics.check_detector_blur(0.0, opts.detector_halo_fraction, opts.detector_halo_radius_m)
    calibration.diffuser.check_nsr_floor(opts.diffuser_nsr_floor)
    field_upsample = check_field_upsample(opts.field_upsample)
    check_sample_field_grid(opts.sample_field_grid)
    prior = _single_material_prior(opts.single_material, opts.sample_material, opts.sample_delta_over_beta, geometry)
    model, kappa = chosen_diffuser_model(
        opts.diffuser_model, opts.diffuser_material, opts.diffuser_beta_over_delta, geometry.energy_eV
    )
    checked = replace(
        opts,
        alpha=alpha,
        field_upsample=field_upsample,
        diffuser_upstream_m=geometry.diffuser_upstream_m,
        diffuser_model=model,
    )
    return checked, prior, kappa


def _resolved_grids(opts: RetrievalOptions, geometry: Geometry, coherence: _Coherence) -> RetrievalOptions:
    """``pad`` and ``upsample`` as numbers: "auto" reads the speckle's spread and the IOTF."""
    pad, upsample = opts.pad, opts.upsample
    if pad == "auto":
        pad = auto_pad(
            geometry.pixel_size_m, geometry.wavelength_m, geometry.speckle_distance_m, coherence.x_m, coherence.y_m
        )
    if upsample == "auto":
        upsample = auto_upsample(geometry.pixel_size_m, coherence.x_m, coherence.y_m)
    return replace(opts, pad=int(pad), upsample=int(upsample))


def _transmission(ref, y, diffuser, opts: RetrievalOptions, geometry: Geometry, coherence: _Coherence, fft):
    """t_r on the computational grid: the one given, or estimated from the reference
    (Methods, Diffuser transmission function; :func:`estimate_diffuser`), the sample image
    ``y``'s noise flooring its Wiener filters under ``diffuser_nsr_floor="sample"``."""
    if diffuser is None:
        return estimate_diffuser(
            ref,
            energy_eV=geometry.energy_eV,
            pixel_size_m=geometry.pixel_size_m,
            diffuser_detector_distance_m=geometry.diffuser_detector_distance_m,
            coherence_length_x_m=coherence.x_m,
            coherence_length_y_m=coherence.y_m,
            pad=opts.pad,
            diffuser_model=opts.diffuser_model,
            diffuser_material=opts.diffuser_material,
            diffuser_beta_over_delta=opts.diffuser_beta_over_delta,
            diffuser_refine_iter=opts.diffuser_refine_iter,
            diffuser_nsr_floor=opts.diffuser_nsr_floor,
            sample=y,
            phase_screen_iter=opts.phase_screen_iter,
            diffuser_upstream_m=geometry.diffuser_upstream_m,
            detector_halo_fraction=opts.detector_halo_fraction,
            detector_halo_radius_m=opts.detector_halo_radius_m,
            fft_workers=fft.workers,
        )
    t = get_array_module(ref).asarray(diffuser)
    shape = computational_shape(tuple(y.shape), opts.pad)
    if t.shape != shape:
        raise ValueError(f"diffuser has shape {t.shape}, the computational grid is {shape} (pad {opts.pad})")
    return t


def _model_builder(t, frame_shape, geometry: Geometry, coherence: _Coherence, opts: RetrievalOptions, excluded, fft):
    """:func:`pwf_dask.pwf.solver.build_model` with everything but the field grid (and the
    discrepancy rule's alpha) fixed: Eq. (forwardModel) with Algorithm S2's filters."""
    return partial(
        solver.build_model,
        t,
        frame_shape=tuple(frame_shape),
        pixel_size_m=geometry.pixel_size_m,
        wavelength=geometry.wavelength_m,
        sample_diffuser_distance_m=geometry.sample_diffuser_distance_m,
        diffuser_detector_distance_m=geometry.diffuser_detector_distance_m,
        coherence_length_x_m=coherence.x_m,
        coherence_length_y_m=coherence.y_m,
        pixel_integration=coherence.pixel_integration,
        detector_halo_fraction=opts.detector_halo_fraction,
        detector_halo_radius_m=opts.detector_halo_radius_m,
        gamma=opts.gamma,
        alpha=solver.PAPER_ALPHA if opts.alpha == "discrepancy" else opts.alpha,  # each rung rebuilds it
        use_preconditioner=opts.preconditioner,
        upsample=opts.upsample,
        pad=opts.pad,
        precision=opts.precision,
        normalization=opts.normalization,
        phase_scale=opts.phase_scale,
        sample_field_grid=opts.sample_field_grid,
        bad_pixels=excluded,
        fft=fft,
    )


def _solver_run(y_full, opts: RetrievalOptions):
    """Algorithm S1 (:func:`pwf_dask.pwf.solver.pwf`) on ``y_full`` with the options' step,
    momentum restart and stop rule; called with a model and a start."""
    return partial(
        solver.pwf,
        y_full,
        step=opts.step,
        max_iter=opts.max_iter,
        tol=opts.tol,
        min_iter=opts.min_iter,
        patience=opts.patience,
        step_search=opts.step_search,
        restart=opts.restart,
        rtol=opts.rtol,
        jtol=opts.jtol,
        low_band_atol_rad=opts.low_band_atol_rad,
        stationary_terms=opts.stationary_terms,
    )


def _phase_and_attenuation(solved: _Solved, single_material: bool, prior: dict, geometry: Geometry):
    """Im psi and -Re psi on the frame, as float64 on the solver's device (the background is
    found and zeroed there); with the single-material prior the phase's low frequencies follow
    the attenuation (in the solver's precision)."""
    psi = solved.sol.psi[solved.model.frame]
    phase = psi.imag
    if single_material:
        phase = single_material_phase(
            psi.imag,
            -psi.real,
            prior["sample_delta_over_beta"],
            pixel_size_m=geometry.pixel_size_m,
            wavelength_m=geometry.wavelength_m,
            distance_m=geometry.sample_detector_distance_m,
        )
    xp = solved.model.xp
    return phase.astype(xp.float64), -psi.real.astype(xp.float64)


def _zeroed_background(phase, attenuation, background_mask, unseen):
    """(background mask, phase, attenuation, planes) with a plane fitted to the background
    pixels subtracted (:mod:`pwf_dask.physics.background`); the given mask, else the detected
    one. The mask comes back on the host, the images on their device; ``planes`` holds each
    plane's [constant, row slope, column slope] (:func:`~pwf_dask.physics.background.plane_terms`)."""
    xp = get_array_module(phase)
    mask = xp.asarray(background_mask) if background_mask is not None else bg.projection_background(phase, attenuation)
    fit = mask if unseen is None else _seen_background(mask, xp.asarray(unseen))
    phase, phase_plane = bg.zeroed_with_plane(phase, fit)
    attenuation, attenuation_plane = bg.zeroed_with_plane(attenuation, fit)
    return to_numpy(mask), phase, attenuation, {"phase": phase_plane, "attenuation": attenuation_plane}


def _seen_background(mask: np.ndarray, unseen: np.ndarray) -> np.ndarray:
    """The background pixels outside the strips the reference never saw (their values are
    the regularizer's or an extrapolation's guess), or all of them where the strips would
    leave too few to fit a plane."""
    seen = mask & ~unseen
    if int(seen.sum()) >= bg.MIN_BACKGROUND_PIXELS:
        return seen
    logger.warning(
        "background: %d sample-free pixels outside the strips the drifted diffuser brought in; "
        "the plane is fitted on all %d",
        int(seen.sum()),
        int(mask.sum()),
    )
    return mask


def _parameters(
    opts: RetrievalOptions,
    solved: _Solved,
    grid: _FieldGrid,
    coherence: _Coherence,
    prior: dict,
    kappa: float | None,
    *,
    diffuser_given: bool,
    diffuser_model_requested: str,
    diffuser_probe: DiffuserChoice | None,
    drift,
    moved: bool,
    outliers: int,
    reference_outliers: int,
    bad_pixels: int = 0,
) -> dict:
    """Every choice a PWF retrieval made, given or found (``RetrievalResult.parameters``)."""
    return {
        "method": opts.method,
        "gamma": opts.gamma,
        "alpha": str(complex(solved.alpha)).strip("()"),
        "alpha_rule": "discrepancy" if solved.alpha_trials else "given",
        "alpha_trials": [[str(a).strip("()"), round(r, 4), n] for a, r, n in solved.alpha_trials or []],
        "step": opts.step,
        "step_search": opts.step_search,
        "restart": opts.restart,
        "phase_scale": solved.model.phase_scale,
        "step_final": solved.sol.step,
        "tol": opts.tol,
        "max_iter": opts.max_iter,
        "min_iter": opts.min_iter,
        "patience": opts.patience,
        "rtol": opts.rtol,
        "jtol": opts.jtol,
        "low_band_atol_rad": opts.low_band_atol_rad,
        "stationary_terms": opts.stationary_terms,
        "preconditioner": opts.preconditioner,
        "precision": opts.precision,
        "fft_library": solved.model.fft.library,
        "normalization": opts.normalization,
        "upsample": opts.upsample,
        "field_upsample": solved.model.field_upsample,
        "field_upsample_requested": opts.field_upsample,
        "sample_field_grid": solved.model.sample_field_grid,
        "phase_gradient_rad_per_px": solved.gradient,
        "diffuser_aliasing": grid.aliasing,
        "initial": opts.initial if isinstance(opts.initial, str) else "array",
        "pad": opts.pad,
        **coherence.parameters(),
        "diffuser_model": opts.diffuser_model,
        "diffuser_model_requested": diffuser_model_requested,
        "diffuser_given": diffuser_given,
        "diffuser_probe_residual_pct": diffuser_probe.residuals_pct if diffuser_probe else None,
        "diffuser_beta_over_delta": kappa,
        "diffuser_refine_iter": opts.diffuser_refine_iter,
        "diffuser_nsr_floor": opts.diffuser_nsr_floor,
        "diffuser_upstream_m": opts.diffuser_upstream_m,
        "detector_halo_fraction": opts.detector_halo_fraction,
        "detector_halo_radius_m": opts.detector_halo_radius_m,
        "restarts": solved.restarts,
        "backtracks": solved.backtracks,
        "stop_reason": solved.sol.stop_reason,
        "outlier_sigma": opts.outlier_sigma,
        "outlier_pixels": outliers,
        "outlier_pixels_reference": reference_outliers,
        "bad_pixels": bad_pixels,
        "diffuser_drift": opts.diffuser_drift if isinstance(opts.diffuser_drift, str) else "given",
        "diffuser_drift_px": [float(drift[0]), float(drift[1])],
        "diffuser_moved": bool(moved),
        **prior,
    }


def retrieve_tracking(
    sample,
    reference,
    *,
    method: str,
    energy_eV: float,
    pixel_size_m: float,
    diffuser_detector_distance_m: float,
    background_mask=None,
    zero_background: bool = True,
    outlier_sigma: float | None = DEFAULT_OUTLIER_SIGMA,
    diffuser_drift: str | tuple[float, float] = "auto",
    **options,
) -> RetrievalResult:
    """The speckle-tracking baselines (``umpa``, ``lcs``, ``gf``, ``mist``) behind the same
    interface.

    ``sample`` and ``reference`` are (y, x) or (K, y, x) stacks of K diffuser positions (LCS
    needs K >= 3, MIST K >= 4); the results are (y, x). ``options`` go to the method (e.g.
    ``window``, ``max_shift`` for UMPA, ``delta_over_beta`` for MIST). Spikes beyond
    ``outlier_sigma`` (:mod:`pwf_dask.physics.detector`) are replaced by their neighbours' median in
    every frame first: the trackers need every pixel.

    ``diffuser_drift`` (not in the papers; as for PWF, :func:`measured_drift`): measured on the
    first position, and where that moved, on every position. Each reference frame that moved
    is shifted by the Fourier shift theorem to where its diffuser was for the sample frame,
    and the strips whose grains the reference never saw are cropped off before tracking;
    phase and attenuation there continue the edge values. Uncorrected, a
    drift eats into UMPA's search range, puts every displacement at LCS's linearisation
    limit or at the sub-pixel fit's half-pixel worst case, and the unmatched strips feed
    wrong displacements into the Fourier integration (docs/validation.md, "Diffuser drift").
    """
    from pwf_dask.baselines import tracking

    xp = get_array_module(sample, reference)
    s, r = _checked_tracking_frames(sample, reference, xp)
    background_mask = _checked_background_mask(background_mask, tuple(s.shape[-2:]))
    check_diffuser_drift(diffuser_drift)
    s, s_outliers = repair_outliers(s, outlier_sigma)
    r, r_outliers = repair_outliers(r, outlier_sigma)
    scale = float(xp.mean(r))
    s, r = s / scale, r / scale
    single = s.ndim == 2
    s, r = (s[None], r[None]) if single else (s, r)
    drifts, unseen = _drift_corrected_references(s, r, diffuser_drift, xp)
    window = _seen_window(unseen)
    s, r = s[(slice(None), *window)], r[(slice(None), *window)]
    if single:
        s, r = s[0], r[0]
    fresnel = optics.wavelength_m(energy_eV) * diffuser_detector_distance_m / pixel_size_m**2
    fn = {"umpa": tracking.umpa, "lcs": tracking.lcs, "gf": tracking.geometric_flow, "mist": tracking.mist}[method]
    out = fn(s, r, fresnel=fresnel, **options)
    ny, nx = unseen.shape
    widths = ((window[0].start, ny - window[0].stop), (window[1].start, nx - window[1].stop))

    def full_frame(a):
        return np.pad(to_numpy(a).astype(np.float64), widths, mode="edge")

    phase, attenuation = full_frame(out.phase), full_frame(out.attenuation)
    mask = None
    if zero_background:
        # GF retrieves no attenuation: the background is found on the phase alone
        with_attenuation = method != "gf"
        mask = _tracking_background(phase, attenuation if with_attenuation else None, background_mask, unseen)
        phase = bg.zero_background(phase, mask)
        if with_attenuation:
            attenuation = bg.zero_background(attenuation, mask)
    res = to_numpy(out.residual) * 100.0
    mean_drift = np.mean(drifts, axis=0)
    return RetrievalResult(
        phase=xp.asarray(phase.astype(np.float32)),
        attenuation=xp.asarray(attenuation.astype(np.float32)),
        iterations=0,
        converged=True,
        residual=xp.asarray(full_frame(res).astype(np.float32)),
        residual_rmse=float(np.sqrt(np.mean(res**2))),
        loss_history=[],
        coherence_length_x_m=float("nan"),
        coherence_length_y_m=float("nan"),
        parameters={
            "method": method,
            **options,
            "outlier_sigma": outlier_sigma,
            "outlier_pixels": int(s_outliers.sum()),
            "outlier_pixels_reference": int(r_outliers.sum()),
            "diffuser_drift": diffuser_drift if isinstance(diffuser_drift, str) else "given",
            # the mean over the measured positions (a scan stores one value per reconstruction)
            "diffuser_drift_px": [float(mean_drift[0]), float(mean_drift[1])],
            "diffuser_drift_px_per_position": [[float(a), float(b)] for a, b in drifts],
            "diffuser_moved": bool(unseen.any()),
        },
        background=mask,
    )


def _initial_psi(initial, sample, reference, model, energy_eV, pixel_size_m, diffuser_detector_distance_m, options):
    """psi_0 of Algorithm S1 on the computational grid (None: zeros); the margin continues the
    frame's edge values, where the sample is assumed to go on."""
    xp = model.xp
    if isinstance(initial, str):
        if initial == "zero":
            return None
        start = retrieve_tracking(
            sample,
            reference,
            method="umpa",
            energy_eV=energy_eV,
            pixel_size_m=pixel_size_m,
            diffuser_detector_distance_m=diffuser_detector_distance_m,
            outlier_sigma=None,  # the caller has repaired both images already
            **(options or {}),
        )
        psi = -to_numpy(start.attenuation).astype(np.float64) + 1j * to_numpy(start.phase).astype(np.float64)
    else:
        psi = np.asarray(to_numpy(initial), dtype=np.complex128)
    frame = model.frame
    ny, nx = model.shape
    widths = ((frame[0].start, ny - frame[0].stop), (frame[1].start, nx - frame[1].stop))
    return xp.asarray(np.pad(psi, widths, mode="edge")).astype(model.cdtype)


def _checked_tracking_frames(sample, reference, xp):
    """Both stacks as float64, refused in one line where their shapes differ or a value is
    non-finite or negative."""
    for name, a in (("sample", sample), ("reference", reference)):
        _check_real(name, xp.asarray(_unmasked(name, a)))
    s = xp.asarray(sample, dtype=xp.float64)
    r = xp.asarray(reference, dtype=xp.float64)
    if s.shape != r.shape or s.ndim not in (2, 3):
        raise ValueError(f"sample {s.shape} and reference {r.shape} must be equal (y, x) or (K, y, x) stacks")
    for name, a in (("sample", s), ("reference", r)):
        if not bool(xp.all(xp.isfinite(a))):
            raise ValueError(f"{name} has non-finite values (NaN or inf)")
        if bool(xp.any(a < 0)):
            raise ValueError(f"{name} has negative values: pass flat/dark-corrected intensities")
    return s, r


def _drift_corrected_references(s, r, diffuser_drift, xp) -> tuple[list, np.ndarray]:
    """Each position's measured drift, its reference (in the (K, y, x) stack ``r``) shifted in
    place to where the diffuser was for the sample frame, and the union of the strips no
    reference saw (:func:`measured_drift`)."""
    drifts, unseen = [], np.zeros(s.shape[1:], bool)
    for k in range(s.shape[0]):
        d, strips = measured_drift(s[k], r[k], diffuser_drift)
        drifts.append(d)
        if strips is not None:
            r[k] = xp.maximum(calibration.shift_transmission(r[k].astype(xp.complex128), d).real, 0.0)
            unseen |= strips
        elif diffuser_drift == "auto" and k == 0:
            # a still first position vouches for the rest: an estimate costs about what LCS
            # spends on a position (0.37 s against 0.22 s for LCS K = 12 at 256^2 with all 12)
            break
    return drifts, unseen


def _seen_window(unseen: np.ndarray) -> tuple[slice, slice]:
    """The rectangle left when the unseen strips, which lie along the edges, are cropped off."""
    rows, cols = np.flatnonzero(~unseen.all(axis=1)), np.flatnonzero(~unseen.all(axis=0))
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def _tracking_background(phase, attenuation, background_mask, unseen) -> np.ndarray:
    """The given background mask, or the one detected, without the unseen strips (their
    values are extrapolated)."""
    mask = background_mask if background_mask is not None else bg.projection_background(phase, attenuation)
    return _seen_background(mask, unseen)
