"""The Siegert calibration against dose, and what PWF makes of it (README, Numerical choices, Calibration).

A 256 x 256 projection (the paper's geometry, sub-pixel sandpaper, the default cellulose rod
with glass beads) at 1e2 - 1e4 photons/pixel, seeds 1-3. For each: the coherence lengths
fitted to the reference (``calibration.coherence_lengths``) over the true source lengths
(the fit includes the pixel blur, so a few per cent long is its design), and PWF's relative
phase error inside the sample (``retrieve_projection`` defaults, background detected) with
the true lengths given and with the lengths calibrated from the reference.

    python workflows/calibration_dose.py [--out workflows/results]

Writes ``calibration_dose.md`` and ``.csv`` (about 5 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pwf_dask.bench import device_name, write_rows_csv
from pwf_dask.calibration import coherence_lengths
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

DOSES = [1e2, 3e2, 1e3, 1e4]
SEEDS = [1, 2, 3]
SHAPE = (256, 256)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="workflows/results")
    args = ap.parse_args(argv)
    rows = []
    for photons in DOSES:
        for seed in SEEDS:
            setup = SpeckleSetup(shape=SHAPE, photons=photons)
            sim = simulate_projection(setup, seed=seed)
            cx, cy = coherence_lengths(sim.reference, setup.pixel_size_m)
            inside = sim.phase < -0.5
            row = {
                "photons": photons,
                "seed": seed,
                "fitted_over_true_x": cx / setup.coherence_length_x_m,
                "fitted_over_true_y": cy / setup.coherence_length_y_m,
            }
            given = {
                "coherence_length_x_m": setup.coherence_length_x_m,
                "coherence_length_y_m": setup.coherence_length_y_m,
            }
            for name, lengths in (("true", given), ("calibrated", {})):
                t0 = time.perf_counter()
                res = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), **lengths)
                err = float(np.sqrt(np.mean((res.phase - sim.phase)[inside] ** 2) / np.mean(sim.phase[inside] ** 2)))
                row[f"phase_error_{name}"] = err
                row[f"iterations_{name}"] = res.iterations
                row[f"wall_s_{name}"] = time.perf_counter() - t0
            rows.append(row)
            print(
                f"{photons:g} ph/px seed {seed}: fitted/true {row['fitted_over_true_x']:.3f} / "
                f"{row['fitted_over_true_y']:.3f}; phase error true {row['phase_error_true']:.3f}, "
                f"calibrated {row['phase_error_calibrated']:.3f}",
                flush=True,
            )
    out = write_rows_csv(args.out, "calibration_dose.csv", rows)
    lines = [
        f"# Coherence-length calibration against dose ({device_name(np)})",
        "",
        "`python workflows/calibration_dose.py`: 256 x 256, paper geometry, sub-pixel sandpaper, seeds 1-3.",
        "Fitted / true coherence lengths (x, y; the fit includes the pixel blur) and PWF's relative phase",
        "error inside the sample (defaults, background detected) with the true and the calibrated lengths.",
        "Per seed, separated by `/`.",
        "",
        "| ph/px | fitted / true x | fitted / true y | phase error, true lengths | phase error, calibrated |",
        "|---|---|---|---|---|",
    ]

    def cell(sel, key, fmt="{:.3f}"):
        return " / ".join(fmt.format(r[key]) for r in sel)

    for photons in DOSES:
        sel = [r for r in rows if r["photons"] == photons]
        lines.append(
            f"| {photons:g} | {cell(sel, 'fitted_over_true_x')} | {cell(sel, 'fitted_over_true_y')} "
            f"| {cell(sel, 'phase_error_true')} | {cell(sel, 'phase_error_calibrated')} |"
        )
    (out / "calibration_dose.md").write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
