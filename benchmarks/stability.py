"""Where each method fails: the stability map (issue 4), one projection against known truth.

One base scene (the paper's optics: 10 keV, 0.65 um pixels, L1 = 3 mm, L2 = 20 mm, coherence
lengths 3.47 / 4.31 um, four layers of P3000 SiC sandpaper, 1e4 photons per pixel, the
cellulose rod with glass beads) is varied along one axis at a time:

- ``dose``: photons per pixel, 1e2 - 1e6 (Poisson noise);
- ``max_phase_pi``: sample thickness along the beam, the projected delta and beta scaled so the
  largest phase shift is 1 - 100 pi (a thicker or denser sample of the same shape);
- ``absorption``: the projected beta scaled by 0 - 10 at the base's phase (0: a pure phase
  object, where single-image geometric flow is meant to hold);
- ``gradient``: the phantom shrunk laterally by 1, 1/2, 1/4, 1/8 at the base's largest phase, so
  the phase gradient, i.e. the speckle displacement relative to the grain size, grows 1 - 8 x;
- ``l2_mm``: diffuser-detector distance 5 - 80 mm, which sets the speckle grain and the
  displacement; the source blur (the coherence PSF) grows in proportion to L2;
- ``coherence_error``: PWF given coherence lengths 30 % short to 30 % long (the baselines do not
  use them);
- ``geometry``: the paper's L1 = 3 mm; sample and diffuser in one plane (L1 = 0); the
  diffuser 5 or 20 mm *upstream* of the sample (the sample lit by developed speckle; the
  algorithms see L1 = 0 and L2 = the sample-detector distance);
- ``ablation``: PWF without the preconditioner, without the regularization window (gamma = 0),
  and without the regularizer (alpha = 0);
- ``bead_radius_px``: one glass bead of 4 - 32 px radius in the base cylinder (the paper's beads
  are <= 106 um across, i.e. up to ~80 px radius at 0.65 um): small strong features;
- ``grain_um``: the diffuser's median grain radius, 1 - 6 um (P3000 is 3.25 um);
- ``calibration``: PWF given the true coherence lengths (every other point), or calibrating
  them from its reference by the template fit (the default of ``retrieve_projection``) or by
  the paper's Gaussian alone.

PWF is given each point's true coherence lengths, so that the map measures the retrieval, except
in the column ``PWF K=1 calibrated``, which calibrates them from the point's own reference at
every point of every other axis, as a user's run does: where the two PWF columns part, the
calibration is what fails.

Every point reports the measured physical coordinates (largest phase in pi, 99th-percentile
speckle displacement over the grain size) beside the axis value, and for every method the phase
and attenuation errors: RMSE inside the sample relative to the RMS true value, after the
sample-free background (taken from the truth for every method alike, so the map measures the
retrieval, not background detection) is zeroed. A method *holds* at a point while its phase
error is below ``PHASE_ERROR_THRESHOLD``. Every point also reports the largest bead's local phase
contrast error (:func:`bead_contrast_error`), which the sample-wide RMSE hides: a bead is a few
per cent of the sample's pixels.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks.reporting import read_rows_csv
from pwf_dask import calibration
from pwf_dask.physics import optics
from pwf_dask.pwf.solver import PAPER_ALPHA
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import Phantom, SpeckleSetup, SpeckleSimulator, Sphere, default_phantom

PHASE_ERROR_THRESHOLD = 0.25

AXES: dict[str, list] = {
    "dose": [1e2, 1e3, 1e4, 1e5, 1e6],
    "max_phase_pi": [1.0, 3.0, 10.0, 30.0, 100.0],
    "absorption": [0.0, 0.1, 1.0, 10.0],
    "gradient": [1.0, 2.0, 4.0, 8.0],
    "l2_mm": [5.0, 10.0, 20.0, 40.0, 80.0],
    "coherence_error": [-0.3, -0.15, 0.0, 0.15, 0.3],
    "geometry": ["L1 = 3 mm", "L1 = 0", "diffuser 5 mm upstream", "diffuser 20 mm upstream"],
    "ablation": ["none", "no preconditioner", "gamma = 0", "alpha = 0"],
    "bead_radius_px": [4.0, 8.0, 16.0, 32.0],
    "dark_field_px": [0.0, 0.5, 1.0, 2.0],
    "pixel_um": [0.65, 1.0, 1.3, 2.0],
    "grain_um": [1.0, 2.0, 3.25, 4.5, 6.0],
    "calibration": ["true lengths", "template", "gaussian"],
}
PWF_ONLY_AXES = ("coherence_error", "ablation", "calibration")

# (label, method, K diffuser positions, options)
METHOD_RUNS: list[tuple[str, str, int, dict]] = [
    ("PWF K=1", "pwf", 1, dict(max_iter=500)),
    # as a user's run: the lengths calibrated from this point's own reference (the default fit)
    ("PWF K=1 calibrated", "pwf", 1, dict(max_iter=500, coherence_method="template")),
    ("PWF K=1 paper alpha", "pwf", 1, dict(max_iter=500, alpha=PAPER_ALPHA)),
    ("LCS K=12", "lcs", 12, {}),
    ("UMPA K=12 w5", "umpa", 12, dict(tracking_options={"window": 5})),
    ("UMPA K=1 w7", "umpa", 1, {}),
    ("GF K=1", "gf", 1, {}),
    ("MIST K=12", "mist", 12, {}),
]


def scaled_phantom(phantom: Phantom, lateral_scale: float) -> Phantom:
    """The phantom with every length (radii, positions) multiplied by ``lateral_scale``."""
    s = lateral_scale
    return replace(
        phantom,
        cylinder_radius_m=phantom.cylinder_radius_m * s,
        cylinder_u_m=phantom.cylinder_u_m * s,
        cylinder_v_m=phantom.cylinder_v_m * s,
        spheres=tuple(
            Sphere(sp.u_m * s, sp.y_m * s, sp.v_m * s, sp.radius_m * s, sp.material) for sp in phantom.spheres
        ),
    )


def single_bead(phantom: Phantom, radius_m: float) -> Sphere:
    """A glass bead of ``radius_m`` in the cylinder, off its axis by half the room left."""
    room = phantom.cylinder_radius_m - 1.05 * radius_m
    if room <= 0:
        raise ValueError(f"a bead of radius {radius_m:g} m does not fit the cylinder")
    return Sphere(phantom.cylinder_u_m + 0.5 * room, 0.0, phantom.cylinder_v_m, radius_m)


def speckle_grain_px(reference: np.ndarray) -> float:
    """Mean full width at half maximum (pixels) of the reference speckle's autocorrelation along
    x and y, photon noise included: the speckle grain size the displacement is compared with
    (:func:`pwf_dask.calibration.speckle_grain_px`, the measure of the committed tables)."""
    return calibration.speckle_grain_px(reference, subtract_noise=False)


def displacement_px(phase: np.ndarray, wavelength: float, l2_m: float, pixel_size_m: float) -> float:
    """99th percentile of the speckle displacement lambda L2 |grad phi| / (2 pi p) in pixels
    (CONTRACT §2), over the pixels where the phase changes."""
    gy, gx = np.gradient(phase)
    g = np.hypot(gx, gy)
    moving = g > 1e-3 * g.max() if g.max() > 0 else np.ones_like(g, bool)
    return float(np.percentile(g[moving], 99) * wavelength * l2_m / (2 * np.pi * pixel_size_m**2))


class Scene:
    """K diffuser positions of one sample at one set-up, noise-free until :meth:`images`."""

    def __init__(
        self,
        setup: SpeckleSetup,
        phantom: Phantom,
        phase_factor: float,
        positions: int,
        seed: int = 0,
        absorption_factor: float = 1.0,
        dark_field_px: float = 0.0,
    ):
        self.setup = setup
        sim = SpeckleSimulator(setup, seed=seed)
        self.sim = sim
        _, psi = sim.sample_field(phantom)
        psi = phase_factor * (absorption_factor * psi.real + 1j * psi.imag)
        field_ = np.exp(psi)
        self.phase = sim._bin(psi.imag)
        self.attenuation = sim._bin(-psi.real)
        shifts = [(7 * k, 13 * k) for k in range(positions)]
        blur = sim.dark_field_sigma_px(psi, dark_field_px)
        self.clean_samples = np.array([sim.intensity(field_, sim.diffuser(s), blur) for s in shifts])
        self.clean_references = np.array([sim.intensity(None, sim.diffuser(s)) for s in shifts])
        self.background = np.abs(self.phase) < 1e-6 * max(np.abs(self.phase).max(), 1e-30)
        self.bead = bead_regions(sim, phantom, phase_factor)

    def images(self, photons: float, k: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(sample, reference) stacks of the first ``k`` positions with Poisson noise at ``photons``."""
        rng = np.random.default_rng(seed)

        def noisy(a):
            return (rng.poisson(np.clip(a, 0, None) * photons) / photons).astype(np.float32)

        return noisy(self.clean_samples[:k]), noisy(self.clean_references[:k])


def calibrated_lengths(reference, setup: SpeckleSetup) -> dict:
    """The coherence options :func:`retrieve_projection` would calibrate for itself from
    ``reference`` (the template fit at the set-up's geometry, and whether its lengths include
    the pixel's blur), for benchmarks that calibrate once and pass them to several runs."""
    from pwf_dask import calibration

    fit = calibration.fit_coherence_lengths(
        reference,
        setup.pixel_size_m,
        energy_eV=setup.energy_eV,
        diffuser_detector_distance_m=setup.diffuser_detector_distance_m + setup.diffuser_upstream_m,
    )
    return {
        "coherence_length_x_m": fit.x_m,
        "coherence_length_y_m": fit.y_m,
        "coherence_includes_pixel_blur": fit.includes_pixel_blur,
    }


def bead_regions(sim: SpeckleSimulator, phantom: Phantom, phase_factor: float = 1.0, angle_deg: float = 0.0):
    """(inner, ring) masks of the largest bead's projection at ``angle_deg``, or None without beads.

    The footprint is the difference of the true phase with and without that bead, so it holds
    for any projection geometry; inner: within half the radius of its centroid, ring: 1.2-1.6
    radii (the local background the bead is seen against).
    """
    if not phantom.spheres:
        return None
    bead = max(phantom.spheres, key=lambda sp: sp.radius_m)
    rest = replace(phantom, spheres=tuple(sp for sp in phantom.spheres if sp is not bead))
    own = sim.sample_field(phantom, angle_deg)[1].imag - sim.sample_field(rest, angle_deg)[1].imag
    own = np.abs(sim._bin(own)) * phase_factor
    if not own.any():
        return None
    yy, xx = np.indices(own.shape)
    cy, cx = np.sum(own * yy) / own.sum(), np.sum(own * xx) / own.sum()
    r = np.hypot(yy - cy, xx - cx) * sim.setup.pixel_size_m / bead.radius_m
    inner, ring = r < 0.5, (r > 1.2) & (r < 1.6)
    return (inner, ring) if inner.any() and ring.any() else None


def bead_contrast_error(phase, truth_phase, bead) -> float:
    """Signed relative error of the bead's local phase contrast (inner mean - ring mean): the
    quantity the tomogram's bead delta inherits; + is an overshoot."""
    if bead is None:
        return float("nan")
    inner, ring = bead
    est = np.asarray(phase, np.float64)
    if not np.all(np.isfinite(est[inner | ring])):
        return float("inf")
    true = truth_phase[inner].mean() - truth_phase[ring].mean()
    return float((est[inner].mean() - est[ring].mean()) / true - 1.0)


def errors(phase, attenuation, truth_phase, truth_attenuation, background, bead=None) -> dict:
    """Relative RMSE of phase and attenuation inside the sample (|true phase| > 2 % of its max)."""
    inside = np.abs(truth_phase) > 0.02 * np.abs(truth_phase).max()

    def offset_free(est):
        est = np.asarray(est, np.float64)
        return est - np.mean(est[background]) if background.any() else est

    def rel(est, true):
        est = offset_free(est)
        if not np.all(np.isfinite(est[inside])):
            return float("inf")
        norm = np.sqrt(np.mean(true[inside] ** 2))
        if norm == 0:  # nothing to recover (a pure phase object's attenuation)
            return float("nan")
        return float(np.sqrt(np.mean((est - true)[inside] ** 2)) / norm)

    out = {"phase_error": rel(phase, truth_phase)}
    out["attenuation_error"] = rel(attenuation, truth_attenuation) if attenuation is not None else float("nan")
    est = offset_free(phase)[inside]
    ok = np.all(np.isfinite(est))
    # regression through the origin: both sides are zero on the background
    t = truth_phase[inside]
    gain_fit = float(np.dot(est, t) / np.dot(t, t)) if ok else np.nan
    out["phase_gain"] = gain_fit
    out["bead_contrast_error"] = bead_contrast_error(phase, truth_phase, bead)
    return out


def _point_setups(axis: str, value, base: SpeckleSetup):
    """(setup, lateral_scale, max phase target or None, absorption factor, photons, PWF
    overrides, dark-field blur in px) for one point."""
    setup, lateral, target, absorption, photons, pwf, dark = base, 1.0, None, 1.0, base.photons, {}, 0.0
    if axis == "dose":
        photons = float(value)
    elif axis == "max_phase_pi":
        target = float(value)
    elif axis == "absorption":
        absorption = float(value)
    elif axis == "gradient":
        lateral = 1.0 / float(value)
    elif axis == "l2_mm":
        f = float(value) * 1e-3 / base.diffuser_detector_distance_m
        setup = replace(
            base,
            diffuser_detector_distance_m=float(value) * 1e-3,
            coherence_length_x_m=base.coherence_length_x_m * f,
            coherence_length_y_m=base.coherence_length_y_m * f,
        )
    elif axis == "coherence_error":
        pwf = dict(
            coherence_length_x_m=base.coherence_length_x_m * (1 + float(value)),
            coherence_length_y_m=base.coherence_length_y_m * (1 + float(value)),
        )
    elif axis == "geometry":
        l1, upstream = {
            "L1 = 3 mm": (base.sample_diffuser_distance_m, 0.0),
            "L1 = 0": (0.0, 0.0),
            "diffuser 5 mm upstream": (0.0, 5e-3),
            "diffuser 20 mm upstream": (0.0, 20e-3),
        }[value]
        setup = replace(base, sample_diffuser_distance_m=l1, diffuser_upstream_m=upstream)
    elif axis == "ablation":
        pwf = {
            "none": {},
            "no preconditioner": dict(preconditioner=False),
            "gamma = 0": dict(gamma=0.0),
            "alpha = 0": dict(alpha=0.0),
        }[value]
    elif axis == "bead_radius_px":
        pass  # the phantom changes (stability_map), not the set-up
    elif axis == "dark_field_px":
        dark = float(value)
    elif axis == "pixel_um":
        # the same sample and beam on a coarser detector: the frame (256 px) sees more of it
        setup = replace(base, pixel_size_m=float(value) * 1e-6)
    elif axis == "grain_um":
        setup = replace(base, diffuser_radius_median_m=float(value) * 1e-6)
    elif axis == "calibration":
        # PWF calibrates the lengths from each reference itself (the baselines use none)
        pwf = {} if value == "true lengths" else {"coherence_method": value}
    else:
        raise ValueError(f"unknown stability axis {axis!r}: choose one of {', '.join(AXES)}")
    return setup, lateral, target, absorption, photons, pwf, dark


def point_methods(axis: str, methods: list[tuple[str, str, int, dict]]) -> list[tuple[str, str, int, dict]]:
    """The runs of one axis: on PWF's own axes (lengths given wrong, ablations, calibration
    methods) the PWF runs given their lengths, not the calibrated column; elsewhere all."""
    if axis in PWF_ONLY_AXES:
        return [m for m in methods if m[1] == "pwf" and "coherence_method" not in m[3]]
    return methods


def pwf_options(opts: dict, pwf_over: dict, setup: SpeckleSetup) -> dict:
    """PWF's keywords at one point: the true coherence lengths, unless the run or the point
    calibrates them from the reference; then the point's own overrides."""
    kw = dict(opts)
    if "coherence_method" not in opts and "coherence_method" not in pwf_over:
        kw.update(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    kw.update(pwf_over)
    return kw


def sensitivity_columns(parameters: dict) -> dict:
    """What PWF's own check measured at a point (:mod:`pwf_dask.calibration.sensitivity`):
    the retrieved phase's speckle shift over the grain, the reference's visibility, the fit's
    misfit in the sample over its background's, the reference's phase sensitivity and whether
    it warned; NaN and False for the methods that do not measure it."""
    return {
        "speckle_shift_over_grain": parameters.get("speckle_shift_over_grain", np.nan),
        "speckle_visibility_measured": parameters.get("speckle_visibility", np.nan),
        "sample_misfit": parameters.get("sample_misfit", np.nan),
        "phase_sensitivity": parameters.get("phase_sensitivity", np.nan),
        "flagged": bool(parameters.get("sensitivity_warning")),
    }


def stability_map(
    shape: tuple[int, int] = (256, 256),
    axes: dict[str, list] | None = None,
    methods: list[tuple[str, str, int, dict]] | None = None,
    seed: int = 0,
    progress: bool = True,
    base: SpeckleSetup | None = None,
) -> list[dict]:
    """All rows of the map: one per (axis, value, method), with errors and wall time. ``base``
    is the scene every axis varies (default: the paper's set-up, P3000 diffuser, ``shape``)."""
    axes = AXES if axes is None else axes
    methods = METHOD_RUNS if methods is None else methods
    base = base or SpeckleSetup(shape=shape)
    shape = base.shape
    fov = shape[1] * base.pixel_size_m
    phantom0 = default_phantom(fov, np.random.default_rng(seed + 1), height_m=shape[0] * base.pixel_size_m)
    kmax = max(k for _, _, k, _ in methods)
    scenes: dict[tuple, Scene] = {}

    def scene_for(setup, phantom, lateral, factor, absorption, dark=0.0) -> Scene:
        # the dose, coherence and ablation points share the base scene: simulate it once
        key = (repr(setup), phantom, lateral, factor, absorption, dark)
        if key not in scenes:
            scenes[key] = Scene(setup, phantom, factor, kmax, seed, absorption, dark)
        return scenes[key]

    base_max_phase = float(np.abs(scene_for(base, phantom0, 1.0, 1.0, 1.0).phase).max())
    rows = []
    for axis, values in axes.items():
        for value in values:
            setup, lateral, target, absorption, photons, pwf_over, dark = _point_setups(axis, value, base)
            phantom = scaled_phantom(phantom0, lateral) if lateral != 1.0 else phantom0
            if axis == "bead_radius_px":
                phantom = replace(phantom0, spheres=(single_bead(phantom0, float(value) * base.pixel_size_m),))
            # the gradient axis keeps the base's largest phase; thickness sets it
            factor = 1.0 / lateral if target is None else target * np.pi / base_max_phase
            runs = point_methods(axis, methods)
            scene = scene_for(setup, phantom, lateral, factor, absorption, dark)
            wl = optics.wavelength_m(setup.energy_eV)
            l2 = setup.diffuser_detector_distance_m
            point = {
                "max_phase_pi": float(np.abs(scene.phase).max() / np.pi),
                "displacement_over_grain": displacement_px(scene.phase, wl, l2, setup.pixel_size_m)
                / speckle_grain_px(scene.clean_references[0]),
            }
            for label, method, k, opts in runs:
                s, r = scene.images(photons, k, seed=seed + 7)
                kw = pwf_options(opts, pwf_over, setup) if method == "pwf" else dict(opts)
                t0 = time.perf_counter()
                res = retrieve_projection(
                    s[0] if k == 1 else s,
                    r[0] if k == 1 else r,
                    method=method,
                    energy_eV=setup.energy_eV,
                    pixel_size_m=setup.pixel_size_m,
                    sample_diffuser_distance_m=setup.sample_diffuser_distance_m,
                    diffuser_detector_distance_m=l2,
                    background_mask=scene.background,
                    **kw,
                )
                wall = time.perf_counter() - t0
                err = errors(
                    res.phase,
                    res.attenuation if method != "gf" else None,
                    scene.phase,
                    scene.attenuation,
                    scene.background,
                    scene.bead,
                )
                row = {
                    "axis": axis,
                    "value": value,
                    "method": label,
                    "K": k,
                    **point,
                    "photons": photons,
                    **err,
                    "holds": bool(err["phase_error"] < PHASE_ERROR_THRESHOLD),
                    "iterations": res.iterations,
                    "wall_s": wall,
                    **sensitivity_columns(res.parameters),
                }
                rows.append(row)
                if progress:
                    print(
                        f"{axis:>16} {str(value):>18}  {label:<14} phase err {row['phase_error']:7.3f}  "
                        f"att err {row['attenuation_error']:7.3f}  gain {row['phase_gain']:6.2f}  "
                        f"bead {100 * row['bead_contrast_error']:+6.1f} %  "
                        f"{wall:6.1f} s",
                        flush=True,
                    )
    return rows


def holds_summary(rows: list[dict]) -> dict[tuple[str, str], str]:
    """Per (axis, method): the axis values where the method holds, in words."""
    out = {}
    for axis in dict.fromkeys(r["axis"] for r in rows):
        for method in dict.fromkeys(r["method"] for r in rows if r["axis"] == axis):
            pts = [r for r in rows if r["axis"] == axis and r["method"] == method]
            held = [_fmt(r["value"]) for r in pts if r["holds"]]
            if len(held) == len(pts):
                out[axis, method] = "holds everywhere"
            elif not held:
                out[axis, method] = "fails everywhere"
            else:
                out[axis, method] = "holds at " + ", ".join(held)
    return out


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if isinstance(v, float) and (abs(v) >= 1e3 or (v != 0 and abs(v) < 1e-2)):
        return f"{v:.0e}"
    return f"{v:g}"


UNITS = {
    "dose": "photons/px",
    "max_phase_pi": "pi",
    "absorption": "x base beta",
    "gradient": "x base gradient",
    "l2_mm": "mm",
    "coherence_error": "relative",
    "ablation": "",
    "bead_radius_px": "px",
    "dark_field_px": "px of speckle blur behind the thickest part",
    "pixel_um": "um detector pixel, coherence lengths 3.47 / 4.31 um",
}


def write_stability_map(rows: list[dict], out_dir: str | Path, device: str) -> None:
    """``stability_map.csv``, ``.md`` (tables and the holds summary) and ``.png``."""
    from benchmarks.reporting import write_rows_csv

    out = write_rows_csv(out_dir, "stability_map.csv", rows)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = [
        f"# Stability map: where each method fails ({device})",
        "",
        "`pwf-dask bench stability`: one projection of the paper's optics (10 keV, 0.65 um pixels, L1 = 3 mm,",
        "L2 = 20 mm, four layers of P3000 SiC sandpaper, cellulose rod with glass beads, 1e4 ph/px) varied along",
        "one axis at a time (axes re-measured alone with `--axes` keep the others' rows). PWF is given the",
        "point's true coherence lengths, except in the column `PWF K=1 calibrated` and on the `calibration` axis,",
        "where it calibrates them from the point's own reference as a user's run does (the template fit, the",
        "default). Entry: phase RMSE inside the sample / RMS true phase (background zeroed on the true",
        "sample-free pixels for every method).",
        f"A method holds while this is below {PHASE_ERROR_THRESHOLD}; **bold** = fails.",
        "In brackets: the largest bead's local phase contrast error (+ = overshoot), which the sample-wide RMSE",
        "hides; the tomogram's bead delta inherits it.",
        "Columns `phase` and `d/grain`: the largest true phase (pi) and the 99th-percentile speckle displacement",
        "over the speckle grain (autocorrelation FWHM) at that point.",
        "",
    ]
    summary = holds_summary(rows)
    for axis in dict.fromkeys(r["axis"] for r in rows):
        pts = [r for r in rows if r["axis"] == axis]
        ms = [m for m in methods if any(r["method"] == m for r in pts)]
        lines += [
            f"## {axis} ({UNITS.get(axis, '')})".replace(" ()", ""),
            "",
            "| value | phase (pi) | d/grain | " + " | ".join(ms) + " |",
            "|---|---:|---:|" + "---:|" * len(ms),
        ]
        for value in dict.fromkeys(r["value"] for r in pts):
            at = {r["method"]: r for r in pts if r["value"] == value}
            any_row = next(iter(at.values()))
            cells = []
            for m in ms:
                r = at.get(m)
                if r is None:
                    cells.append("")
                    continue
                e = f"{r['phase_error']:.3f}" if np.isfinite(r["phase_error"]) else "diverged"
                b = r.get("bead_contrast_error", float("nan"))
                bead = f" ({100 * b:+.0f} %)" if np.isfinite(b) else ""
                cells.append((e if r["holds"] else f"**{e}**") + bead)
            lines.append(
                f"| {_fmt(value)} | {any_row['max_phase_pi']:.1f} | {any_row['displacement_over_grain']:.2f} | "
                + " | ".join(cells)
                + " |"
            )
        lines += ["", *[f"- {m}: {summary[axis, m]}" for m in ms], ""]
    (out / "stability_map.md").write_text("\n".join(lines) + "\n")
    stability_plot(out / "stability_map.png", rows)


def stability_plot(path, rows: list[dict]) -> None:
    from pwf_dask.plots import pyplot, save_figure

    plt = pyplot()

    axes_names = list(dict.fromkeys(r["axis"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    colors = {m: f"C{i}" for i, m in enumerate(methods)}
    ncol = 3
    nrow = (len(axes_names) + ncol - 1) // ncol
    fig, axs = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.3 * nrow), squeeze=False)
    for ax, axis in zip(axs.flat, axes_names):
        pts = [r for r in rows if r["axis"] == axis]
        values = list(dict.fromkeys(r["value"] for r in pts))
        categorical = any(isinstance(v, str) for v in values)
        for m in methods:
            mr = [r for r in pts if r["method"] == m]
            if not mr:
                continue
            xs = [values.index(r["value"]) if categorical else r["value"] for r in mr]
            if axis == "bead_radius_px":  # the sample-wide RMSE hides a small bead
                ys = [float(np.clip(r["bead_contrast_error"], -2.0, 2.0)) for r in mr]
            else:
                ys = [min(r["phase_error"], 10.0) for r in mr]
            ax.plot(xs, ys, "o-", color=colors[m], label=m, ms=4)
        if axis == "bead_radius_px":
            for level in (-0.15, 0.0, 0.15):
                ax.axhline(level, color="k", ls="--" if level else ":", lw=0.8)
        else:
            ax.axhline(PHASE_ERROR_THRESHOLD, color="k", ls="--", lw=0.8)
            ax.set_yscale("log")
        if categorical:
            ax.set_xticks(range(len(values)))
            ax.set_xticklabels(values, rotation=20, fontsize=7)
        else:
            if axis in ("dose", "max_phase_pi", "gradient", "l2_mm", "bead_radius_px"):
                ax.set_xscale("log")
            elif axis == "absorption":
                ax.set_xscale("symlog", linthresh=0.1)
                ax.set_xlim(-0.02, max(values) * 1.3)
            ax.minorticks_off()
            ax.set_xticks(values)
            ax.set_xticklabels([_fmt(v) for v in values], fontsize=7)
        ax.set_title(f"{axis} ({UNITS.get(axis, '')})".replace(" ()", ""), fontsize=9)
        ax.set_ylabel(
            "bead phase contrast error" if axis == "bead_radius_px" else "phase error (rel. RMSE)", fontsize=8
        )
    for ax in list(axs.flat)[len(axes_names) :]:
        ax.axis("off")
    axs.flat[0].legend(fontsize=7)
    save_figure(fig, path)


def read_stability_rows(path: str | Path) -> list[dict]:
    """The rows of a written ``stability_map.csv``, with numbers, booleans and axis values
    (numbers or labels) as :func:`stability_map` returned them."""
    path = Path(path)
    rows = read_rows_csv(path.parent, path.name)
    for r in rows:
        r["value"] = float(r["value"]) if isinstance(r["value"], int) else r["value"]
        r["method"], r["axis"] = str(r["method"]), str(r["axis"])
    return rows


def run_stability_benchmark(out_dir: str | Path, quick: bool = False, axes: list[str] | None = None) -> list[dict]:
    """``pwf-dask bench stability``: the full map (``quick``: a 96 x 96 frame, two values per axis).

    ``axes``: re-measure only these axes and keep every other axis's rows of the map already
    in ``out_dir`` (in :data:`AXES` order), e.g. after a change that only they show.
    """
    from benchmarks.reporting import device_name

    unknown = sorted(set(axes or ()) - set(AXES))
    if unknown:
        raise ValueError(f"unknown stability axis {unknown[0]!r}: choose from {', '.join(AXES)}")
    chosen = {a: v for a, v in AXES.items() if axes is None or a in axes}
    kept = Path(out_dir) / "stability_map.csv"
    if axes is not None and not kept.exists():
        raise ValueError(f"--axes re-measures part of a map, but {kept} does not exist: run the full map")
    if quick:
        rows = stability_map(shape=(96, 96), axes={a: [v[0], v[-1]] for a, v in chosen.items()})
    else:
        rows = stability_map(axes=chosen)
    if axes is not None:
        # rows written before a column existed get it empty, so that one CSV holds them all
        blank = sensitivity_columns({})
        old = [{**blank, **r} for r in read_stability_rows(kept) if r["axis"] not in chosen]
        order = list(AXES)
        rows = sorted(old + rows, key=lambda r: order.index(r["axis"]) if r["axis"] in order else len(order))
    write_stability_map(rows, out_dir, device_name(np))
    return rows
