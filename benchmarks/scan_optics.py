"""Whole scans at beamlines other than the paper's, through the command line alone.

Each scene is the `beads` preset (160 x 320 px, the paper's 83 um glass beads in a cellulose
cylinder, raw uint16 counts with flat and dark, one diffuser position) under other optics:
energy, pixel, L1 / L2 (an upstream diffuser with L1 = 0 included), the source's coherence
lengths, grit, grain shape, dose and an off-centre rotation axis. Each runs as a user would:

    pwf-dask simulate SCAN --angles 41 --positions 1 --axis-offset-px A --energy-eV E ...
    pwf-dask run SCAN RECON            # every default: lengths calibrated, centre found

The reconstruction is then read against the truth the simulated scan records: the largest
bead's delta and beta inside half its radius (xraydb's soda-lime glass), the cylinder's core
(its beads left out; xraydb's cellulose), the calibrated lengths and the rotation centre against
the scan's, the FSC between the angle halves, iterations, and any warning `run` printed.

    python -m benchmarks.scan_optics [--out benchmarks/results] [--only NAME ...]

Writes ``scan_optics.md`` and ``.csv`` (about 28 min on 2 cores).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.demo_dose import cylinder_values
from benchmarks.reporting import command_line, device_name, write_rows_csv

#: (name, what it is, `pwf-dask simulate` options beyond ``--angles 41 --positions 1``); each is
#: run with every default, and the scenes of :data:`GIVEN_UPSTREAM` once more told the distance
SCENES: list[tuple[str, str, list[str]]] = [
    ("paper", "the paper's optics (10 keV, 0.65 um, L1 3 mm, L2 20 mm), P3000", ["--axis-offset-px", "3.3"]),
    (
        "paper-upstream",
        "the paper's optics with its P3000 50 mm upstream of the sample (L1 = 0), raw counts",
        ["--sample-diffuser-distance-m", "0", "--diffuser-upstream-m", "0.05", "--axis-offset-px", "-4.1"],
    ),
    (
        "17keV-upstream",
        "17 keV, 1 um pixels, P2000 50 mm upstream (L1 = 0), L2 60 mm, lengths 3 / 5 um, 5e3 ph/px",
        [
            "--energy-eV",
            "17000",
            "--pixel-size-m",
            "1e-6",
            "--sample-diffuser-distance-m",
            "0",
            "--diffuser-upstream-m",
            "0.05",
            "--diffuser-detector-distance-m",
            "0.06",
            "--grit",
            "P2000",
            "--coherence-length-x-m",
            "3e-6",
            "--coherence-length-y-m",
            "5e-6",
            "--photons",
            "5e3",
            "--axis-offset-px",
            "-5.2",
        ],
    ),  # fmt: skip
    (
        "25keV-coarse",
        "25 keV, 3 um pixels, P1000 200 mm upstream (L1 = 0), L2 0.5 m, lengths 9 / 12 um, 2e4 ph/px",
        [
            "--energy-eV",
            "25000",
            "--pixel-size-m",
            "3e-6",
            "--sample-diffuser-distance-m",
            "0",
            "--diffuser-upstream-m",
            "0.2",
            "--diffuser-detector-distance-m",
            "0.5",
            "--grit",
            "P1000",
            "--coherence-length-x-m",
            "9e-6",
            "--coherence-length-y-m",
            "12e-6",
            "--photons",
            "2e4",
            "--axis-offset-px",
            "7.0",
        ],
    ),  # fmt: skip
    (
        "12keV-faceted-low-dose",
        "12 keV, 0.65 um, L1 5 mm, L2 40 mm, lengths 2.5 / 3.5 um, faceted P3000, 2e3 ph/px",
        [
            "--energy-eV",
            "12000",
            "--sample-diffuser-distance-m",
            "5e-3",
            "--diffuser-detector-distance-m",
            "0.04",
            "--coherence-length-x-m",
            "2.5e-6",
            "--coherence-length-y-m",
            "3.5e-6",
            "--grain-shape",
            "faceted",
            "--photons",
            "2e3",
            "--axis-offset-px",
            "-2.4",
        ],
    ),  # fmt: skip
    (
        "paper-source",
        "the paper's optics, its coherence from an extended source (`--coherence-model source`: the sample "
        "moves against the speckle by 0.23 px rms)",
        ["--coherence-model", "source", "--axis-offset-px", "3.3"],
    ),
    (
        "paper-upstream-source",
        "the paper's optics with its P3000 50 mm upstream, coherence from an extended source (the sample moves "
        "against the speckle by 1.08 px rms)",
        [
            "--sample-diffuser-distance-m",
            "0",
            "--diffuser-upstream-m",
            "0.05",
            "--coherence-model",
            "source",
            "--axis-offset-px",
            "-4.1",
        ],
    ),
    (
        "8keV-absorbing",
        "8 keV (glass beta / delta 0.016: the Re(alpha) rule binds), the paper's distances and lengths, P3000",
        ["--energy-eV", "8000", "--axis-offset-px", "1.7"],
    ),
]
ANGLES = 41
#: scenes whose diffuser sits upstream, run again with ``--diffuser-upstream-m`` as simulated
GIVEN_UPSTREAM = ("paper-upstream", "paper-upstream-source", "17keV-upstream", "25keV-coarse")


def _pwf_dask(*args: str) -> tuple[str, float]:
    """Run ``pwf-dask ARGS`` as a user would; (its stderr, seconds). A failure raises with its line."""
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pwf_dask.cli", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"pwf-dask {args[0]} failed: {done.stderr.strip().splitlines()[-1:]}")
    return done.stderr, time.perf_counter() - t0


def scene_row(work: Path, name: str, what: str, options: list[str], seed: int = 11, run_options=()) -> dict:
    """Simulate, run (with ``run_options``), and read one scene against its truth."""
    import xarray as xr

    from pwf_dask.physics.materials import delta_beta
    from tests.measures import bead_values

    stem = name.replace(", ", "-").replace(" ", "-")
    scan, recon = work / f"{stem}.zarr", work / f"{stem}-recon.zarr"
    _pwf_dask("simulate", str(scan), "--angles", str(ANGLES), "--positions", "1", "--seed", str(seed), *options)
    log, wall = _pwf_dask("run", str(scan), str(recon), *run_options)
    s, ds = xr.open_zarr(scan), xr.open_zarr(recon)
    energy = float(s.attrs["energy_eV"])
    (dg, bg), (dc, bc) = delta_beta("soda-lime glass", energy), delta_beta("cellulose", energy)
    d, b = bead_values(ds, 0)
    cd, cb = cylinder_values(ds)
    pixel = float(s.attrs["pixel_size_m"])
    centre_true = float(s.attrs["simulation_rotation_axis_offset_m"])
    warnings = [line.split("warning:", 1)[1].strip() for line in log.splitlines() if "warning:" in line]
    return {
        "scene": name,
        "what": what,
        "bead_delta_err": d / dg - 1,
        "bead_beta_err": b / bg - 1,
        "cylinder_delta_err": cd / dc - 1,
        "cylinder_beta_err": cb / bc - 1,
        "coherence_x_err": float(ds.attrs["coherence_length_x_m"]) / float(s.attrs["simulation_coherence_length_x_m"])
        - 1,
        "coherence_y_err": float(ds.attrs["coherence_length_y_m"]) / float(s.attrs["simulation_coherence_length_y_m"])
        - 1,
        "centre_err_px": (float(ds.attrs["rotation_center_m"]) - centre_true) / pixel,
        "fsc_delta_um": float(ds.fsc_delta.attrs["resolution_m"]) * 1e6,
        "pixel_um": pixel * 1e6,
        "iterations_median": float(np.median(ds.iterations.values)),
        "iterations_max": int(ds.iterations.values.max()),
        "converged": f"{int(ds.converged.values.sum())}/{ds.converged.size}",
        "alpha": str(ds.attrs.get("alpha", "")),
        "diffuser_model": str(ds.attrs.get("diffuser_model_chosen", ds.attrs.get("diffuser_model", ""))),
        "warnings": " | ".join(warnings),
        "run_s": wall,
    }


def write_report(out_dir, rows: list[dict], argv=None) -> None:
    write_rows_csv(out_dir, "scan_optics.csv", rows)
    lines = [
        f"# Whole scans at other beamlines, through the command line ({device_name(np)})",
        "",
        f"`{command_line('benchmarks.scan_optics', argv)}`: the `beads` preset (160 x 320 px, {ANGLES} angles,",
        "K = 1, raw counts with flat and dark) under each scene's optics, `pwf-dask simulate` then",
        "`pwf-dask run` with every default (lengths calibrated, rotation centre found). Errors are",
        "relative to xraydb's soda-lime glass (the largest bead, inside half its radius) and cellulose",
        "(the cylinder's core, beads left out); the lengths against the simulated source's; the centre",
        "in pixels; the FSC between the angle halves (1/2 criterion).",
        "",
        "| scene | bead delta | bead beta | cylinder delta | cylinder beta | lengths x / y | centre (px) "
        "| FSC delta (um) | iterations median / max | converged | diffuser model | alpha | s |",
        "|---|---:|---:|---:|---:|---|---:|---:|---|---|---|---|---:|",
    ]
    for r in rows:
        alpha = complex(r["alpha"].replace(" ", ""))
        lines.append(
            f"| {r['scene']} | {r['bead_delta_err']:+.1%} | {r['bead_beta_err']:+.1%} "
            f"| {r['cylinder_delta_err']:+.1%} | {r['cylinder_beta_err']:+.1%} "
            f"| {r['coherence_x_err']:+.1%} / {r['coherence_y_err']:+.1%} | {r['centre_err_px']:+.2f} "
            f"| {r['fsc_delta_um']:.2f} ({r['fsc_delta_um'] / r['pixel_um']:.1f} px) "
            f"| {r['iterations_median']:.0f} / {r['iterations_max']} | {r['converged']} | {r['diffuser_model']} "
            f"| {alpha.real:.3g}{alpha.imag:+.3g}j | {r['run_s']:.0f} |"
        )
    lines += ["", "Scenes:", ""] + [f"- **{r['scene']}**: {r['what']}." for r in rows]
    warned = [r for r in rows if r["warnings"]]
    lines += ["", "Warnings `run` printed:", ""]
    lines += [f"- {r['scene']}: {r['warnings']}" for r in warned] or ["- none"]
    with open(Path(out_dir) / "scan_optics.md", "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--only", nargs="+", metavar="NAME", help=f"scenes to run (of {', '.join(s[0] for s in SCENES)})")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="pwf-scan-optics-"))
    rows = []
    try:
        runs = [(name, what, options, ()) for name, what, options in SCENES]
        for name, _what, options in SCENES:
            if name in GIVEN_UPSTREAM:
                distance = options[options.index("--diffuser-upstream-m") + 1]
                given = ("--diffuser-upstream-m", distance)
                runs.append(
                    (f"{name}, distance given", f"the same, `run --diffuser-upstream-m {distance}`", options, given)
                )
        for name, what, options, run_options in runs:
            if args.only and name.split(",")[0] not in args.only:
                continue
            rows.append(scene_row(work, name, what, options, run_options=run_options))
            r = rows[-1]
            print(
                f"{name}: bead {r['bead_delta_err']:+.1%} / {r['bead_beta_err']:+.1%}, cylinder "
                f"{r['cylinder_delta_err']:+.1%} / {r['cylinder_beta_err']:+.1%}, "
                f"lengths {r['coherence_x_err']:+.1%} / "
                f"{r['coherence_y_err']:+.1%}, centre {r['centre_err_px']:+.2f} px, FSC {r['fsc_delta_um']:.2f} um, "
                f"{r['run_s']:.0f} s{'; warned' if r['warnings'] else ''}",
                flush=True,
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write_report(args.out, rows, argv)
    return rows


if __name__ == "__main__":
    main()
