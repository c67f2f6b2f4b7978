"""What the speckle can carry: the reference's visibility and speckle grain, and how far a
retrieved phase moves that speckle against its grain (not in the paper).

A sample is seen through the speckle it moves: a phase gradient grad(phi) tilts the wave by
lambda grad(phi) / 2 pi, which shifts the speckle on the detector by

    d = lambda L2 |grad phi| / (2 pi p)   pixels (p the pixel size),

the quantity every speckle-tracking method measures and the one the 80 random geometries of
docs/validation.md sort by. Where d is a small fraction of the speckle grain g (the width of
the reference's autocorrelation), or the speckle itself is faint, the measured frame hardly
differs from the reference and no single-image method gets the phase back: PWF returns too
little of it (or, rarely, too much). :func:`assess` measures d / g on the retrieved phase, and
the visibility and :func:`phase_sensitivity` (how much a unit phase gradient changes the
frame) on the reference, and words a warning where one lies below :class:`SensitivityLimits`
(benchmarks/sensitivity_check.py: on 160 random geometries and the paper's optics at 16-25 keV
no holding scene is flagged, and over half the failures are; the others read part of the phase).

The other way to fail is the fit's own: where the sample is too steep or too dark for the
iteration to follow (a phase wrapped by several pi, a local minimum), the model leaves misfit
in the sample that it does not leave in the background. :func:`sample_misfit` compares the two
on the photon-noise scale, and :func:`assess` warns above ``max_sample_misfit`` (session 84:
the stability map's 100 pi and 10x absorption points read 2.75 and 1.61, every holding scene
of 151 random geometries at most 1.19). Where the data fit but carry the phase
only in part (the random geometries' middle band), the misfit is the background's too: the
failures there fit their data as well as the holding scenes do, and no residual tells them apart.

Both reference measures come from one power spectrum with its white photon-noise floor taken
out (:func:`pwf_dask.calibration.white_noise_floor`'s corners): photon noise would otherwise
add to the visibility and narrow the autocorrelation. Every function runs on its input's
array module (NumPy or CuPy); the numbers come back as Python floats.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pwf_dask.backend import get_array_module, ndimage

#: the fewest sample pixels (outside the background mask) the shift's percentile is taken over;
#: with fewer the whole frame is used
MIN_SAMPLE_PIXELS = 100
#: which percentile of the sample's speckle shift stands for the sample (its steepest edges
#: without the few pixels noise or a defect makes steeper)
SHIFT_PERCENTILE = 99.0


@dataclass(frozen=True)
class SensitivityLimits:
    """Below these the data carry little of the phase (benchmarks/results/sensitivity_check.md).
    Set again in session 91 under the default alpha rule, which reads more of a faint
    speckle's phase: on random scenes 0-79 the smallest shift that holds is 0.027 of the grain
    (the paper's 128^2 scene at 25 keV holds at 0.025, gain 1.06) and the faintest holding
    speckle's visibility 0.039 (under the fixed alpha, session 82: 0.044 and 0.05); checked on
    scenes 80-159.

    ``min_shift_over_grain``: the 99th percentile of the retrieved phase's speckle shift over
    the speckle grain. ``min_visibility``: the reference's rms over its mean, photon noise
    removed. ``max_sample_misfit``: :func:`sample_misfit`, the sample's misfit over the
    background's (above it the model does not fit the sample; benchmarks/results/sensitivity_check.md).
    ``max_position_disagreement``: :func:`position_disagreement` of a scan's K >= 2 diffuser
    positions (benchmarks/results/position_agreement.md: chosen in session 88 above every pair
    of scenes 0-79 where both hold; under the alpha rule (session 93) above all 43 such pairs of
    114, the largest 0.251, and 23 of the 47 failures the other limits miss lie above it).
    ``min_phase_sensitivity``: :func:`phase_sensitivity` of the reference, measured before any
    fit (session 92): no random scene of 0-159 below 7.2e-5 holds (31 of 151 lie below 3e-5,
    every one a failure, 7 of them unflagged by the other limits), and the paper's 256^2 scene
    still holds at 28 keV (4.8e-5 and 5.2e-5 on two draws, looked at after the limit was chosen
    among 2e-5 to 7e-5) and fails at 30 keV (3.4e-5, flagged by the visibility). Held-out
    scenes 160-239 (session 102): 20 of 21 below 3e-5 fail; scene 160 holds at 2.95e-5 (error
    0.12) and is the one holding scene of 113 the warning flags.
    """

    min_shift_over_grain: float = 0.02
    min_visibility: float = 0.035
    min_phase_sensitivity: float = 3e-5
    max_sample_misfit: float = 1.3
    max_position_disagreement: float = 0.35


@dataclass(frozen=True)
class Sensitivity:
    """What :func:`assess` measured; ``warning`` is None where the data carry the phase."""

    visibility: float
    speckle_grain_px: float
    speckle_shift_px: float
    shift_over_grain: float
    warning: str | None
    sample_misfit: float = float("nan")  # NaN: not measured (no residual, or no background)
    phase_sensitivity: float = float("nan")

    def parameters(self) -> dict:
        """The record ``RetrievalResult.parameters`` keeps."""
        return {
            "speckle_visibility": self.visibility,
            "speckle_grain_px": self.speckle_grain_px,
            "speckle_shift_px": self.speckle_shift_px,
            "speckle_shift_over_grain": self.shift_over_grain,
            "sample_misfit": self.sample_misfit,
            "phase_sensitivity": self.phase_sensitivity,
            "sensitivity_warning": self.warning,
        }


def _periodogram_and_floor(reference):
    """The reference's relative contrast's power spectrum (rfft2 layout), its white
    photon-noise floor and how many corner bins that floor was read from."""
    xp = get_array_module(reference)
    r = xp.asarray(reference, dtype=xp.float64)
    r = r / r.mean() - 1.0
    ny, nx = r.shape
    spec = xp.abs(xp.fft.rfft2(r)) ** 2 / (ny * nx)
    # the IOTF leaves no speckle beyond the Nyquist circle: there the periodogram is white
    # noise, exponentially distributed, so its median is ln 2 of the floor
    corners = _frequency_squared(spec.shape, ny, nx, xp) > 0.3
    n = int(corners.sum())
    noise = float(xp.median(spec[corners])) / np.log(2.0) if n else 0.0
    return spec, noise, n


def _frequency_squared(shape, ny: int, nx: int, xp):
    v, u = xp.fft.fftfreq(ny)[:, None], xp.fft.rfftfreq(nx)[None, :]
    return xp.broadcast_to(u * u + v * v, shape)


def _noise_free_spectrum(reference):
    """Power spectrum (rfft2 layout) of the reference's relative contrast with the white
    photon-noise floor subtracted and its mean removed: an unbiased estimate of the speckle's
    own spectrum, whose sums (variance, autocorrelation) carry no photon noise."""
    spec, noise, _ = _periodogram_and_floor(reference)
    # not clipped at zero: where there is no speckle, half the bins lie below the floor, and
    # clipping them would leave 37 % of the noise in every sum over the spectrum
    spec = spec - noise
    spec[0, 0] = 0.0
    return spec


def _real_sum(spec, nx: int) -> float:
    """Sum over the full 2-D spectrum of an rfft2-layout half (the columns that stand for two)."""
    return float((spec * _column_weight(spec.shape[1], nx, get_array_module(spec))).sum())


def _column_weight(columns: int, nx: int, xp):
    """How many bins of the full spectrum each rfft-half column stands for (two, save the zero
    and, for even ``nx``, the Nyquist column)."""
    weight = xp.full(columns, 2.0)
    weight[0] = 1.0
    if nx % 2 == 0:
        weight[-1] = 1.0
    return weight


def speckle_visibility(reference) -> float:
    """The reference's rms contrast over its mean, photon noise removed (sqrt of the
    noise-free spectrum's power, Parseval)."""
    nx = reference.shape[-1]
    return float(np.sqrt(max(_real_sum(_noise_free_spectrum(reference), nx) / reference.size, 0.0)))


def autocorrelation_fwhm_px(autocorrelation) -> float:
    """Mean full width at half maximum (pixels) of an autocorrelation (zero lag at [0, 0])
    along x and y, the half-maximum crossing interpolated linearly."""
    xp = get_array_module(autocorrelation)
    ac = autocorrelation / autocorrelation[0, 0]
    widths = []
    ny, nx = ac.shape
    for prof in (ac[0, : nx // 2], ac[: ny // 2, 0]):
        prof = np.asarray(prof.get() if xp is not np else prof)
        below = np.nonzero(prof < 0.5)[0]
        i = int(below[0]) if below.size else len(prof) - 1
        x = i - 1 + (prof[i - 1] - 0.5) / max(prof[i - 1] - prof[i], 1e-12)
        widths.append(2.0 * x)
    return float(np.mean(widths))


def phase_sensitivity(reference, wavelength_m: float, distance_m: float, pixel_size_m: float) -> float:
    """How much the data change per unit of phase gradient: the mean square of the relative
    intensity change a phase gradient of 1 rad per pixel makes by shifting the speckle,

        S = (lambda L2 / (2 pi p^2))^2 <|grad_px (I_ref / <I_ref>)|^2>,

    the gradient's power summed over the reference's noise-free spectrum
    (:func:`_noise_free_spectrum`, photon noise taken out). A phase gradient shifts the speckle
    by lambda L2 grad(phi) / (2 pi p) pixels (module docstring) and the intensity by minus that
    shift times grad(I), so S is the data term's curvature along the phase's gradient, the
    weight the regularizer's Im(alpha) is balanced against (:func:`pwf_dask.pwf.solver.sensitivity_alpha`).
    Weak speckle (visibility, blur), short L2, high energy and coarse pixels all lower it; the
    paper's 256^2 scene reads 0.0177."""
    xp = get_array_module(reference)
    spec = _noise_free_spectrum(reference)
    ny, nx = reference.shape
    gradient_power = _real_sum(spec * _gradient_weight(spec.shape, ny, nx, xp), nx) / reference.size
    return float(max(gradient_power, 0.0) * _shift_per_rad(wavelength_m, distance_m, pixel_size_m) ** 2)


def _gradient_weight(shape, ny: int, nx: int, xp):
    """|2 pi f|^2 per bin: a gradient's power from the spectrum's."""
    return (2 * np.pi) ** 2 * _frequency_squared(shape, ny, nx, xp)


def _shift_per_rad(wavelength_m: float, distance_m: float, pixel_size_m: float) -> float:
    return wavelength_m * distance_m / (2 * np.pi * pixel_size_m**2)


#: how many standard errors of :func:`phase_sensitivity`'s estimate make
#: :func:`phase_sensitivity_noise_bound`
NOISE_BOUND_SIGMAS = 2.0


def phase_sensitivity_noise_bound(reference, wavelength_m: float, distance_m: float, pixel_size_m: float) -> float:
    """The largest phase sensitivity the reference's photon noise could hide:
    :data:`NOISE_BOUND_SIGMAS` standard errors of :func:`phase_sensitivity`'s estimate (not in
    the paper).

    The estimate subtracts one noise floor, read as the median of n exponentially distributed
    corner bins (relative standard error 1 / (ln 2 sqrt(n))), from every bin, so the floor's
    error enters times the gradient weight |2 pi f|^2 summed over the spectrum; each bin's own
    scatter (an exponential's: its floor) adds in quadrature. At 1e2-1e3 ph/px the floor's term
    dominates and S can read 0 where the speckle carries 1e-4 to 1e-3: 4 of the 240 random
    geometries, and the rule's Im(alpha) then sits at its floor and the phase overshoots
    (:func:`pwf_dask.pwf.solver.rule_sensitivity`, docs/methods.md, "S read at low dose")."""
    xp = get_array_module(reference)
    spec, noise, n = _periodogram_and_floor(reference)
    ny, nx = reference.shape
    weight = _column_weight(spec.shape[1], nx, xp) * _gradient_weight(spec.shape, ny, nx, xp)
    floor_error = float(weight.sum()) / (np.log(2.0) * np.sqrt(max(n, 1)))
    scatter = float(np.sqrt(float((weight * weight).sum())))
    sigma = noise / reference.size * float(np.hypot(floor_error, scatter))
    return NOISE_BOUND_SIGMAS * sigma * _shift_per_rad(wavelength_m, distance_m, pixel_size_m) ** 2


#: the percentiles whose spread :func:`attenuation_contrast` reads (the sample's darkest part
#: against its background, without the few pixels noise or a defect makes darker or brighter)
CONTRAST_PERCENTILES = (1.0, 99.0)


def attenuation_contrast(sample, reference) -> float:
    """How far the sample's attenuation spans, read from the images before any retrieval: the
    spread between the 1st and 99th percentiles of -ln(G * y / G * I_ref) / 2, the amplitude
    attenuation of the local mean transmission, G a Gaussian as wide as the speckle grain
    (:func:`speckle_grain_px`) so that the speckle itself cancels in the ratio (not in the paper).

    Re(alpha) damps the attenuation outside the STF; where the attenuation is strong, what it
    damps the phase makes up (:func:`pwf_dask.pwf.solver.sensitivity_alpha`). On the stability
    map's scene it reads 0.14, 0.37, 1.17 and 2.26 for 1, 3, 10 and 20 times the beads' beta
    (true range 0.15, 0.46, 1.53, 3.06: the Gaussian spreads the beads' edges), the same from
    1e2 to 1e5 ph/px; the 240 random geometries read at most 0.66."""
    xp = get_array_module(sample, reference)
    sigma = max(1.0, speckle_grain_px(reference))
    nd = ndimage(xp)
    y = nd.gaussian_filter(xp.asarray(sample, dtype=xp.float64), sigma)
    r = nd.gaussian_filter(xp.asarray(reference, dtype=xp.float64), sigma)
    # a pixel with no light at all stands for a transmission of 1e-6 (an attenuation of 6.9)
    a = -0.5 * xp.log(xp.clip(y / xp.clip(r, 1e-30, None), 1e-6, None))
    lo, hi = (float(v) for v in xp.percentile(a, xp.asarray(CONTRAST_PERCENTILES)))
    return hi - lo


def speckle_grain_px(reference, *, subtract_noise: bool = True) -> float:
    """Speckle grain size (pixels): the mean FWHM of the reference's autocorrelation along x
    and y. ``subtract_noise=False`` keeps the photon noise's spike at zero lag (the measure of
    the committed random-scene and stability tables, benchmarks/stability.py)."""
    xp = get_array_module(reference)
    if subtract_noise:
        spec = _noise_free_spectrum(reference)
    else:
        r = xp.asarray(reference, dtype=xp.float64)
        spec = xp.abs(xp.fft.rfft2(r / r.mean() - 1.0)) ** 2
    if not float(spec.max()) > 0:
        return float("nan")
    return autocorrelation_fwhm_px(xp.fft.irfft2(spec, s=reference.shape))


def speckle_shift_px(phase, wavelength_m: float, distance_m: float, pixel_size_m: float, sample=None) -> float:
    """The sample's speckle shift lambda L |grad phi| / (2 pi p) in pixels at its
    :data:`SHIFT_PERCENTILE`, over the ``sample`` pixels (True = sample) where there are at
    least :data:`MIN_SAMPLE_PIXELS` of them, else over the frame. ``distance_m`` is the
    distance from the modulating plane to the detector (L2 of the paper)."""
    xp = get_array_module(phase)
    gy, gx = xp.gradient(xp.asarray(phase, dtype=xp.float64))
    slope = xp.hypot(gx, gy)
    if sample is not None and int(sample.sum()) >= MIN_SAMPLE_PIXELS:
        slope = slope[sample]
    return float(xp.percentile(slope, SHIFT_PERCENTILE)) * wavelength_m * distance_m / (2 * np.pi * pixel_size_m**2)


#: the transmission below which a pixel's photon noise is taken as at this floor: a nearly
#: opaque pixel's few counts would otherwise weigh its misfit without bound
MISFIT_INTENSITY_FLOOR = 0.05


def sample_misfit(residual, intensity, background, excluded=None) -> float:
    """The data misfit inside the sample over the misfit in its background, each the rms of
    ``residual / sqrt(intensity)`` (both relative to the mean reference; Poisson noise's
    standard deviation goes as the root of the intensity, so a fit to the noise reads 1 on a
    dark sample as on the bright background). ``background``: True = sample-free;
    ``excluded``: pixels left out of the fit. NaN where either side has fewer than
    :data:`MIN_SAMPLE_PIXELS` pixels."""
    xp = get_array_module(residual)
    r = xp.asarray(residual, dtype=xp.float64)
    weighted = r * r / xp.maximum(xp.asarray(intensity, dtype=xp.float64), MISFIT_INTENSITY_FLOOR)
    fitted = xp.ones(r.shape, dtype=bool) if excluded is None else ~xp.asarray(excluded)
    bg = xp.asarray(background) & fitted
    sample = ~xp.asarray(background) & fitted
    if int(bg.sum()) < MIN_SAMPLE_PIXELS or int(sample.sum()) < MIN_SAMPLE_PIXELS:
        return float("nan")
    return float(xp.sqrt(weighted[sample].mean() / weighted[bg].mean()))


#: the sample's pixels by the positions' mean phase: above this fraction of its largest |phase|
DISAGREEMENT_SAMPLE_FRACTION = 0.1


def position_disagreement(phases) -> list[float]:
    """How far K >= 2 diffuser positions' phases of one projection disagree (not in the paper).

    ``phases``: (K, ny, nx), each position's retrieved phase (independent speckle, the same
    sample and angle). For each position, the rms of its phase less the mean of the others'
    over the rms of all K's mean, where that mean's |phase| exceeds
    :data:`DISAGREEMENT_SAMPLE_FRACTION` of its largest; for K = 2 both read
    rms(phi_0 - phi_1) / rms((phi_0 + phi_1) / 2). A phase that is what the data tell agrees
    across diffusers; one the diffuser draw chose does not (session 88, random geometries 0-119:
    pairs where both hold 0.03-0.33, failures no other check flags 0.05-1.7; docs/validation.md,
    "What the data carry"). NaN where the mean has no phase.
    """
    xp = get_array_module(phases)
    a = xp.asarray(phases, dtype=xp.float64)
    k = a.shape[0]
    if a.ndim != 3 or k < 2:
        raise ValueError(f"position_disagreement needs (K >= 2, ny, nx) phases, got shape {tuple(a.shape)}")
    total = a.sum(axis=0)
    mean = total / k
    inside = xp.abs(mean) > DISAGREEMENT_SAMPLE_FRACTION * float(xp.abs(mean).max())
    norm = float(xp.sqrt(xp.mean(mean[inside] ** 2))) if bool(inside.any()) else 0.0
    if not norm > 0:
        return [float("nan")] * k
    return [float(xp.sqrt(xp.mean((a[p] - (total - a[p]) / (k - 1))[inside] ** 2))) / norm for p in range(k)]


def assess(
    phase,
    reference,
    *,
    wavelength_m: float,
    diffuser_detector_distance_m: float,
    pixel_size_m: float,
    background=None,
    residual=None,
    intensity=None,
    excluded=None,
    limits: SensitivityLimits = SensitivityLimits(),
    misfit_hint: str = "",
) -> Sensitivity:
    """Visibility, grain and :func:`phase_sensitivity` of ``reference``, the speckle shift of
    ``phase`` over the pixels ``background`` (True = sample-free) leaves, the fit's
    :func:`sample_misfit` where the ``residual`` and the measured ``intensity`` are given, and a
    one-line warning where the data carry little of the phase or the model does not fit the
    sample (:class:`SensitivityLimits`; ``misfit_hint``: :func:`misfit_warning`'s)."""
    visibility = speckle_visibility(reference)
    grain = speckle_grain_px(reference)
    sample = None if background is None else ~background
    shift = speckle_shift_px(phase, wavelength_m, diffuser_detector_distance_m, pixel_size_m, sample)
    ratio = shift / grain if grain > 0 else float("nan")
    s = phase_sensitivity(reference, wavelength_m, diffuser_detector_distance_m, pixel_size_m)
    problems = []
    if s < limits.min_phase_sensitivity:
        problems.append(insensitive_words(s, limits))
    if ratio < limits.min_shift_over_grain:
        problems.append(
            f"the sample moves the speckle by {ratio:.3f} of its {grain:.1f}-px grain "
            f"(below {limits.min_shift_over_grain:g})"
        )
    if visibility < limits.min_visibility:
        problems.append(f"the reference's speckle visibility is {visibility:.3f} (below {limits.min_visibility:g})")
    warnings = []
    if problems:
        warnings.append(
            "; ".join(problems) + ": the data carry little of the phase, and the phase "
            "returned is unreliable, mostly too low (docs/validation.md, 'What the data carry')"
        )
    misfit = float("nan")
    if residual is not None and intensity is not None and background is not None:
        misfit = sample_misfit(residual, intensity, background, excluded)
    if misfit > limits.max_sample_misfit:
        warnings.append(misfit_warning(misfit, limits, misfit_hint))
    return Sensitivity(visibility, grain, shift, ratio, "; ".join(warnings) or None, misfit, s)


def insensitive_words(sensitivity: float, limits: SensitivityLimits = SensitivityLimits()) -> str:
    """The words for data whose :func:`phase_sensitivity` lies below the limit (a projection's
    warning and a scan's summary line say it alike)."""
    return (
        f"the data's phase sensitivity is {sensitivity:.1e} (below {limits.min_phase_sensitivity:g}: "
        "the speckle's shift barely changes the frame)"
    )


#: what a misfit warning adds where L1 = 0 and no upstream distance was given: a diffuser
#: upstream of the sample, taken as at it, misfits so too (session 107: a 17 keV scan with the
#: diffuser 50 mm upstream read 1.40 on every projection without its distance, none over 1.3
#: with it)
UPSTREAM_MISFIT_HINT = (
    "; with L1 = 0 and no upstream distance given, a diffuser upstream of the sample misfits so too: "
    "give its distance (--diffuser-upstream-m) where it is known"
)


#: what a misfit warning adds where the diffuser's upstream distance was given: an extended
#: source also misfits there, and more than the limit, while delta holds (session 108: the
#: paper's optics, P3000 50 mm upstream, simulated with an extended source: every projection
#: over the limit, the largest 2.08, the bead +2.7 %, the cylinder -0.8 %)
EXTENDED_SOURCE_MISFIT_HINT = (
    "; with the diffuser upstream a source of finite size blurs the sample's own fringes less than the "
    "speckle, which PWF's one-blur model lacks: simulated so, every projection misfit (up to 2.1) while "
    "delta held within 3 % (docs/validation.md, 'An extended source')"
)


def misfit_hint(sample_diffuser_distance_m: float, diffuser_upstream_m: float) -> str:
    """What a misfit warning adds for where the diffuser sits: :data:`UPSTREAM_MISFIT_HINT`
    with L1 = 0 and no upstream distance, :data:`EXTENDED_SOURCE_MISFIT_HINT` with one, nothing
    with the diffuser downstream (L1 > 0)."""
    if sample_diffuser_distance_m != 0:
        return ""
    return EXTENDED_SOURCE_MISFIT_HINT if diffuser_upstream_m else UPSTREAM_MISFIT_HINT


def misfit_warning(misfit: float, limits: SensitivityLimits = SensitivityLimits(), hint: str = "") -> str:
    """The words for a fit that leaves ``misfit`` times the background's misfit in the sample,
    and ``hint`` (:func:`misfit_hint`) after them."""
    return (
        f"the fit leaves {misfit:.2f} times the background's misfit inside the sample (above "
        f"{limits.max_sample_misfit:g}): the model does not reach the sample's data (a steep or "
        "strongly absorbing sample, a local minimum), and the phase returned is unreliable "
        "(docs/validation.md, 'What the data carry')" + hint
    )
