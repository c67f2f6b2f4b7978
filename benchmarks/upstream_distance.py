"""An upstream diffuser whose distance is not known: what the data tell of it, and what each guess costs.

Where the diffuser sits upstream of the sample the scan records L1 = 0 (CONTRACT: no field for
the upstream distance), and the single-material fit of the reference is made over L2 alone.
``retrieve_projection(..., diffuser_upstream_m=d)`` fits it over d + L2 and lights the sample
with its field propagated over d (:func:`pwf_dask.calibration.diffuser.diffuser_transmission`).
A user who does not know d would want it read from the data. Two candidates:

- the reference alone: the single-material fit's residual at each assumed distance
  (:func:`pwf_dask.calibration.diffuser.single_material_diffuser`, its default iterations);
- the pair: PWF's data residual at each assumed distance.

Per scene (the paper's optics, 10 keV, 0.65 um pixels, L2 = 20 mm, 256^2, the default bead
phantom, 1e4 ph/px; L1 = 0 and the diffuser ``true`` mm upstream, 0 = at the sample plane) and
assumed distance: both residuals, the phase gain and the relative phase error with every other
default (calibrated coherence, ``"auto"``'s model); and the paper's zero-phase estimate once (it
does not depend on the distance: back-propagating over d + L2 and forward over d is
back-propagating over L2).

    python -m benchmarks.upstream_distance [--out benchmarks/results]

Writes ``upstream_distance.md`` and ``.csv`` (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.reporting import command_line, device_name, rows_of
from benchmarks.stability import errors
from pwf_dask.calibration.diffuser import single_material_diffuser
from pwf_dask.physics import optics
from pwf_dask.retrieval import chosen_diffuser_model, retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

#: the diffuser's true distance upstream of the sample (m), L1 = 0 throughout
TRUE_UPSTREAM_M = (0.0, 5e-3, 20e-3, 50e-3, 100e-3)
#: the distances a user might assume (m): 0 is what a scan's L1 = 0 gives
ASSUMED_UPSTREAM_M = (0.0, 10e-3, 25e-3, 50e-3, 100e-3)
GRITS = ("P3000", "P1200")
SEEDS = (1, 2)


def upstream_setup(grit: str, upstream_m: float) -> SpeckleSetup:
    return SpeckleSetup(
        shape=(256, 256), diffuser_grit=grit, sample_diffuser_distance_m=0.0, diffuser_upstream_m=upstream_m
    )


def reference_fit_residual(sim, setup: SpeckleSetup, assumed_m: float) -> float:
    """rms misfit (of the mean) of the single-material fit of the reference over ``assumed_m`` + L2,
    at the true blurred coherence lengths (the calibration is not what is asked here)."""
    x, y = setup.blurred_coherence_lengths_m()
    kappa = chosen_diffuser_model("single-material", setup.diffuser_material, None, setup.energy_eV)[1]
    return single_material_diffuser(
        sim.reference,
        beta_over_delta=kappa,
        pixel_size_m=setup.pixel_size_m,
        wavelength=optics.wavelength_m(setup.energy_eV),
        diffuser_detector_distance_m=setup.diffuser_detector_distance_m + assumed_m,
        coherence_length_x_m=x,
        coherence_length_y_m=y,
        pad=16,
    ).residual_rmse


def run(sim, **options) -> dict:
    """One retrieval with every default but ``options``, measured against the truth."""
    t0 = time.perf_counter()
    r = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), **options)
    seconds = time.perf_counter() - t0
    e = errors(np.asarray(r.phase), np.asarray(r.attenuation), sim.phase, sim.attenuation, np.abs(sim.phase) < 1e-6)
    return {
        "residual_pct": r.residual_rmse,
        "phase_gain": e["phase_gain"],
        "phase_error": e["phase_error"],
        "diffuser_model": r.parameters["diffuser_model"],
        "iterations": r.iterations,
        "seconds": seconds,
    }


def scene_rows(grit: str, true_m: float, seed: int) -> list[dict]:
    setup = upstream_setup(grit, true_m)
    sim = simulate_projection(setup, seed=seed)
    scene = {"grit": grit, "true_mm": true_m * 1e3, "seed": seed}
    rows = []
    for assumed in ASSUMED_UPSTREAM_M:
        row = {**scene, "assumed_mm": assumed * 1e3, "model": "default"}
        row["reference_fit_residual"] = reference_fit_residual(sim, setup, assumed)
        rows.append({**row, **run(sim, diffuser_upstream_m=assumed)})
        print(rows[-1], flush=True)
    rows.append({**scene, "assumed_mm": float("nan"), "model": "zero-phase", "reference_fit_residual": float("nan")})
    rows[-1].update(run(sim, diffuser_model="zero-phase"))
    print(rows[-1], flush=True)
    return rows


def _argmin(rows: list[dict], key: str) -> float:
    return min(rows, key=lambda r: r[key])["assumed_mm"]


def summary_lines(rows: list[dict]) -> list[str]:
    """Per grit and true distance, over the seeds: the mean phase error at each assumed distance
    and with zero phase, and where each residual and the error put the distance."""
    assumed = list(dict.fromkeys(r["assumed_mm"] for r in rows if r["model"] == "default"))
    head = " | ".join(f"{a:.0f} mm" for a in assumed)
    lines = [
        "| grit | true (mm) | phase error, assumed: " + head + " | zero phase "
        "| lowest: reference fit's residual | PWF residual | phase error |",
        "|---|---:|" + "---:|" * (len(assumed) + 1) + "---|---|---|",
    ]
    for grit in dict.fromkeys(r["grit"] for r in rows):
        for true in dict.fromkeys(r["true_mm"] for r in rows if r["grit"] == grit):
            here = [r for r in rows if r["grit"] == grit and r["true_mm"] == true]
            seeds = list(dict.fromkeys(r["seed"] for r in here))
            cells = [grit, f"{true:.0f}"]
            for a in assumed:
                cells.append(f"{np.mean([r['phase_error'] for r in here if r['assumed_mm'] == a]):.3f}")
            cells.append(f"{np.mean([r['phase_error'] for r in here if r['model'] == 'zero-phase']):.3f}")
            for key in ("reference_fit_residual", "residual_pct", "phase_error"):
                picks = [_argmin([r for r in here if r["seed"] == s and r["model"] == "default"], key) for s in seeds]
                cells.append(" / ".join(f"{p:.0f}" for p in picks))
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def write_markdown(rows: list[dict], path: str, command: str) -> None:
    lines = [
        "# An upstream diffuser whose distance is not known",
        "",
        f"`{command}` on {device_name(np)}: the paper's optics (10 keV, 0.65 um pixels, L2 = 20 mm,",
        "coherence 3.47 / 4.31 um), L1 = 0 with the diffuser `true` mm upstream of the sample (0: at the",
        "sample plane), 256^2, the default bead phantom, 1e4 ph/px, seeds "
        + ", ".join(str(s) for s in dict.fromkeys(r["seed"] for r in rows))
        + ". PWF with every default",
        '(calibrated coherence, `diffuser_model="auto"`) and `diffuser_upstream_m` = the assumed distance;',
        'zero phase: `diffuser_model="zero-phase"`, which does not depend on it. Phase error: rms over the',
        "sample relative to the true phase's rms (`benchmarks.stability.errors`), mean over the seeds. Lowest:",
        "the assumed distance (mm) at which each quantity is least, per seed: the reference's single-material",
        "fit residual (the fit's default 25 iterations, true lengths), PWF's data residual, and the phase error",
        "itself (what a perfect selector would pick).",
        "",
        *summary_lines(rows),
        "",
        "## Every run",
        "",
        "| grit | true (mm) | seed | model | assumed (mm) | reference fit residual | PWF residual % "
        "| phase gain | phase error | iterations | s |",
        "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        zp = r["model"] == "zero-phase"
        assumed = "" if zp else f"{r['assumed_mm']:.0f}"
        fit = "" if zp else f"{r['reference_fit_residual']:.4f}"
        lines.append(
            f"| {r['grit']} | {r['true_mm']:.0f} | {r['seed']} | {r['diffuser_model']} | {assumed} | {fit} "
            f"| {r['residual_pct']:.3f} | {r['phase_gain']:.3f} | {r['phase_error']:.3f} | {r['iterations']} "
            f"| {r['seconds']:.1f} |"
        )
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results", help="folder for upstream_distance.md and .csv")
    ap.add_argument("--report-only", action="store_true", help="re-write the report from the CSV")
    a = ap.parse_args(argv)

    def compute() -> list[dict]:
        return [r for grit in GRITS for true in TRUE_UPSTREAM_M for seed in SEEDS for r in scene_rows(grit, true, seed)]

    rows = rows_of(a.out, "upstream_distance.csv", a.report_only, compute)
    write_markdown(rows, f"{a.out}/upstream_distance.md", command_line("benchmarks.upstream_distance", argv))


if __name__ == "__main__":
    main()
