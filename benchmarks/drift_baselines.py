"""The speckle-tracking baselines under diffuser drift, uncorrected and corrected (docs/validation.md, Diffuser drift).

A 256 x 256 projection (the paper's geometry, four layers of P3000 SiC sandpaper, 1e4 photons/pixel, the
default cellulose rod with glass beads): the sample frames are taken through the diffuser
moved by a drift since the references. UMPA with one image (seeds 1-6) and LCS with 12
positions (seeds 1-3; every position drifted alike) run through ``retrieve_projection`` with
``diffuser_drift="off"`` and ``"auto"`` (the default). Reported: relative phase error inside
the sample (background detected, as a user gets it), per seed and the mean.

    python -m benchmarks.drift_baselines [--out benchmarks/results]

Writes ``drift_baselines.md`` and ``.csv`` (under a minute on 2 cores).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, default_phantom

DRIFTS_PX = [(0.0, 0.0), (2.0, -3.0), (-0.5, 1.5)]
#: (method, K diffuser positions, seeds)
RUNS = [("umpa", 1, range(1, 7)), ("lcs", 12, range(1, 4))]
SHAPE = (256, 256)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    setup = SpeckleSetup(shape=SHAPE)
    geometry = setup.geometry()
    fov = SHAPE[0] * setup.pixel_size_m
    rows = []
    for method, k, seeds in RUNS:
        for seed in seeds:
            sim = SpeckleSimulator(setup, seed=seed)
            field, psi = sim.sample_field(default_phantom(fov, np.random.default_rng(2), height_m=fov))
            truth = sim._bin(psi.imag)
            inside = truth < -0.5
            shifts = [(7 * i, 13 * i) for i in range(k)]
            references = np.array([sim.reference(sh) for sh in shifts])
            for dy, dx in DRIFTS_PX:
                samples = np.array([sim.noisy(sim.intensity(field, sim.diffuser((a + dy, b + dx)))) for a, b in shifts])
                s, r = (samples[0], references[0]) if k == 1 else (samples, references)
                for drift in ("off", "auto") if (dy, dx) != (0.0, 0.0) else ("auto",):
                    res = retrieve_projection(s, r, method=method, **geometry, diffuser_drift=drift)
                    err = float(np.sqrt(np.mean((res.phase - truth)[inside] ** 2) / np.mean(truth[inside] ** 2)))
                    row = {
                        "method": method,
                        "K": k,
                        "seed": seed,
                        "drift_y_px": dy,
                        "drift_x_px": dx,
                        "diffuser_drift": drift,
                        "measured_y_px": res.parameters["diffuser_drift_px"][0],
                        "measured_x_px": res.parameters["diffuser_drift_px"][1],
                        "phase_error": err,
                    }
                    rows.append(row)
                    print(f"{method} K={k} seed {seed} drift ({dy}, {dx}) {drift:4s} phase error {err:.3f}", flush=True)
    out = write_rows_csv(args.out, "drift_baselines.csv", rows)
    lines = [
        f"# Speckle-tracking baselines under diffuser drift ({device_name(np)})",
        "",
        "`python -m benchmarks.drift_baselines`: 256 x 256, paper geometry, four layers of P3000 SiC sandpaper, "
        "1e4 ph/px;",
        "the sample frames taken through the diffuser moved by the drift. Relative phase error inside the",
        "sample (background detected); mean over seeds, range in brackets. `still` = no drift.",
        "",
        "| method | drift (dy, dx) px | off | auto (default) |",
        "|---|---|---|---|",
    ]
    for method, k, _ in RUNS:
        for dy, dx in DRIFTS_PX:
            cells = []
            for drift in ("off", "auto"):
                e = [
                    r["phase_error"]
                    for r in rows
                    if (r["method"], r["drift_y_px"], r["drift_x_px"], r["diffuser_drift"]) == (method, dy, dx, drift)
                ]
                cells.append(f"{np.mean(e):.3f} ({min(e):.3f}-{max(e):.3f})" if e else "-")
            label = "still" if (dy, dx) == (0.0, 0.0) else f"({dy:g}, {dx:g})"
            lines.append(f"| {method.upper()} K={k} | {label} | {cells[0]} | {cells[1]} |")
    Path(out, "drift_baselines.md").write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
