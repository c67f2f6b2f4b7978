"""Calibrated coherence lengths scaled long on the random geometries' low-dose scenes: a lead.

At 1e2-1e3 ph/px the phase leans on the coherence lengths far more than at 1e4, and lopsidedly:
short lengths cost far more than long ones (docs/methods.md, "Sensitivity to the coherence
length", session 102). The calibration reads 0.945-0.99 of the lengths at those doses. Do lengths
biased long help a user's run where the dose is low? Every random geometry of
``sensitivity_check.csv`` (scenes 0-239) whose reference carries under ``--max-photons`` ph/px,
whose calibration did not refuse and whose phase sensitivity S is at or above the warning's limit
(below it the data carry little either way) is retrieved by PWF with every default but the
lengths: the calibrated lengths (the committed row's ``coherence_*_um_used``) times each factor.
The committed row itself is the factor 1 (today's defaults; the same ``scene_row``).

    python -m benchmarks.low_dose_lengths [--factors 1.1 1.25] [--max-photons 2000] [--report-only]
                                          [--out benchmarks/results]

Writes ``low_dose_lengths.md`` and ``.csv`` (about 16 min for two factors on 2 cores).
``--scale im-alpha`` scales the alpha rule's Im(alpha) instead, the lengths as calibrated (the
other route: a stronger penalty where the noise is high), and writes ``low_dose_alpha.*``.

``--fresh FIRST COUNT`` checks a factor chosen on those scenes on scenes it was not chosen on:
random geometries FIRST to FIRST + COUNT - 1, drawn as ``random_scenes`` draws them but with the
dose drawn log-uniform from 1e2 to ``--max-photons`` (seeded per scene), each retrieved with
every default (the factor 1) and with the calibrated lengths times each factor; scenes whose
calibration refuses or whose S lies under the limit are left out. Writes
``low_dose_lengths_fresh.md`` and ``.csv``.

``--reference-dose K`` asks where the long lengths' gain comes from: each of the committed
scenes is run again with its reference at K times the sample's dose (the K flats a beamline
averages; a noise draw of its own, :func:`reference_at_dose`), the lengths the committed row's
calibrated ones times each factor (give ``--factors 1 1.1``). The report sets each row against
the committed one and each factor against this run's factor 1. Writes ``low_dose_reference.md``
and ``.csv`` (about 18 min for K = 10 and two factors); at another K ``low_dose_reference_<K>x.*``.
``--nsr-floor F`` gives the retrievals ``diffuser_nsr_floor=F`` (a number, or "sample": the default)
and adds ``_floor<F>`` to the name where F is a number: 0 is the Wiener NSR as the reference reads
it, the default before session 104 (a reference that clean breaks the zero-phase estimate with it:
docs/methods.md). ``--min-photons M --max-photons inf`` takes the committed scenes from M ph/px up
instead and writes ``high_dose_reference*.*``: does a cleaner reference pay where the sample
images are bright?
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from benchmarks.random_scenes import draw_scene, retrieve_scene
from benchmarks.reporting import command_line, device_name, read_rows_csv, rows_of
from benchmarks.stability import PHASE_ERROR_THRESHOLD, errors
from pwf_dask.calibration import SensitivityLimits
from pwf_dask.calibration.diffuser import SAMPLE_FLOOR
from pwf_dask.options import DEFAULTS
from pwf_dask.pwf.solver import sensitivity_alpha
from pwf_dask.simulation import SpeckleSimulator

#: the doses the summary keeps apart (ph/px): the calibration's low-dose threshold is 500
DOSE_BANDS = ((0.0, 500.0, "under 500"), (500.0, np.inf, "500 and over"))
#: ``--fresh`` scene i draws its dose from default_rng(FRESH_DOSE_SEED + i)
FRESH_DOSE_SEED = 5000
#: ``--reference-dose``: scene i's reference noise from default_rng((REFERENCE_NOISE_SEED, i))
REFERENCE_NOISE_SEED = 6000


def low_dose_scenes(out_dir: str, max_photons: float, min_photons: float = 0.0) -> list[dict]:
    """The committed PWF rows this study scales: a dose from ``min_photons`` to under
    ``max_photons``, calibrated, S at or above the limit."""
    limit = SensitivityLimits().min_phase_sensitivity
    return [
        r
        for r in read_rows_csv(out_dir, "sensitivity_check.csv")
        if not r["refused"] and min_photons <= r["photons"] < max_photons and r["phase_sensitivity"] >= limit
    ]


def fresh_base(i: int, max_photons: float) -> dict | None:
    """Scene ``i`` at a dose drawn from 1e2 to ``max_photons``, retrieved with every default:
    its row as :func:`low_dose_scenes` gives the committed ones (None where the calibration
    refuses or S lies under the limit)."""
    rng = np.random.default_rng(FRESH_DOSE_SEED + i)
    photons = float(10 ** rng.uniform(2.0, np.log10(max_photons)))
    setup, sim, background = draw_scene(i, photons)
    try:
        res = retrieve_scene(setup, sim, background, "pwf")
    except ValueError:
        return None
    if res.parameters["phase_sensitivity"] < SensitivityLimits().min_phase_sensitivity:
        return None
    err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
    return {
        "scene": i,
        "photons": photons,
        "phase_error": err["phase_error"],
        "phase_gain": err["phase_gain"],
        "coherence_x_um_used": res.coherence_length_x_m * 1e6,
        "coherence_y_um_used": res.coherence_length_y_m * 1e6,
        "phase_sensitivity": res.parameters["phase_sensitivity"],
    }


def reference_at_dose(setup, scene: int, dose_factor: float) -> np.ndarray:
    """Scene ``scene``'s reference (its diffuser, :func:`draw_scene`) at ``dose_factor`` times
    the scene's dose (inf: noise-free): the many flats a beamline averages into one reference.
    Its photon noise is drawn from a stream of its own, not the sample image's."""
    sim = SpeckleSimulator(setup, seed=scene)
    clean = sim.intensity(None, sim.diffuser())
    sim.rng = np.random.default_rng((REFERENCE_NOISE_SEED, scene))
    return sim.noisy(clean, dose_factor * setup.photons)


def scaled_row(
    base: dict,
    factor: float,
    scaled: str = "lengths",
    reference_dose: float = 1.0,
    nsr_floor: float | str = DEFAULTS.diffuser_nsr_floor,
) -> dict:
    """PWF on ``base``'s scene (at its dose) with its calibrated lengths times ``factor``, or
    (``scaled="im-alpha"``) with those lengths and the alpha rule's Im(alpha) times ``factor``;
    ``reference_dose`` != 1: the reference at that many times the sample's dose
    (:func:`reference_at_dose`), the lengths still the committed row's calibrated ones;
    ``nsr_floor``: the retrieval's ``diffuser_nsr_floor``."""
    setup, sim, background = draw_scene(int(base["scene"]), base["photons"])
    if reference_dose != 1.0:
        sim = replace(sim, reference=reference_at_dose(setup, int(base["scene"]), reference_dose))
    lengths = factor if scaled == "lengths" else 1.0
    options = {"diffuser_nsr_floor": nsr_floor}
    if scaled == "im-alpha":
        rule = sensitivity_alpha(base["phase_sensitivity"])
        options["alpha"] = complex(rule.real, factor * rule.imag)
    res = retrieve_scene(
        setup,
        sim,
        background,
        "pwf",
        coherence_length_x_m=lengths * base["coherence_x_um_used"] * 1e-6,
        coherence_length_y_m=lengths * base["coherence_y_um_used"] * 1e-6,
        **options,
    )
    err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
    return {
        "scene": base["scene"],
        "photons": base["photons"],
        "factor": factor,
        "reference_dose": reference_dose,
        "nsr_floor": nsr_floor,
        "phase_error": err["phase_error"],
        "phase_gain": err["phase_gain"],
        "iterations": int(res.iterations),
        "base_error": base["phase_error"],
        "base_gain": base["phase_gain"],
    }


def summary_lines(rows: list[dict]) -> list[str]:
    """Per factor and dose band: holds at factor 1 and scaled, gained and lost, better and worse."""
    lines = [
        "| factor | ph/px | scenes | holds: calibrated -> scaled | gained / lost | better / worse by 0.02 "
        "| median error |",
        "|---:|---|---:|---|---|---|---|",
    ]
    for factor in dict.fromkeys(r["factor"] for r in rows):
        for lo, hi, label in (*DOSE_BANDS, (0.0, np.inf, "all")):
            rs = [r for r in rows if r["factor"] == factor and lo <= r["photons"] < hi]
            if not rs:  # a band the scenes' doses miss
                continue
            base = np.array([r["base_error"] for r in rs])
            new = np.array([r["phase_error"] for r in rs])
            held, holds = base < PHASE_ERROR_THRESHOLD, new < PHASE_ERROR_THRESHOLD
            lines.append(
                f"| {factor:g} | {label} | {len(rs)} | {held.sum()} -> {holds.sum()} "
                f"| {np.sum(holds & ~held)} / {np.sum(held & ~holds)} "
                f"| {np.sum(new < base - 0.02)} / {np.sum(new > base + 0.02)} "
                f"| {np.median(base):.3f} -> {np.median(new):.3f} |"
            )
    return lines


def against_factor_one(rows: list[dict]) -> list[dict]:
    """``rows`` other than the factor 1, each with that scene's factor-1 row of the same run as
    its base: what the factor adds on top of whatever else the run changed."""
    one = {r["scene"]: r for r in rows if r["factor"] == 1.0}
    return [
        r | {"base_error": one[r["scene"]]["phase_error"], "base_gain": one[r["scene"]]["phase_gain"]}
        for r in rows
        if r["factor"] != 1.0 and r["scene"] in one
    ]


def write_report(rows: list[dict], out_dir: str, device: str, command: str, name: str = "low_dose_lengths") -> None:
    band = "high dose" if name.startswith("high_dose") else "low dose"
    scenes = (
        "new random geometries at a dose drawn from 1e2 ph/px up, a calibration that did not refuse and S at or",
        "above the warning's limit; the factor 1 is every default, run beside (module docstring).",
    )
    if not name.endswith("_fresh"):
        scenes = (
            f"the random geometries of `sensitivity_check.csv` with a {band}, a calibration that did not refuse",
            "and S at or above the warning's limit; the factor 1 is the committed row (module docstring).",
        )
    what, scaled = (
        "Calibrated coherence lengths scaled long",
        "the coherence lengths, the calibrated ones times the factor",
    )
    if name.startswith("low_dose_alpha"):
        what, scaled = "Im(alpha) raised", "Im(alpha), the alpha rule's times the factor (the lengths calibrated)"
    within = []
    if name.startswith(("low_dose_reference", "high_dose_reference")):
        # rows of before the option ran with the reference's own ratio (0)
        dose, floor = rows[0]["reference_dose"], rows[0].get("nsr_floor", 0.0)
        fixed = floor != SAMPLE_FLOOR
        longer = any(r["factor"] != 1.0 for r in rows)
        parts = [f"A reference at {dose:g}x the sample's dose", *longer * ["the lengths scaled long"]]
        parts += [f"the Wiener NSR floored at {floor:g}" if floor else "the Wiener NSR as read"] if fixed else []
        what = ", ".join(parts) + ("," if len(parts) > 1 else "")
        scaled = (
            f"the reference, at {dose:g}x the sample's dose (its own noise draw), and the coherence lengths,"
            " the calibrated ones times the factor"
        )
        scaled += f", with `diffuser_nsr_floor={floor:g}`" if fixed else ""
        within = longer * [
            "",
            "Each factor against the factor 1 of this run (both with the reference at that dose):",
            "",
            *summary_lines(against_factor_one(rows)),
        ]
    lines = [
        f"# {what} at {band} ({device})",
        "",
        f"`{command}`: PWF with every default but {scaled}, on",
        *scenes,
        f"A scene holds below a relative phase error of {PHASE_ERROR_THRESHOLD:g} inside the sample.",
        "",
        *summary_lines(rows),
        *within,
        "",
        "| scene | ph/px | factor | phase error: calibrated -> scaled | gain: calibrated -> scaled | iterations |",
        "|---:|---:|---:|---|---|---:|",
    ]
    for r in sorted(rows, key=lambda r: (r["scene"], r["factor"])):
        lines.append(
            f"| {r['scene']} | {r['photons']:.0f} | {r['factor']:g} | {r['base_error']:.3f} -> {r['phase_error']:.3f} "
            f"| {r['base_gain']:.2f} -> {r['phase_gain']:.2f} | {r['iterations']} |"
        )
    with open(f"{out_dir}/{name}.md", "w") as fh:
        fh.write("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--factors", type=float, nargs="+", default=[1.1, 1.25])
    ap.add_argument("--max-photons", type=float, default=2000.0)
    ap.add_argument(
        "--min-photons",
        type=float,
        default=0.0,
        help="with --reference-dose: the committed scenes from this dose up (and --max-photons inf); writes "
        "high_dose_reference*.* (the reference cleaner where the sample images are bright)",
    )
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the committed csv")
    ap.add_argument("--fresh", type=int, nargs=2, metavar=("FIRST", "COUNT"), help="new scenes at a drawn low dose")
    ap.add_argument(
        "--reference-dose",
        type=float,
        default=1.0,
        help="the reference at this many times the sample's dose (inf: noise-free); writes low_dose_reference.* "
        "at 10, low_dose_reference_<K>x.* at others",
    )
    ap.add_argument(
        "--nsr-floor",
        type=lambda text: text if text == SAMPLE_FLOOR else float(text),
        default=DEFAULTS.diffuser_nsr_floor,
        help="with --reference-dose: the retrieval's diffuser_nsr_floor ('sample', the default, or a number: "
        "adds _floor<F> to the name)",
    )
    ap.add_argument(
        "--scale",
        choices=("lengths", "im-alpha"),
        default="lengths",
        help="what the factors scale (im-alpha: the rule's)",
    )
    args = ap.parse_args(argv)
    name = ("low_dose_lengths" if args.scale == "lengths" else "low_dose_alpha") + ("_fresh" if args.fresh else "")
    if args.reference_dose != 1.0:
        if args.fresh or args.scale != "lengths":
            ap.error("--reference-dose scales the committed scenes' lengths only (no --fresh, no --scale)")
        name = "low_dose_reference" + ("" if args.reference_dose == 10 else f"_{args.reference_dose:g}x")
        name += "" if args.nsr_floor == SAMPLE_FLOOR else f"_floor{args.nsr_floor:g}"
        if args.min_photons:
            name = name.replace("low_dose", "high_dose", 1)
    elif args.nsr_floor != DEFAULTS.diffuser_nsr_floor or args.min_photons:
        ap.error("--nsr-floor and --min-photons go with --reference-dose")

    def bases():
        if not args.fresh:
            yield from low_dose_scenes(args.out, args.max_photons, args.min_photons)
            return
        first, count = args.fresh
        for i in range(first, first + count):
            base = fresh_base(i, args.max_photons)
            if base is not None:
                yield base

    def compute() -> list[dict]:
        rows = []
        for base in bases():
            for factor in args.factors:
                rows.append(scaled_row(base, factor, args.scale, args.reference_dose, args.nsr_floor))
                print(f"scene {base['scene']} x{factor:g}: {rows[-1]['phase_error']:.3f}", flush=True)
        return rows

    rows = rows_of(args.out, f"{name}.csv", args.report_only, compute)
    write_report(rows, args.out, device_name(np), command_line("benchmarks.low_dose_lengths", argv), name)
    return rows


if __name__ == "__main__":
    main()
