"""Algorithm S1 of the paper: Nesterov-accelerated, preconditioned Wirtinger flow with a safe
step, momentum restarts and a robust stop (:func:`pwf`), and the discrepancy rule for alpha.

The model lives in :mod:`pwf_dask.pwf.model`, Algorithm S2 (forward model, Wirtinger
derivative, preconditioned direction, regularizer, curvature) in :mod:`pwf_dask.pwf.operators`
and the stop rule in :mod:`pwf_dask.pwf.stopping`; their public names are re-exported here, so
``solver.build_model``, ``solver.objective_and_direction`` and ``solver.STOP_RULE`` read as before.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any

import numpy as np

from pwf_dask.backend import host_numbers, inner
from pwf_dask.pwf import kernels
from pwf_dask.pwf.model import (  # noqa: F401  (re-exported)
    DEFAULT_ALPHA,
    PAPER_ALPHA,
    PAPER_FRESNEL_SCALE,
    PWFModel,
    _crop_spectrum,
    _pad_spectrum,
    build_model,
    fast_len,
    field_grid,
    interpolate_field,
    phase_block_scale,
    restrict_field,
)
from pwf_dask.pwf.operators import (  # noqa: F401  (re-exported)
    CURVATURE_ITERATIONS,
    Evaluation,
    _filter_real,
    largest_curvature,
    metric_norm,
    objective,
    objective_and_direction,
    objective_of_sums,
    objective_sums_and_direction,
    physical_model,
    regularizer_value,
    residual,
    wirtinger_derivative,
)
from pwf_dask.pwf.stopping import (  # noqa: F401  (re-exported)
    LOW_BAND_PX,
    PAPER_TOL,
    STATIONARY_TERMS,
    STOP_RULE,
    StopRule,
    _low_band_settled,
    _settled,
    _stationary,
    check_stationary_terms,
    low_band_filter,
    rms,
)

#: Im(alpha) tried by :func:`discrepancy_alpha` (Re(alpha) stays the paper's 0.1: raising it
#: damps a small bead's attenuation and the phase overshoots to compensate, docs/methods.md),
#: the rung tried first (the usual answer), and the residual the rule aims at, in units of
#: the photon noise.
ALPHA_IMAG_LADDER = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
ALPHA_LADDER_START = 2
DISCREPANCY_TARGET = 1.0

#: The data's phase sensitivity (:func:`pwf_dask.calibration.sensitivity.phase_sensitivity`)
#: from which ``alpha="sensitivity"`` keeps the default Im(alpha); below, it scales it by
#: sqrt(S / this), down to :data:`MIN_ALPHA_SCALE`. The scenes the default was tuned on, the
#: paper's (10 keV, 0.65 um pixels, L2 = 20 mm, P3000), read 0.0163-0.0181 (256^2 seeds 1-3,
#: 128^2, 512^2; 1e2-1e4 ph/px), so they keep it exactly; 20 keV reads 0.0004.
TUNED_PHASE_SENSITIVITY = 0.015
MIN_ALPHA_SCALE = 0.01
#: The sample's attenuation contrast (:func:`pwf_dask.calibration.sensitivity.attenuation_contrast`)
#: up to which ``alpha="sensitivity"`` keeps the default Re(alpha); above, it scales it by
#: (this / contrast)^2. The stability map's scene wants Re(alpha) 0.1 at 1-3x its beads' beta
#: (contrast 0.14-0.37), 0.03 at 5x (0.60), 0.02-0.03 at 7x, 0.01 at 10x (1.17) and 0.003 at
#: 20x (2.26) (docs/methods.md, "Re(alpha) and a strongly absorbing sample"). On 24 random
#: geometries with their beta scaled up (benchmarks/absorbing_samples.py) 0.4 held 12 and 13 at
#: attenuation ranges 1 and 2 where 0.7 held 10 and 9, losing none. It binds on 2 of the 240
#: random geometries as drawn (8 keV, 0.65): their phase errors 0.199 -> 0.203 and 0.270 -> 0.263,
#: their attenuation errors 0.23 -> 0.34.
TUNED_ATTENUATION_CONTRAST = 0.4
#: Where the reference's phase sensitivity reads none (S <= 0), the noise bound
#: (:func:`pwf_dask.calibration.sensitivity.phase_sensitivity_noise_bound`) from which the
#: rule takes that bound for S (:func:`rule_sensitivity`): noise that could hide over 3x the
#: warning limit's sensitivity. Chosen on random geometries 0-1059 (every S = 0 scene it binds on
#: gained) and checked on 1060-3239 (docs/methods.md, "S read at low dose").
NOISE_HIDDEN_SENSITIVITY = 1e-4

#: A gradient restart after two steps psi_k - psi_{k-1} this anti-aligned (cosine below it)
#: was caused by a mode too stiff for eta (see :func:`pwf`, "Step"): eta is halved.
STIFF_COSINE = -0.5

#: Momentum restart rules of :func:`pwf`; ``"none"`` is plain Algorithm S1.
RESTARTS = ("gradient", "function", "none")


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


#: eta of Algorithm S1 in units of 1/L (with the step search), and the width of the
#: regularization window over the STF (Eq. (regularization window)): defaults of every caller
DEFAULT_STEP = 1.0
DEFAULT_GAMMA = 1.0


@dataclass
class _Trial:
    """What accepting the iterate psi takes beyond J: its step, the field correlation and the
    descent point of Algorithm S1, lines 12-14. It is computed before J decides whether psi is
    accepted, so that one transfer fetches its sums with J's (:func:`pwf`): on a GPU each fetch
    of a sum is a synchronisation, and an iteration fetched seven (session 63). Where psi is
    rejected (rarely) the passes are wasted."""

    eta: float  # the eta ``phi`` was taken with
    phi: Any  # psi - eta d
    uphill: Any  # Re<d, phi - phi_prev>, the gradient restart's test
    x_sq: Any  # |x|^2
    dpsi: Any = None  # psi - psi_{k-1} (None at the first accepted point)
    step_sq: Any = None  # |psi - psi_{k-1}|^2
    overlap: Any = None  # <x_{k-1}, x>
    scale: Any = None  # rms(psi) for the step test, fetched ahead on a device only

    SUMS = ("uphill", "x_sq", "step_sq", "overlap", "scale")

    def sums(self) -> list:
        return [getattr(self, name) for name in self.SUMS if getattr(self, name) is not None]

    def take(self, numbers: list) -> None:
        """Replace the sums by their fetched values (in :meth:`sums`' order)."""
        present = [name for name in self.SUMS if getattr(self, name) is not None]
        for name, number in zip(present, numbers, strict=True):
            setattr(self, name, number)


@dataclass
class _Run:
    """The state of one run of Algorithm S1 (:func:`pwf`) between iterations: Nesterov's
    momentum, the last accepted point, the step eta and what the stop rule watches."""

    xp: ModuleType
    fft: Any
    restart: str  # the momentum restart rule, one of RESTARTS
    rule: StopRule
    rise_tol: float  # a rise of J below this (relative) is the working precision's rounding
    phi_prev: Any
    low_pass: Any = None  # the low band's filter (None: not watched)
    eta: float = 0.0  # eta of Algorithm S1 (halved by the safety rules)
    mu: float = 1.0
    momentum_used: bool = False
    last: tuple | None = None  # (psi, J, direction, evaluation) of the last accepted point
    last_x_norm: float = 0.0
    steps: list[float] = field(default_factory=list)  # rms steps since the last momentum restart
    recent_steps: list = field(default_factory=list)  # the last two accepted psi_k - psi_{k-1}
    history: list[float] = field(default_factory=list)
    data_history: list[float] = field(default_factory=list)  # J's data term, L / (4 N_t)
    low_band: list = field(default_factory=list)  # low-passed phase, one per window
    accepted: int = 0
    restarts: int = 0
    backtracks: int = 0
    streak: int = 0  # consecutive accepted iterations that pass the field correlation
    anchor_j: float = math.inf  # J at the start of the momentum run
    run_best: float = math.inf  # J's lowest value in the momentum run
    stalled: int = 0  # accepted iterations since run_best last fell
    halved: bool = False  # eta was halved at the last momentum restart
    scale: float | None = None  # rms of the last accepted psi where fetched with its trial
    low_band_still: bool | None = None  # _low_band_settled of the snapshots (None: not yet asked)

    @property
    def stall_limit(self) -> int:
        """Iterations without a new low of J after which momentum restarts; long on purpose:
        20 iterations cut productive runs at 1e3 ph/px (error 0.42 for 0.06)."""
        return 5 * self.rule.window

    def rose(self, j: float) -> bool:
        """J above the last accepted value (function rule); the gradient rule tolerates J
        at the extrapolated point oscillating inside a momentum run as long as it stays below
        the run's start. Never under ``"none"``."""
        if self.last is None or self.restart == "none":
            return False
        ref_j = self.anchor_j if (self.restart == "gradient" and self.momentum_used) else self.last[1]
        return j > ref_j * (1.0 + self.rise_tol)

    def restart_momentum(self) -> None:
        """Count a momentum restart; under the gradient rule, halve eta when a stiff mode
        caused it (:data:`STIFF_COSINE`), unless eta was halved at the restart before: that
        run's oscillation grew at the longer step."""
        self.restarts += 1
        self.steps.clear()  # the stop's rate estimate starts afresh with the run (_settled)
        if self.restart != "gradient" or len(self.recent_steps) < 2:
            return
        if self.halved:
            self.halved = False
            return
        before, now = self.recent_steps
        sums = [
            inner(before, now, host=False).real,
            inner(before, before, host=False).real,
            inner(now, now, host=False).real,
        ]
        overlap, before_sq, now_sq = host_numbers(sums)
        cosine = overlap / math.sqrt(before_sq * now_sq or 1.0)
        if cosine < STIFF_COSINE:
            self.eta *= 0.5
            self.backtracks += 1
            self.halved = True

    def reject(self) -> tuple:
        """Discard the point where J rose: a momentum restart, or after a plain step a halved
        eta. Returns the last accepted (psi, J, direction, evaluation) to go on from."""
        if self.momentum_used:
            self.restart_momentum()
        else:
            self.backtracks += 1
            self.eta *= 0.5
            self.steps.clear()
        self.mu = 1.0
        self.momentum_used = False
        self.streak = 0
        return self.last

    def trial(self, psi, d, ev, k: int) -> _Trial:
        """The passes and sums that accepting ``psi`` (iteration ``k``) would take, the sums
        left on the device (see :class:`_Trial`)."""
        phi, uphill = kernels.descent_point(psi, d, self.phi_prev, self.eta, host=False)
        if self.last is None:
            return _Trial(self.eta, phi, uphill, x_sq=inner(ev.x, ev.x, host=False).real)
        dpsi, step_sq = kernels.step_and_norm(psi, self.last[0], host=False)
        x_sq, overlap = kernels.field_correlation(ev.x, self.last[3].x, host=False)
        rule = self.rule
        # on the CPU the step test's scale costs a pass, not a round trip: taken when asked
        ahead = self.xp is not np and rule.tol > 0 and rule.rtol > 0 and k >= rule.min_iter
        scale = rms(psi, self.xp) if ahead else None
        return _Trial(self.eta, phi, uphill, x_sq, dpsi, step_sq, overlap, scale)

    def accept(self, psi, j: float, d, ev, data_j: float, trial: _Trial) -> None:
        """Record an accepted point from its fetched ``trial``: its step, the field correlation
        with the last one (Algorithm S1, line 14), J for the momentum run, J's data term
        ``data_j`` for the stop, the low band."""
        x_norm = math.sqrt(trial.x_sq)
        if self.last is not None:
            self.recent_steps = [*self.recent_steps[-1:], trial.dpsi]
            self.steps.append(math.sqrt(trial.step_sq / trial.dpsi.size))
            corr = abs(trial.overlap) / (x_norm * self.last_x_norm)
            self.streak = self.streak + 1 if 1.0 - corr < self.rule.tol else 0
        self.last_x_norm = x_norm
        self.scale = trial.scale
        if not self.momentum_used:
            self.anchor_j = j
            self.run_best, self.stalled = j, 0
        elif j < self.run_best:
            self.run_best, self.stalled = j, 0
        else:
            self.stalled += 1
        self.last = (psi, j, d, ev)
        self.history.append(j)
        self.data_history.append(data_j)
        self.accepted += 1
        if self.low_pass is not None and self.accepted % self.rule.window == 0:
            band = _filter_real(self.xp.ascontiguousarray(psi.imag), self.low_pass, self.fft)
            self.low_band = [*self.low_band[-2:], band]
            self.low_band_still = None

    def converged(self, psi, k: int) -> bool:
        """The stop rule (:class:`StopRule`, see :func:`pwf`) after the accepted iterate ``k``."""
        rule = self.rule
        if not (rule.tol > 0 and self.streak >= rule.patience and k >= rule.min_iter):
            return False
        if _settled(self.steps, psi, rule.rtol, rule.window, self.xp, self.scale):
            return True
        stationary = _stationary(self.history, rule.jtol, rule.window) or (
            rule.stationary_terms == "j-or-data" and _stationary(self.data_history, rule.jtol, rule.window)
        )
        if not stationary or self.low_pass is None:
            return stationary
        if self.low_band_still is None:  # asked once per snapshot: its sums cost a round trip
            self.low_band_still = _low_band_settled(self.low_band, rule.rtol, self.xp, rule.low_band_atol_rad)
        return self.low_band_still

    def extrapolate(self, psi, d, trial: _Trial | None = None):
        """Algorithm S1, lines 12-13: phi = psi - eta d and the next point
        phi + beta (phi - phi_prev), with the momentum dropped when it points uphill along
        the preconditioned gradient or has made no new low of J for :attr:`stall_limit`
        iterations (the uphill test can stay silent for ever while J oscillates: at
        L1 = 0, one 1000-iteration run). phi is the accepted ``trial``'s where it was taken
        with this eta."""
        if trial is not None and trial.eta == self.eta:
            phi, uphill = trial.phi, trial.uphill
        else:  # a rejected point, or eta set by the first step search: momentum is off (beta 0)
            phi, uphill = kernels.descent_point(psi, d, self.phi_prev, self.eta, host=False)
        mu_prev = self.mu
        self.mu = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * self.mu * self.mu))
        beta = (mu_prev - 1.0) / self.mu
        if self.restart == "gradient" and beta > 0 and (uphill > 0 or self.stalled >= self.stall_limit):
            self.restart_momentum()
            self.mu, beta = 1.0, 0.0
            self.stalled = 0
        self.momentum_used = beta > 0
        psi = kernels.momentum_point(phi, self.phi_prev, beta) if self.momentum_used else phi
        self.phi_prev = phi
        return psi


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
    low_band_atol_rad: float = STOP_RULE.low_band_atol_rad,
    stationary_terms: str = STOP_RULE.stationary_terms,
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
    disables this test), or J stationary (``stationary_terms="j-or-data"``: J or its data term
    L / (4 N_t)): its best value changed by less than ``jtol`` (relative) from one window to the
    next over each of the last two windows (:func:`_stationary`; ``jtol`` = 0 disables it)
    while the phase's structure wider than ``low_band_px`` has settled as well
    (:func:`_low_band_settled`, ``low_band_px`` = 0 leaves it out; not while its last window
    moved ``low_band_atol_rad`` rms or more, 0 drops that floor).

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
    check_stationary_terms(stationary_terms)
    xp = model.xp
    psi = xp.zeros(model.shape, dtype=model.cdtype) if psi0 is None else xp.asarray(psi0, dtype=model.cdtype)
    rule = StopRule(
        max_iter=max_iter,
        tol=tol,
        min_iter=min_iter,
        patience=patience,
        rtol=rtol,
        jtol=jtol,
        window=window,
        low_band_px=low_band_px,
        low_band_atol_rad=low_band_atol_rad,
        stationary_terms=stationary_terms,
    )
    # J is summed in float64 from residuals rounded to the working precision: a rise
    # smaller than that rounding is noise, not a failed step
    run = _Run(
        xp=xp,
        fft=model.fft,
        restart=restart,
        rule=rule,
        rise_tol=1e-5 if model.rdtype == np.float32 else 1e-11,
        phi_prev=psi,
        low_pass=low_band_filter(model.shape, xp, model.rdtype, low_band_px) if low_band_px > 0 else None,
        eta=float(step),
    )
    converged = False
    reason = "max_iter"
    k = 0
    while k < max_iter:
        k += 1
        # an over-long trial step may overflow exp(psi); J is then inf and the step is rejected
        with np.errstate(over="ignore", invalid="ignore"):
            sums, d, ev = objective_sums_and_direction(psi, y, model)
            trial = run.trial(psi, d, ev, k)
            numbers = host_numbers([*sums, *trial.sums()])  # the iteration's one transfer
        ev.loss = numbers[0]
        j = objective_of_sums(numbers[: len(sums)], model)
        trial.take(numbers[len(sums) :])
        if not math.isfinite(j):
            if run.last is None:
                raise FloatingPointError("PWF objective is not finite at the first iterate")
            if restart == "none":
                reason = "non-finite objective"
                break  # plain Algorithm S1 has no way back: it diverged
            j = math.inf  # a rejected trial step; the run goes on from the last accepted point
        if run.rose(j):
            psi, j, d, ev = run.reject()
            trial = None
            if run.eta < 1e-12 * step:
                reason = "step collapsed"
                break
        else:
            if run.last is None and step_search:
                run.eta = step / largest_curvature(psi, y, model, direction=d)
            run.accept(psi, j, d, ev, ev.loss / (4.0 * model.norm), trial)
            if callback is not None:
                callback(k, j, psi)
            if run.converged(psi, k):
                converged = True
                reason = "converged"
                break
        psi = run.extrapolate(psi, d, trial)
    psi_best, _, _, ev_best = run.last
    return PWFSolution(
        psi=psi_best,
        evaluation=ev_best,
        iterations=k,
        converged=converged,
        objective_history=run.history,
        step=run.eta,
        restarts=run.restarts,
        backtracks=run.backtracks,
        stop_reason=reason,
    )


def rule_sensitivity(phase_sensitivity: float, noise_bound: float | None = None) -> float:
    """The S that ``alpha="sensitivity"`` balances Im(alpha) against (not in the paper): the
    reference's phase sensitivity as read, except where it reads none (S <= 0) while its
    photon noise could hide at least :data:`NOISE_HIDDEN_SENSITIVITY` (``noise_bound``,
    :func:`pwf_dask.calibration.sensitivity.phase_sensitivity_noise_bound`): then that bound.

    Why: at 1e2-1e3 ph/px the noise floor's own error can take the estimate below zero where
    the speckle carries 4e-5 to 5e-4 (random geometries 53, 96, 143, 237). S = 0 puts Im(alpha)
    at its floor, the phase then fits the noise and overshoots (gains 2.3-2.9). The bound
    regularizes as much as the data could need; where the noise hides little (a bound under
    1e-4: a geometry that truly sees no phase), the floor stays, since there the bound lost
    (docs/methods.md, "S read at low dose"). The warning keeps S as read."""
    if phase_sensitivity <= 0.0 and noise_bound is not None and noise_bound >= NOISE_HIDDEN_SENSITIVITY:
        return float(noise_bound)
    return phase_sensitivity


def sensitivity_alpha(
    phase_sensitivity: float,
    base: complex = DEFAULT_ALPHA,
    tuned: float = TUNED_PHASE_SENSITIVITY,
    min_scale: float = MIN_ALPHA_SCALE,
    attenuation_contrast: float = 0.0,
    tuned_contrast: float = TUNED_ATTENUATION_CONTRAST,
) -> complex:
    """Im(alpha) balanced against how strongly the data see the phase: the rule of
    ``alpha="sensitivity"`` (an option, not in the paper).

    Algorithm S2's phase penalty Im(alpha) (u^2+v^2) Gamma^2 |Im psi|^2 grows as the phase's
    gradient does, and so does the data term's curvature along it, S times that gradient's
    square (:func:`pwf_dask.calibration.sensitivity.phase_sensitivity`). A fixed alpha, tuned
    where S is the paper's, outweighs data that see the phase 10-100x more weakly (faint
    speckle, short L2, high energy, coarse pixels): started from the true psi, PWF walks to 0.65
    of the phase on such scenes, the optimum of J, not a stop too early (6000 iterations give
    the same). Lowering Im(alpha) by sqrt(S / tuned) there, a middle way between keeping the
    penalty (bias) and scaling it by S (the balance the paper's scene has, at the cost of the
    noise): on 80 random geometries PWF then holds on 43 instead of 33 (docs/methods.md,
    "Im(alpha) from the data's phase sensitivity"). The default since session 91, once the
    background of a projection was found whole (:func:`pwf_dask.physics.background.projection_background`):
    on the wide 430 x 2220 strip of thick rods the rule's phase then holds as the fixed alpha's
    does (rms error 8.05 / 8.10 rad).

    Re(alpha) is seen through the mean intensity, not the speckle's shift, and S does not move
    it. It damps the attenuation outside the STF by a fixed fraction; where the sample absorbs
    strongly, the intensity that fraction leaves unexplained is large and the phase makes it up
    (a lens over each dark bead): the stability map's 10x absorption failed at 0.264 with
    misfit 1.66, and started from the true psi PWF walks to the same answer. Above
    ``tuned_contrast`` of the sample's ``attenuation_contrast``
    (:func:`pwf_dask.calibration.sensitivity.attenuation_contrast`) Re(alpha) is scaled by
    (tuned_contrast / contrast)^2, Tikhonov's noise-over-signal squared (docs/methods.md,
    "Re(alpha) and a strongly absorbing sample"). At or above ``tuned`` and at or below
    ``tuned_contrast`` ``base`` is returned exactly.
    """
    real = base.real
    if attenuation_contrast > tuned_contrast:
        real *= (tuned_contrast / attenuation_contrast) ** 2
    if not phase_sensitivity < tuned:
        return complex(real, base.imag)
    scale = max(math.sqrt(max(phase_sensitivity, 0.0) / tuned), min_scale)
    return complex(real, base.imag * scale)


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
