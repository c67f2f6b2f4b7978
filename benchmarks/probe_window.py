"""The diffuser probe on a window of wide frames against the whole frame (docs/methods.md,
"The probe on a window of wide frames").

``diffuser_model="auto"`` probes both diffuser models for
:data:`pwf_dask.retrieval.DIFFUSER_PROBE_ITER` iterations where the absorption rule gives zero
phase (25 keV here). A frame over
:data:`pwf_dask.retrieval.DIFFUSER_PROBE_MAX_PX` is probed on its centred window
(:func:`pwf_dask.retrieval.probe_window`). For each strip of the issue's real-data regime
(25 keV, 6.5 um pixels, four PMMA rods; P3000 on four draws, P1200 and P2000) this runs
:func:`pwf_dask.retrieval.choose_diffuser` with the cap lifted (the whole frame) and as it is:
the model chosen, both residuals, their ratio (the rule's threshold is 0.5) and the time; then
the issue's real-data call on the whole 430 x 2220 frame both ways: time, iterations, phase gain.

    python -m benchmarks.probe_window [--out benchmarks/results]

Writes ``probe_window.md``, ``.csv`` and ``probe_window_call.csv`` (about 12 minutes on 2 cores).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.frame_size import (
    STRIP_SETUP,
    phase_gain,
    phase_rms_error,
    strip_crop,
    strip_projection,
    strip_setup,
)
from benchmarks.reporting import device_name, timed_with, write_rows_csv
from pwf_dask import retrieval

#: (grit, seed, frame): the issue's whole frame on four P3000 draws and two coarser grits,
#: the 430 x 700 crop of the issue's table and the 160 x 2220 full-width strip
SCENES = (
    *(("P3000", seed, (430, 2220)) for seed in (1, 2, 3, 4)),
    ("P3000", 1, (430, 700)),
    ("P3000", 1, (160, 2220)),
    ("P1200", 1, (430, 2220)),
    ("P2000", 1, (430, 2220)),
)
#: the cap that probes every frame whole (the code before session 59)
WHOLE_FRAME = 10**12


def choices() -> list[dict]:
    """Per scene, the probe on the whole frame and on its window."""
    rows = []
    for grit, seed, (ny, nx) in SCENES:
        setup = strip_setup(None if grit == "P3000" else grit)
        sample, reference, _, _ = strip_projection(setup, seed)
        crop = strip_crop(setup, ny, nx)
        for probed, cap in (("whole frame", WHOLE_FRAME), ("window", retrieval.DIFFUSER_PROBE_MAX_PX)):
            window = retrieval.probe_window((ny, nx), cap)
            choice, seconds = timed_with(
                retrieval,
                "DIFFUSER_PROBE_MAX_PX",
                cap,
                retrieval.choose_diffuser,
                sample[crop],
                reference[crop],
                **setup.geometry(),
            )
            r = choice.residuals_pct
            rows.append(
                {
                    "scene": f"strip, {grit}, seed {seed}",
                    "frame": f"{ny} x {nx}",
                    "probed": f"{probed} ({window[0].stop - window[0].start} x {window[1].stop - window[1].start})",
                    "model": choice.model,
                    "zero_phase_pct": r["zero-phase"],
                    "single_material_pct": r["single-material"],
                    "ratio": r["single-material"] / r["zero-phase"],
                    "seconds": seconds,
                }
            )
            print(rows[-1], flush=True)
    return rows


def whole_frame_call() -> list[dict]:
    """The issue's real-data call (every default, L1 = 0, L2 = 0.7 m) on its whole frame,
    the probe on the whole frame and on its window."""
    sample, reference, phase, _ = strip_projection(STRIP_SETUP, 1)
    rows = []
    for probed, cap in (("whole frame", WHOLE_FRAME), ("window", retrieval.DIFFUSER_PROBE_MAX_PX)):
        r, seconds = timed_with(
            retrieval,
            "DIFFUSER_PROBE_MAX_PX",
            cap,
            retrieval.retrieve_projection,
            sample,
            reference,
            **STRIP_SETUP.geometry(),
        )
        rows.append(
            {
                "probed": probed,
                "model": r.parameters["diffuser_model"],
                "iterations": r.iterations,
                "phase_gain": phase_gain(np.asarray(r.phase), phase),
                "phase_rms_error_rad": phase_rms_error(np.asarray(r.phase), phase),
                "seconds": seconds,
            }
        )
        print(rows[-1], flush=True)
    return rows


def write_markdown(probes: list[dict], calls: list[dict], path: str) -> None:
    lines = [
        "# The diffuser probe on a window of wide frames",
        "",
        f"`python -m benchmarks.probe_window` on {device_name(np)}. `choose_diffuser` on the strip regime "
        "(25 keV, 6.5 um pixels, the diffuser 50 mm upstream, L1 = 0, L2 = 0.7 m, four PMMA rods), the probe "
        "on the whole frame and on its centred window of at most 512^2 pixels; residuals after "
        f"{retrieval.DIFFUSER_PROBE_ITER} iterations of each model, % of the mean reference; ratio = single "
        "material / zero phase ('auto' takes the single-material fit below 0.5). Seconds include both diffuser "
        "estimates.",
        "",
        "| scene | frame | probed | model | zero phase % | single material % | ratio | s |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    for r in probes:
        lines.append(
            f"| {r['scene']} | {r['frame']} | {r['probed']} | {r['model']} | {r['zero_phase_pct']:.3f} "
            f"| {r['single_material_pct']:.3f} | {r['ratio']:.3f} | {r['seconds']:.1f} |"
        )
    lines += [
        "",
        "The issue's real-data call on its whole 430 x 2220 frame (P3000, seed 1; `retrieve_projection` with "
        "L1 = 0, L2 = 0.7 m and nothing else), one run:",
        "",
        "| probe | model | iterations | phase gain | phase rms error (rad) | s |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for r in calls:
        lines.append(
            f"| {r['probed']} | {r['model']} | {r['iterations']} | {r['phase_gain']:.3f} "
            f"| {r['phase_rms_error_rad']:.2f} | {r['seconds']:.1f} |"
        )
    if len(calls) == 2:
        lines += ["", f"Window / whole frame: {calls[1]['seconds'] / calls[0]['seconds']:.2f}x the time."]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results", help="folder for probe_window.md and its .csv files")
    a = ap.parse_args()
    probes = choices()
    calls = whole_frame_call()
    write_rows_csv(a.out, "probe_window.csv", probes)
    write_rows_csv(a.out, "probe_window_call.csv", calls)
    write_markdown(probes, calls, f"{a.out}/probe_window.md")


if __name__ == "__main__":
    main()
