"""PWF and single-image UMPA under the detector's own blur, which the paper's model does not have.

Every real frame passes a scintillator and a microscope before the pixels: the paper's 50 um
LuAG:Ce screen behind a 10x NA 0.25 objective blurs the intensity by about 0.75 um FWHM at
10 keV (Koch et al. 1998, R = sqrt((0.18/NA)^2 + (0.075 dz NA)^2) um with the screen's ~12 um
absorption depth as dz), and scattered scintillation light spreads a fraction of it far wider.
The simulator's ``SpeckleSetup(detector_blur_fwhm_m, detector_halo_fraction,
detector_halo_radius_m)`` puts that on the intensity before pixel integration
(:func:`pwf_dask.physics.optics.detector_transfer_function`). A Gaussian core is one blur with
the IOTF, Eq. (IOTF): its lengths are sqrt(x^2 + 4 pi sigma^2)
(:func:`pwf_dask.physics.optics.blurred_coherence_length_m`), which a calibration from the
reference should read. A halo is outside PWF's model.

Per scene (the paper's geometry, 256^2, the default bead phantom) and detector:

- PWF with every default, lengths calibrated from the reference (a user's run): the lengths
  over the blurred true ones, the phase gain (the accuracy tests' fitted slope), the relative
  phase and attenuation errors, the largest bead's phase contrast error;
- PWF given the blurred true lengths (what the calibration costs);
- where the detector has a halo, PWF told it (``detector_halo_fraction``, ``detector_halo_radius_m``:
  the model's own filter beside the IOTF), lengths calibrated;
- UMPA with the one image (K = 1, the single-shot baseline).

    python -m benchmarks.detector_psf [--out benchmarks/results]

Writes ``detector_psf.md`` and ``.csv`` (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.frame_size import fitted_phase_gain
from benchmarks.reporting import command_line, device_name, rows_of
from benchmarks.stability import bead_regions, errors
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, simulate_projection

_BASE = SpeckleSetup(shape=(256, 256))
#: (label, setup, seed): P3000 (the paper's diffuser) on three draws, finer and coarser grains, a low dose
SCENES = (
    ("P3000, seed 1", _BASE, 1),
    ("P3000, seed 2", _BASE, 2),
    ("P3000, seed 3", _BASE, 3),
    ("1.2 um grains, seed 1", replace(_BASE, diffuser_radius_median_m=1.2e-6), 1),
    ("4.5 um grains, seed 1", replace(_BASE, diffuser_radius_median_m=4.5e-6), 1),
    ("P3000 1e3 ph/px, seed 1", replace(_BASE, photons=1e3), 1),
)
#: (label, Gaussian core FWHM m, halo fraction, halo 1/e radius m)
DETECTORS = (
    ("none", 0.0, 0.0, 0.0),
    ("0.75 um", 0.75e-6, 0.0, 0.0),
    ("1.5 um", 1.5e-6, 0.0, 0.0),
    ("3 um", 3.0e-6, 0.0, 0.0),
    ("0.75 um + 10 % at 3 um", 0.75e-6, 0.1, 3e-6),
    ("0.75 um + 30 % at 3 um", 0.75e-6, 0.3, 3e-6),
    ("0.75 um + 10 % at 10 um", 0.75e-6, 0.1, 10e-6),
    ("0.75 um + 30 % at 10 um", 0.75e-6, 0.3, 10e-6),
)
METHODS = ("pwf", "pwf_blurred_true_lengths", "pwf_told_halo", "umpa")


def detector_setup(setup: SpeckleSetup, fwhm_m: float, halo_fraction: float, halo_radius_m: float) -> SpeckleSetup:
    return replace(
        setup, detector_blur_fwhm_m=fwhm_m, detector_halo_fraction=halo_fraction, detector_halo_radius_m=halo_radius_m
    )


def _options(method: str, setup: SpeckleSetup) -> dict:
    if method == "umpa":
        return {"method": "umpa"}
    if method == "pwf_blurred_true_lengths":
        x, y = setup.blurred_coherence_lengths_m()
        return {"coherence_length_x_m": x, "coherence_length_y_m": y}
    if method == "pwf_told_halo":
        return {
            "detector_halo_fraction": setup.detector_halo_fraction,
            "detector_halo_radius_m": setup.detector_halo_radius_m,
        }
    return {}


def run(sim, setup: SpeckleSetup, bead, method: str) -> dict:
    """One retrieval of ``sim`` by ``method``, measured against the truth."""
    t0 = time.perf_counter()
    r = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), **_options(method, setup))
    seconds = time.perf_counter() - t0
    phase = np.asarray(r.phase)
    attenuation = None if r.attenuation is None else np.asarray(r.attenuation)
    e = errors(phase, attenuation, sim.phase, sim.attenuation, np.abs(sim.phase) < 1e-6, bead)
    x, y = setup.blurred_coherence_lengths_m()
    pwf = method != "umpa"
    return {
        "method": method,
        "length_x_over_blurred": float(r.coherence_length_x_m / x) if pwf else float("nan"),
        "length_y_over_blurred": float(r.coherence_length_y_m / y) if pwf else float("nan"),
        "phase_gain": fitted_phase_gain(phase, sim.phase),
        "phase_error": e["phase_error"],
        "attenuation_error": e["attenuation_error"],
        "bead_contrast_error": e["bead_contrast_error"],
        "iterations": r.iterations,
        "diffuser_model": r.parameters.get("diffuser_model", ""),
        "seconds": seconds,
    }


def scene_rows(label: str, base: SpeckleSetup, seed: int, detectors=DETECTORS, methods=METHODS) -> list[dict]:
    """Every detector and method on one scene: the same diffuser draw, phantom and noise seed."""
    rows = []
    for name, fwhm, fraction, radius in detectors:
        setup = detector_setup(base, fwhm, fraction, radius)
        sim = simulate_projection(setup, seed=seed)
        bead = bead_regions(SpeckleSimulator(setup, seed=seed), sim.phantom)
        x, y = setup.blurred_coherence_lengths_m()
        scene = {
            "scene": label,
            "detector": name,
            "blur_fwhm_um": fwhm * 1e6,
            "halo_fraction": fraction,
            "halo_radius_um": radius * 1e6,
            "blurred_length_x_um": x * 1e6,
            "blurred_length_y_um": y * 1e6,
            "visibility": float(sim.reference.std() / sim.reference.mean()),
        }
        for method in methods:
            if method == "pwf_told_halo" and not fraction:
                continue  # no halo to tell: the plain run
            rows.append({**scene, **run(sim, setup, bead, method)})
            print(rows[-1], flush=True)
    return rows


def _fmt_pct(v: float) -> str:
    return "" if not np.isfinite(v) else f"{v:+.1%}"


def _range(values: list[float]) -> str:
    return f"{min(values):.3f}-{max(values):.3f}" if values else ""


def summary_lines(rows: list[dict]) -> list[str]:
    """Per detector over the scenes: each method's range of phase gain and of phase error, and
    PWF's calibrated lengths over the blurred true ones."""
    lines = [
        "## Per detector, over the scenes (ranges)",
        "",
        "| detector | lengths / blurred | PWF gain | PWF error | PWF told the halo: gain | error "
        "| UMPA K = 1: gain | error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for det in dict.fromkeys(r["detector"] for r in rows):
        by = {m: [r for r in rows if r["detector"] == det and r["method"] == m] for m in METHODS}
        lengths = [r[k] for r in by["pwf"] for k in ("length_x_over_blurred", "length_y_over_blurred")]
        cells = [det, _range(lengths)]
        for m in ("pwf", "pwf_told_halo", "umpa"):
            cells += [_range([r["phase_gain"] for r in by[m]]), _range([r["phase_error"] for r in by[m]])]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_markdown(rows: list[dict], path: str, command: str) -> None:
    lines = [
        "# PWF and single-image UMPA under the detector's own blur",
        "",
        f"`{command}` on {device_name(np)}: the paper's geometry (10 keV, 0.65 um pixels, L1 = 3 mm,",
        "L2 = 20 mm, coherence 3.47 / 4.31 um), 256^2, 1e4 ph/px unless named, the default bead phantom. The",
        "detector's PSF (a Gaussian core of the FWHM named, convolved with a halo holding the fraction named of",
        "the light over an exponential of the 1/e radius named) blurs the intensity before pixel integration.",
        "Lengths: calibrated over the blurred true ones, sqrt(x^2 + 4 pi sigma^2) (x / y). Gain: the slope of",
        "recovered on true phase where the true phase is below -0.5 rad; errors: rms over the sample, relative;",
        "bead: the largest bead's phase contrast error. PWF: every default (calibrated); PWF, true: given",
        "the blurred true lengths; PWF, told the halo: `detector_halo_fraction` and `detector_halo_radius_m`",
        "given, lengths calibrated; UMPA K = 1: the one image.",
        "",
        *summary_lines(rows),
        "",
        "## Every scene",
        "",
        "| scene | detector | visibility | lengths (PWF) | PWF gain / error / bead / att. error "
        "| PWF, true lengths: gain / error | PWF, told the halo: gain / error | UMPA K = 1: gain / error |",
        "|---|---|---:|---|---|---|---|---|",
    ]
    keyed = {(r["scene"], r["detector"], r["method"]): r for r in rows}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for det in dict.fromkeys(r["detector"] for r in rows if r["scene"] == scene):
            p = keyed.get((scene, det, "pwf"))
            t = keyed.get((scene, det, "pwf_blurred_true_lengths"))
            h = keyed.get((scene, det, "pwf_told_halo"))
            u = keyed.get((scene, det, "umpa"))
            cells = [scene, det, f"{(p or t or u)['visibility']:.3f}"]
            cells.append(f"{p['length_x_over_blurred']:.3f} / {p['length_y_over_blurred']:.3f}" if p else "")
            cells.append(
                f"{p['phase_gain']:.3f} / {p['phase_error']:.3f} / {_fmt_pct(p['bead_contrast_error'])} / "
                f"{p['attenuation_error']:.3f}"
                if p
                else ""
            )
            cells.append(f"{t['phase_gain']:.3f} / {t['phase_error']:.3f}" if t else "")
            cells.append(f"{h['phase_gain']:.3f} / {h['phase_error']:.3f}" if h else "")
            cells.append(f"{u['phase_gain']:.3f} / {u['phase_error']:.3f}" if u else "")
            lines.append("| " + " | ".join(cells) + " |")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results", help="folder for detector_psf.md and .csv")
    ap.add_argument("--report-only", action="store_true", help="re-write the report from the CSV")
    a = ap.parse_args(argv)
    rows = rows_of(
        a.out, "detector_psf.csv", a.report_only, lambda: [r for scene in SCENES for r in scene_rows(*scene)]
    )
    write_markdown(rows, f"{a.out}/detector_psf.md", command_line("benchmarks.detector_psf", argv))


if __name__ == "__main__":
    main()
