"""How many iterations the diffuser probe needs (docs/methods.md, "The probe's length and its
window's own estimates").

``diffuser_model="auto"`` probes both diffuser models where the absorption rule gives zero
phase: :data:`pwf_dask.retrieval.DIFFUSER_PROBE_ITER` iterations of each from zero, then the
single-material fit where its data residual is under
:data:`pwf_dask.retrieval.DIFFUSER_PROBE_RATIO` of zero phase's. The probe is per-scan work
(once per diffuser position) that a single projection's call pays in full. Here
:func:`pwf_dask.retrieval.choose_diffuser` runs at several probe lengths on every scene of
:mod:`benchmarks.random_scenes` where it probes (true coherence lengths, then calibrated ones,
as a user's run) and on three strips of the issue's 25 keV real-data regime: the residual
ratio, the model chosen and the time, beside one zero-phase retrieval of the same scene.

    python -m benchmarks.probe_iterations [--iterations 10,20,40] [--scenes 80] [--part all|strips]
        [--out benchmarks/results]

Writes ``probe_iterations.md`` and ``.csv`` (about 25 minutes on 2 cores; ``--part strips``
re-runs the strips only, about 6 minutes, keeping the random scenes' rows in ``--out``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.frame_size import strip_crop, strip_projection, strip_setup
from benchmarks.random_scenes import draw_scene
from benchmarks.reporting import device_name, read_rows_csv, timed_with, write_rows_csv
from pwf_dask import retrieval
from pwf_dask.options import DEFAULTS

ITERATIONS = (10, 20, 40)
#: (grit, frame) of the strip regime (benchmarks/frame_size.py, seed 1): the issue's whole
#: frame, a coarser grit on it, and the 430 x 700 crop of the issue's table
STRIPS = (("P3000", (430, 2220)), ("P1200", (430, 2220)), ("P3000", (430, 700)))


def _probe_rows(scene: str, lengths: str, sample, reference, geometry: dict, iterations, retrieval_s: float):
    rows = []
    for n in iterations:
        choice, seconds = timed_with(
            retrieval, "DIFFUSER_PROBE_ITER", n, retrieval.choose_diffuser, sample, reference, **geometry
        )
        r = choice.residuals_pct
        rows.append(
            {
                "scene": scene,
                "lengths": lengths,
                "iterations": n,
                "model": choice.model,
                "zero_phase_pct": r["zero-phase"],
                "single_material_pct": r["single-material"],
                "ratio": r["single-material"] / r["zero-phase"],
                "probe_s": seconds,
                "retrieval_s": retrieval_s,
            }
        )
        print(rows[-1], flush=True)
    return rows


def random_scene_rows(i: int, iterations, calibrated: bool) -> list[dict]:
    """Scene ``i`` of :mod:`benchmarks.random_scenes` at each probe length, where the absorption
    rule gives zero phase (else no rows), and one zero-phase retrieval's time."""
    setup, sim, _ = draw_scene(i)
    if retrieval.chosen_diffuser_model("auto", DEFAULTS.diffuser_material, None, setup.energy_eV)[0] != "zero-phase":
        return []
    geometry = dict(sim.geometry())
    if setup.diffuser_upstream_m:
        geometry["diffuser_upstream_m"] = setup.diffuser_upstream_m
    if not calibrated:
        geometry.update(
            coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m
        )
    t0 = time.perf_counter()
    try:
        retrieval.retrieve_projection(sim.sample, sim.reference, **geometry, diffuser_model="zero-phase")
    except ValueError:  # the calibration's refusal (calibrated lengths): no probe either
        return []
    retrieval_s = time.perf_counter() - t0
    lengths = "calibrated" if calibrated else "true"
    return _probe_rows(str(i), lengths, sim.sample, sim.reference, geometry, iterations, retrieval_s)


def strip_rows(iterations) -> list[dict]:
    """The strips of :data:`STRIPS` (calibrated lengths, every default) at each probe length."""
    rows = []
    for grit, (ny, nx) in STRIPS:
        setup = strip_setup(None if grit == "P3000" else grit)
        sample, reference, _, _ = strip_projection(setup, 1)
        crop = strip_crop(setup, ny, nx)
        t0 = time.perf_counter()
        retrieval.retrieve_projection(sample[crop], reference[crop], **setup.geometry(), diffuser_model="zero-phase")
        retrieval_s = time.perf_counter() - t0
        scene = f"strip {grit} {ny} x {nx}"
        rows += _probe_rows(
            scene, "calibrated", sample[crop], reference[crop], setup.geometry(), iterations, retrieval_s
        )
    return rows


def _summary_line(rows: list[dict], reference: dict) -> str:
    switched = [r for r in rows if r["model"] == "single-material"]
    stayed = [r for r in rows if r["model"] == "zero-phase"]
    same = sum(r["model"] == reference[r["scene"]] for r in rows)
    cost = np.median([r["probe_s"] / r["retrieval_s"] for r in rows])
    return (
        f"| {rows[0]['lengths']} | {rows[0]['iterations']} | {len(rows)} "
        f"| {', '.join(r['scene'] for r in switched) or '-'} "
        f"| {max((r['ratio'] for r in switched), default=float('nan')):.3f} "
        f"| {min((r['ratio'] for r in stayed), default=float('nan')):.3f} | {same} | {cost:.2f} |"
    )


def write_markdown(rows: list[dict], iterations, path: str) -> None:
    longest = max(iterations)
    scenes = [r for r in rows if not r["scene"].startswith("strip")]
    lines = [
        "# How many iterations the diffuser probe needs",
        "",
        f"`python -m benchmarks.probe_iterations` on {device_name(np)}. `choose_diffuser` at each probe length on "
        "the scenes of `benchmarks.random_scenes` where the absorption rule gives zero phase (the probe "
        "runs there), with the true coherence lengths and with calibrated ones (scenes the calibration "
        "refuses left out). Switched: the scenes where the single-material fit's residual is under 0.5 of "
        "zero phase's. Cost: the probe (`choose_diffuser`, both diffuser estimates included) over one "
        "zero-phase `retrieve_projection` of the same scene, median.",
        "",
        f"| lengths | iterations | scenes probed | switched | largest ratio switched | smallest ratio kept "
        f"| same choice as {longest} | probe / retrieval |",
        "|---|---:|---:|---|---:|---:|---:|---:|",
    ]
    for lengths in ("true", "calibrated"):
        group = [r for r in scenes if r["lengths"] == lengths]
        reference = {r["scene"]: r["model"] for r in group if r["iterations"] == longest}
        for n in iterations:
            picked = [r for r in group if r["iterations"] == n]
            if picked:
                lines.append(_summary_line(picked, reference))
    lines += [
        "",
        "The strip regime (25 keV, 6.5 um pixels, 50 mm upstream, L1 = 0, L2 = 0.7 m, four PMMA rods, seed 1, "
        "calibrated lengths; frames over 512^2 probed on their centred window):",
        "",
        "| scene | iterations | model | zero phase % | single material % | ratio | probe s | retrieval s |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r["scene"].startswith("strip"):
            lines.append(
                f"| {r['scene']} | {r['iterations']} | {r['model']} | {r['zero_phase_pct']:.3f} "
                f"| {r['single_material_pct']:.3f} | {r['ratio']:.3f} | {r['probe_s']:.1f} | {r['retrieval_s']:.1f} |"
            )
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", default=",".join(map(str, ITERATIONS)))
    ap.add_argument("--scenes", type=int, default=80)
    ap.add_argument("--part", choices=("all", "strips"), default="all")
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    iterations = tuple(int(n) for n in args.iterations.split(","))
    rows = []
    if args.part == "strips":
        kept = read_rows_csv(args.out, "probe_iterations.csv")
        rows = [{**r, "scene": str(r["scene"])} for r in kept if not str(r["scene"]).startswith("strip")]
    else:
        for calibrated in (False, True):
            for i in range(args.scenes):
                rows += random_scene_rows(i, iterations, calibrated)
    rows += strip_rows(iterations)
    out = write_rows_csv(args.out, "probe_iterations.csv", rows)
    write_markdown(rows, iterations, str(out / "probe_iterations.md"))
    return rows


if __name__ == "__main__":
    main()
