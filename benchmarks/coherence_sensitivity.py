"""Phase gain against coherence-length error, every other default (issue #27, item 4;
docs/methods.md, "Sensitivity to the coherence length").

Each scene (the paper's geometry, 1e4 ph/px, the default bead phantom) is retrieved with both
coherence lengths set to ``scale`` x the true ones, for each scale, and once calibrated as a
user's run is. Per run: the phase gain as the accuracy tests measure it (a line fitted where the
true phase is below -0.5 rad) and as the stability map does (through the origin over the whole
sample, the background's mean removed), the relative phase error, the largest bead's phase-contrast error
and the grid and diffuser model the defaults chose (both follow the lengths). Per scene, the
sensitivity: the largest |gain(scale) - gain(1)| per 10 % of length error over the scales
within ``--band`` of 1, and the slope of a line fitted over them.

    python -m benchmarks.coherence_sensitivity [--photons 1e4] [--out benchmarks/results]

Writes ``coherence_sensitivity.md`` and ``.csv`` (about 12 minutes on 2 cores); at another dose
(``--photons``, session 102: 1e3 and 1e2 ph/px, where a held-out random scene at 113 ph/px read
gain 1.44 with lengths 8-11 % short and 1.01 with the true ones) ``coherence_sensitivity_<N>ph.*``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.frame_size import fitted_phase_gain
from benchmarks.reporting import device_name, write_rows_csv
from benchmarks.stability import bead_regions, errors
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, simulate_projection

SCALES = (0.7, 0.85, 0.9, 1.0, 1.1, 1.15, 1.3)
#: the scales the sensitivity is read over: a calibration within this of the truth
BAND = 0.15
#: the dose of the committed ``coherence_sensitivity.*`` (ph/px)
DEFAULT_PHOTONS = 1e4
#: (label, setup, seed): P3000 (the default) on three draws, finer and coarser grains, 512^2
SCENES = (
    ("P3000 256^2, seed 1", SpeckleSetup(shape=(256, 256)), 1),
    ("P3000 256^2, seed 2", SpeckleSetup(shape=(256, 256)), 2),
    ("P3000 256^2, seed 3", SpeckleSetup(shape=(256, 256)), 3),
    ("1.2 um grains 256^2, seed 1", replace(SpeckleSetup(shape=(256, 256)), diffuser_radius_median_m=1.2e-6), 1),
    ("4.5 um grains 256^2, seed 1", replace(SpeckleSetup(shape=(256, 256)), diffuser_radius_median_m=4.5e-6), 1),
    ("P3000 512^2, seed 1", SpeckleSetup(shape=(512, 512)), 1),
)


def run(sim, bead, label: str, scale: float | None) -> dict:
    """One retrieval at ``scale`` x the true lengths (None: calibrated)."""
    lengths = {}
    if scale is not None:
        lengths = {
            "coherence_length_x_m": scale * sim.coherence_length_x_m,
            "coherence_length_y_m": scale * sim.coherence_length_y_m,
        }
    t0 = time.perf_counter()
    r = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), **lengths)
    seconds = time.perf_counter() - t0
    phase = np.asarray(r.phase)
    background = np.abs(sim.phase) < 1e-6
    e = errors(phase, np.asarray(r.attenuation), sim.phase, sim.attenuation, background, bead)
    return {
        "scene": label,
        "scale": float(r.coherence_length_x_m / sim.coherence_length_x_m),
        "scale_y": float(r.coherence_length_y_m / sim.coherence_length_y_m),
        "calibrated": scale is None,
        "phase_gain": fitted_phase_gain(phase, sim.phase),
        "phase_gain_origin": e["phase_gain"],
        "phase_error": e["phase_error"],
        "bead_contrast_error": e["bead_contrast_error"],
        "field_upsample": r.parameters["field_upsample"],
        "diffuser_model": r.parameters["diffuser_model"],
        "iterations": r.iterations,
        "seconds": seconds,
    }


def scene_rows(label: str, setup: SpeckleSetup, seed: int, photons: float = DEFAULT_PHOTONS) -> list[dict]:
    setup = replace(setup, photons=photons)
    sim = simulate_projection(setup, seed=seed)
    bead = bead_regions(SpeckleSimulator(setup, seed=seed), sim.phantom)
    rows = []
    for scale in (*SCALES, None):
        rows.append(run(sim, bead, label, scale))
        print(rows[-1], flush=True)
    return rows


def sensitivity(rows: list[dict], key: str = "phase_gain", band: float = BAND) -> dict:
    """Per 10 % of length error: the largest |change| of ``key`` and its fitted slope, over the
    fixed scales within ``band`` of 1."""
    fixed = [r for r in rows if not r["calibrated"] and abs(r["scale"] - 1.0) <= band + 1e-9]
    g1 = next(r[key] for r in fixed if abs(r["scale"] - 1.0) < 1e-9)
    worst = max(abs(r[key] - g1) / abs(r["scale"] - 1.0) * 0.1 for r in fixed if r["scale"] != 1.0)
    slope = np.polyfit([r["scale"] for r in fixed], [r[key] for r in fixed], 1)[0]
    return {"worst_per_10pct": float(worst), "slope_per_10pct": float(slope * 0.1), "gain_true": g1}


def results_name(photons: float) -> str:
    """The file stem at ``photons`` ph/px: ``coherence_sensitivity`` at the default dose."""
    return "coherence_sensitivity" if photons == DEFAULT_PHOTONS else f"coherence_sensitivity_{photons:g}ph"


def write_markdown(rows: list[dict], path: str, photons: float = DEFAULT_PHOTONS) -> None:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    option = "" if photons == DEFAULT_PHOTONS else f" --photons {photons:g}"
    lines = [
        "# Phase gain against coherence-length error",
        "",
        f"`python -m benchmarks.coherence_sensitivity{option}` on {device_name(np)}: the paper's geometry,",
        f"{photons:g} ph/px, the default bead phantom, every default but the lengths (both set to scale x",
        "the true ones; the last",
        "row of each scene calibrated from its reference). Gain: the slope of a line fitted to recovered",
        "against true phase where the true phase is below -0.5 rad (the accuracy tests' measure); through 0:",
        "the stability map's (through the origin, the whole sample); phase error: rms over the sample,",
        "relative; bead: the largest bead's phase contrast error. The defaults choose the field grid and",
        "the diffuser model from the lengths.",
        "",
        f"## Sensitivity (per 10 % of length error, scales within {BAND:.0%} of the truth)",
        "",
        "| scene | gain, true lengths | largest change | fitted slope | through 0: gain, largest change "
        "| phase error: true lengths, largest in the band, calibrated |",
        "|---|---|---|---|---|---|",
    ]
    for name in scenes:
        own = [r for r in rows if r["scene"] == name]
        s, o = sensitivity(own), sensitivity(own, "phase_gain_origin")
        fixed = [r for r in own if not r["calibrated"]]
        true = next(r["phase_error"] for r in fixed if abs(r["scale"] - 1.0) < 1e-9)
        band = max(r["phase_error"] for r in fixed if abs(r["scale"] - 1.0) <= BAND + 1e-9)
        calibrated = next(r["phase_error"] for r in own if r["calibrated"])
        lines.append(
            f"| {name} | {s['gain_true']:.3f} | {s['worst_per_10pct']:.1%} | {s['slope_per_10pct']:+.1%} "
            f"| {o['gain_true']:.3f}, {o['worst_per_10pct']:.1%} | {true:.3f}, {band:.3f}, {calibrated:.3f} |"
        )
    lines += [
        "",
        "## Every run",
        "",
        "| scene | scale | gain | gain through 0 | phase error | bead | field grid | diffuser | iterations | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        scale = f"{r['scale']:.3f} / {r['scale_y']:.3f} (calibrated)" if r["calibrated"] else f"{r['scale']:.2f}"
        lines.append(
            f"| {r['scene']} | {scale} | {r['phase_gain']:.3f} | {r['phase_gain_origin']:.3f} | {r['phase_error']:.3f} "
            f"| {r['bead_contrast_error']:+.1%} | {r['field_upsample']} | {r['diffuser_model']} "
            f"| {r['iterations']} | {r['seconds']:.0f} |"
        )
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results", help="folder for coherence_sensitivity.md and .csv")
    ap.add_argument("--photons", type=float, default=DEFAULT_PHOTONS, help="the scenes' dose, ph/px")
    a = ap.parse_args()
    rows = [row for label, setup, seed in SCENES for row in scene_rows(label, setup, seed, a.photons)]
    name = results_name(a.photons)
    write_rows_csv(a.out, f"{name}.csv", rows)
    write_markdown(rows, f"{a.out}/{name}.md", a.photons)


if __name__ == "__main__":
    main()
