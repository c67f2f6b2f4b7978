"""Coherence calibration against dose, and what PWF makes of it (docs/methods.md, Coherence calibration).

A 256 x 256 projection (the paper's geometry and diffuser: four layers of P3000; the default
cellulose rod with glass beads) at 1e2 - 1e5 photons/pixel, seeds 1-3. For each: the
coherence lengths fitted to the reference by the template fit (the default) and by the
paper's Gaussian alone (``calibration.fit_coherence_lengths``), over the true source lengths,
and PWF's phase gain (slope of recovered on true phase inside the sample) and relative phase
error with the true lengths and with each calibration.

    python -m benchmarks.calibration_dose [--out benchmarks/results]

Writes ``calibration_dose.md`` and ``.csv`` (about 6 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.calibration import coherence, fit_coherence_lengths
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

DOSES = [1e2, 3e2, 1e3, 1e4, 1e5]
SEEDS = [1, 2, 3]
SHAPE = (256, 256)
CALIBRATIONS = ("true", "template", "gaussian")


def phase_scores(recovered: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    """(gain, relative RMS error) inside the sample, after removing the mean offset."""
    inside = true < -0.5
    r = recovered[inside] - recovered[inside].mean()
    t = true[inside] - true[inside].mean()
    gain = float(np.dot(r, t) / np.dot(t, t))
    err = float(np.sqrt(np.mean((recovered - true)[inside] ** 2) / np.mean(true[inside] ** 2)))
    return gain, err


def measure(photons: float, seed: int) -> dict:
    setup = SpeckleSetup(shape=SHAPE, photons=photons)
    sim = simulate_projection(setup, seed=seed)
    geometry = sim.geometry()
    row: dict = {"photons": photons, "seed": seed}
    lengths = {"true": (setup.coherence_length_x_m, setup.coherence_length_y_m)}
    for method in ("template", "gaussian"):
        t0 = time.perf_counter()
        fit = fit_coherence_lengths(
            sim.reference,
            setup.pixel_size_m,
            energy_eV=setup.energy_eV,
            diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
            method=method,
        )
        row[f"calibration_s_{method}"] = time.perf_counter() - t0
        row[f"{method}_over_true_x"] = fit.x_m / setup.coherence_length_x_m
        row[f"{method}_over_true_y"] = fit.y_m / setup.coherence_length_y_m
        lengths[method] = (fit.x_m, fit.y_m)
    for name in CALIBRATIONS:
        t0 = time.perf_counter()
        res = retrieve_projection(
            sim.sample,
            sim.reference,
            **geometry,
            coherence_length_x_m=lengths[name][0],
            coherence_length_y_m=lengths[name][1],
            # the Gaussian's lengths include the pixel's blur; the template's and the truth do not
            coherence_includes_pixel_blur=name == "gaussian",
        )
        row[f"wall_s_{name}"] = time.perf_counter() - t0
        row[f"phase_gain_{name}"], row[f"phase_error_{name}"] = phase_scores(res.phase, sim.phase)
    return row


def write_markdown(out, rows: list[dict]) -> None:
    lines = [
        f"# Coherence-length calibration against dose ({device_name(np)})",
        "",
        "`python -m benchmarks.calibration_dose`: 256 x 256, the paper's geometry and diffuser (four layers",
        "of P3000), seeds 1-3 separated by `/`. Fitted / true coherence lengths (x, y) by the template fit",
        "(default) and the Gaussian alone, and PWF's phase gain inside the sample (defaults, background",
        "detected) with the true lengths and with each calibration. Below "
        f"{coherence.LOW_DOSE_PHOTONS:g} photons a pixel",
        "(read from the reference's white floor) the template fit chooses its frequencies on the smoothed",
        "spectrum (docs/methods.md, Coherence calibration).",
        "",
        "| ph/px | template / true x, y | Gaussian / true x, y | gain, true | gain, template | gain, Gaussian |",
        "|---|---|---|---|---|---|",
    ]

    def cell(sel, key):
        return " / ".join(f"{r[key]:.3f}" for r in sel)

    for photons in DOSES:
        sel = [r for r in rows if r["photons"] == photons]
        lines.append(
            f"| {photons:g} | {cell(sel, 'template_over_true_x')}; {cell(sel, 'template_over_true_y')} "
            f"| {cell(sel, 'gaussian_over_true_x')}; {cell(sel, 'gaussian_over_true_y')} "
            f"| {cell(sel, 'phase_gain_true')} | {cell(sel, 'phase_gain_template')} "
            f"| {cell(sel, 'phase_gain_gaussian')} |"
        )
    template_s = np.median([r["calibration_s_template"] for r in rows])
    retrieval_s = np.median([r["wall_s_template"] for r in rows])
    lines += [
        "",
        f"Median time of the template calibration {template_s:.2f} s (templates cached per geometry; the",
        f"first call simulates them) against {retrieval_s:.1f} s for one projection's retrieval.",
    ]
    (out / "calibration_dose.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    rows = []
    for photons in DOSES:
        for seed in SEEDS:
            row = measure(photons, seed)
            rows.append(row)
            print(
                f"{photons:g} ph/px seed {seed}: template {row['template_over_true_x']:.3f}/"
                f"{row['template_over_true_y']:.3f}, gaussian {row['gaussian_over_true_x']:.3f}/"
                f"{row['gaussian_over_true_y']:.3f}; gain true {row['phase_gain_true']:.3f}, template "
                f"{row['phase_gain_template']:.3f}, gaussian {row['phase_gain_gaussian']:.3f}",
                flush=True,
            )
    out = write_rows_csv(args.out, "calibration_dose.csv", rows)
    write_markdown(out, rows)
    return rows


if __name__ == "__main__":
    main()
