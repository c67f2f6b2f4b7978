"""When Algorithm S1 stops: the paper's field-correlation test and the tests that keep it from
stopping inside Nesterov's oscillation dips or while wide structure still moves (:class:`StopRule`)."""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

import numpy as np

from pwf_dask.backend import host_numbers
from pwf_dask.physics import optics

#: The paper's stop rule: normalised correlation of successive fields > 10^-0.00001.
PAPER_TOL = 1.0 - 10.0 ** (-0.00001)


def rms(psi, xp):
    """rms(psi), a 0-d array of psi's precision on psi's device: the step test's scale."""
    return xp.sqrt(xp.mean(psi.real**2 + psi.imag**2))


def _settled(steps: list[float], psi, rtol: float, window: int, xp, scale: float | None = None) -> bool:
    """Extrapolated remaining change of psi below ``rtol`` rms(psi) (see :func:`~pwf_dask.pwf.solver.pwf`;
    ``scale``: rms(psi) where already fetched).

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
    if not rho < 1.0:  # steps equal to rounding: no geometric tail to extrapolate
        return False
    remaining = s2 * rho / (1.0 - rho)
    scale = float(rms(psi, xp)) if scale is None else scale
    return remaining < rtol * max(scale, 1e-12)


def _stationary(history: list[float], jtol: float, window: int) -> bool:
    """J's best value changed by less than ``jtol`` (relative) from one ``window`` to the next,
    over each of the last two such steps.

    The psi test of :func:`_settled` cannot pass while a low-frequency phase creeps at a
    constant rate along a direction that neither the data nor Gamma^2 constrain (measured at
    L1 = 0: 0.04 rad rms in 800 iterations, J changing 4e-5). J then no longer moves, and
    the creep does not change the fit.

    A window whose best J lies *above* the one before is not stationary: after a momentum
    restart J ripples (the gradient rule lets it rise below the run's start), and a rise had
    passed as "fell by less than jtol". On the full-width paper scan every projection from
    zero stopped so at 220 iterations, 0.6 % above the misfit PWF reaches and 1.8-2.1 rad rms
    (2 % of the phase) away from its 1500-iteration solution; with the rise refused it stops
    at 460, 0.13-0.16 rad away (session 45).

    One quiet window is not enough: J's descent can pause for a window and resume. On the
    geometry sweep's 0.33 um pixel scene (256^2) the best J fell 2.5e-4, 2.8e-5, then 5.7e-5
    to 8.1e-5 per window; the single test stopped at that pause (220 iterations, phase error
    0.078 against 0.067 at 520). With two steps it stops at 520, while full-width warm starts
    take 0-20 iterations more (session 47, docs/methods.md).

    With ``StopRule.stationary_terms="j-or-data"`` :func:`~pwf_dask.pwf.solver.pwf` asks it of
    J and of J's *data term* L / (4 N_t), and either will do: the regularizer's part can go on
    falling where the data say nothing, the padding margin, whose phase bridges the sample
    across the grid's periodic edges. On the camera's 2160 x 2560 frame the data term was flat
    from iteration 140 (59.16 to 4 digits) while the regularizer's fell 30.97 -> 30.43 to
    iteration 587, where the test on J let the run stop; the data term's test stops it at 300,
    nearer the true phase (5.51 rad rms against 5.59; session 62, docs/validation.md). The
    default since session 67: on small frames from zero it stops much sooner too (the 256^2
    P3000 scene 174 iterations for 360) at a median error change of +1 %, while warm starts
    there gain little over it (session 62; ``"j"``, J alone, is the former rule). The data term
    alone is no rule either: where the regularizer's fall is bought with a slight rise of the
    misfit, J settles first (a random scene: J's test at 217 iterations, the data term's at 520).
    """
    if jtol <= 0 or len(history) < 3 * window:
        return False
    bests = [min(history[-k * window : len(history) - (k - 1) * window]) for k in (3, 2, 1)]
    return all(abs(a - b) < jtol * abs(a) for a, b in zip(bests, bests[1:]))


#: What :func:`_stationary` is asked of (:class:`StopRule`): J alone, or J or its data term
STATIONARY_TERMS = ("j", "j-or-data")


def check_stationary_terms(value) -> None:
    """Refuse a ``stationary_terms`` outside :data:`STATIONARY_TERMS` in one line."""
    if value not in STATIONARY_TERMS:
        raise ValueError(f"stationary_terms must be one of {', '.join(STATIONARY_TERMS)}, got {value!r}")


#: Scales the low-band stop test watches (:func:`_low_band_settled`): phase structure wider
#: than this many pixels, the wide smooth objects whose phase the data fix only weakly
LOW_BAND_PX = 64.0


def low_band_filter(shape: tuple[int, int], xp: ModuleType = np, dtype=np.float32, width_px: float = LOW_BAND_PX):
    """Gaussian low pass exp(-2 pi^2 sigma^2 q^2) with sigma = ``width_px`` / 4 (half spectrum):
    keeps structure wider than ``width_px``, whatever the frame size."""
    v, u = optics.frequency_grid(shape, 1.0, half=True)
    sigma = width_px / 4.0
    return xp.asarray(np.exp(-2.0 * np.pi**2 * sigma**2 * (u * u + v * v)).astype(dtype))


def _low_band_settled(snapshots: list, rtol: float, xp, atol_rad: float = 0.0) -> bool:
    """The low band of the phase (:func:`low_band_filter`, one snapshot per stop window) has
    stopped moving: its change over the last window is below ``atol_rad`` (rms, radians) and,
    extrapolated at the rate of the two windows before (a geometric tail), below ``rtol``
    times its rms.

    :func:`_stationary` alone lets a run stop while J no longer moves but the phase of wide
    objects still does (issue #27 asks that such a run never be called converged; on the
    simulated strips of that issue the low band had settled when J had, and this test added
    13 iterations). A change that does not shrink from one window to the next is not
    settled unless it is below ``rtol`` / 100 of the rms (rounding).

    Why an absolute floor (``atol_rad``, :attr:`StopRule.low_band_atol_rad`, off by default;
    session 73): after a momentum restart the band pauses for a window, and that lull against
    the fast window before it reads as a steep geometric tail, while a deep sample's rms makes
    ``rtol`` x rms generous. The ``paper`` preset's rod on a 96 x 2560 crop from zero stops so at
    205 iterations, 7.09 rad rms from the truth, its band moving 0.09-0.15 rad a window for 200
    iterations more (J's test alone: 430, 4.87 rad). Not settled while the last window moved
    0.05 rad or more, it stops at 400, 4.90 rad; the 80 random geometries, six small cold P3000
    frames (256^2 and 384^2, seeds 1-3), the camera's 270 rows from zero and warm-started, and
    the issue's 430 x 2220 strip stop where they did, to the digit (0.02 rad holds two small
    frames 2x longer for nothing); but the whole 2160 x 2560 camera frame from zero runs 658
    iterations for 300 at the same phase, so it is an option (docs/validation.md)."""
    if rtol <= 0:
        return True
    if len(snapshots) < 3:
        return False
    a, b, c = snapshots[-3:]
    sums = [xp.sqrt(xp.mean(c * c)), xp.sqrt(xp.mean((b - a) ** 2)), xp.sqrt(xp.mean((c - b) ** 2))]
    scale, d1, d2 = (float(v) for v in host_numbers(sums))
    if atol_rad > 0 and d2 >= atol_rad:
        return False
    scale = max(scale, 1e-12)
    if d2 < 0.01 * rtol * scale:
        return True
    if not d2 < d1:
        return False
    rho = d2 / d1
    return d2 * rho / (1.0 - rho) < rtol * scale


@dataclass(frozen=True)
class StopRule:
    """When :func:`~pwf_dask.pwf.solver.pwf` stops: the defaults of every caller (retrieval, pipeline,
    CLI), defined here once.

    ``tol``: the paper's field-correlation test (Algorithm S1, line 14), met on ``patience``
    consecutive accepted iterations and not before ``min_iter``; ``rtol``: the extrapolated
    remaining change (:func:`_settled`, over ``window``-iteration windows); ``jtol``: J
    stationary (:func:`_stationary`; ``stationary_terms="j-or-data"``: J or its data term) with
    the band wider than ``low_band_px`` settled (:func:`_low_band_settled`; with
    ``low_band_atol_rad`` > 0 its last window's change below that too); ``max_iter``: the cap.
    See :func:`~pwf_dask.pwf.solver.pwf`.

    ``jtol`` 3e-5 (1e-5 until session 46): warm-started full-width projections stop at 187-200
    iterations instead of 340-360 with the same error against the true phase (4.07 / 4.12 rad
    rms against 4.06 / 4.14, of ~97); from zero the low band holds the run to 460 either way
    (``benchmarks/results/warm_stop.md``, docs/methods.md). With the J test over two windows
    (session 47) the whole full-width scan's warm starts take 233 on average (224 over one) and
    the mean error against the true phase is 5.49 rad rms (5.51; ``bench_fullwidth_cpu.md``).

    ``low_band_atol_rad`` (session 73; 0, off, by default): the low band is not settled while its
    last window moved that much (0.05 rad: a deep rod's cold crop that the default stops at 205
    iterations, 7.09 rad rms off, runs to 400 and 4.90; :func:`_low_band_settled`). Not the
    default: the whole camera frame from zero then takes 658 iterations for 300 at the same phase
    (gain 0.9495, 5.516 rad against 0.949, 5.52): its wide structure goes on moving from 300 to
    658 without nearing the truth (the measured frame alone, margin left out, reads the same).

    ``stationary_terms`` "j-or-data" ("j" until session 67): the J test also passes on J's data
    term, which settles long before the padding margin's regularizer on large frames (the
    camera frame from zero 300 iterations for 587, session 62) and on small cold P3000 frames
    (174 for 360 at the same phase error, median +1 % over nine frames; docs/validation.md).
    """

    max_iter: int = 2000
    tol: float = PAPER_TOL
    min_iter: int = 50
    patience: int = 10
    rtol: float = 1e-3
    jtol: float = 3e-5
    window: int = 20
    low_band_px: float = LOW_BAND_PX
    low_band_atol_rad: float = 0.0
    stationary_terms: str = "j-or-data"


#: the stop rule every caller defaults to
STOP_RULE = StopRule()
