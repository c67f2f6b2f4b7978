"""Does PWF's own warning find the scenes whose data do not carry the phase?

Every PWF retrieval measures what its speckle could carry (:mod:`pwf_dask.calibration.sensitivity`):
the 99th percentile of the retrieved phase's speckle shift lambda L2 |grad phi| / 2 pi p over
the reference's speckle grain, and the reference's visibility with photon noise removed, and
warns below :class:`pwf_dask.calibration.SensitivityLimits`. A user has nothing else to tell a
faint, low result from a faint sample. This runs PWF with every default (lengths calibrated)
on the random geometries of :mod:`benchmarks.random_scenes` in three sets:

- scenes 0-79, those of ``random_scenes.md``, where any shift limit of 0.015-0.04 flags no
  holding scene;
- scenes 80-119, drawn from the same ranges and looked at while choosing;
- scenes 120-159, never looked at before this benchmark ran: the held-out check of session 84;
- scenes 160-239, session 102's held-out set: drawn from the same ranges and run once, after the
  phase-sensitivity limit, the alpha rule, its model probe and session 101's way out had been
  chosen on scenes 0-159 (``--add-scenes`` ran them beside the rows already committed);
- the paper's optics (its 256^2 scene, P3000) at 16-30 keV on two diffuser draws, where the
  speckle fades and the phase shrinks together: the family that set the shift limit at 0.02
  (one draw holds at 0.022-0.028 from 21 to 23 keV), and from 26 keV (session 92) the check of
  the phase-sensitivity limit (28 keV still holds at S = 4.8e-5);
- the stability map's scene axes (:mod:`benchmarks.stability`, the paper's scene varied one axis
  at a time), PWF with its lengths calibrated as in the map's column of that name: its failures
  there are of the other kind (steep phase, coarse pixels, strong absorption, a short L2), which
  the shift and visibility limits are not meant to flag; the fit's misfit in the sample over
  its background's (session 84) flags those whose model does not reach the sample's data.

A scene holds where its relative phase error inside the sample stays below 0.25 (as in
``random_scenes``). Reported per set: how many hold and fail, how many of each the warning
flags, and the flagged and unflagged failures' gains.

    python -m benchmarks.sensitivity_check [--scenes 240] [--out benchmarks/results]
                                           [--only-stability | --add-scenes | --rerun SCENE ...]

Writes ``sensitivity_check.md``, ``.csv``, ``.png``, ``sensitivity_check_energies.csv`` and
``sensitivity_check_stability.csv`` (about 33 min for scenes 0-159 and the sweep on 2 cores, about
17 more for 160-239, 23 more for the map's 44 points; ``--only-stability`` runs those alone and
reads the rest back; ``--add-scenes`` runs only the scenes missing from the rows in ``--out``;
``--rerun`` runs the scenes named again and keeps every other row).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from benchmarks.random_scenes import add_rerun_argument, rows_kept_but, run_and_report
from benchmarks.reporting import device_name, read_rows_csv, write_rows_csv
from benchmarks.stability import AXES, PHASE_ERROR_THRESHOLD, PWF_ONLY_AXES, errors, sensitivity_columns, stability_map
from pwf_dask.calibration import SensitivityLimits
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

#: (first scene, end, name) of the sets the report keeps apart
SETS = (
    (0, 80, "0-79 (limits set here)"),
    (80, 120, "80-119 (seen while choosing)"),
    (120, 160, "120-159 (held out)"),
    (160, 240, "160-239 (held out, session 102)"),
)


#: energies (keV) and draws of the paper-optics sweep
ENERGIES_KEV = (16.0, 18.0, 20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0, 27.0, 28.0, 30.0)
ENERGY_SEEDS = (1, 2)


def energy_row(energy_keV: float, seed: int) -> dict:
    """The paper's 256^2 scene at ``energy_keV`` (draw ``seed``) retrieved with every default:
    its phase error and gain and what the check measured."""
    sim = simulate_projection(replace(SpeckleSetup(shape=(256, 256)), energy_eV=1e3 * energy_keV), seed=seed)
    background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
    res = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), background_mask=background)
    err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
    return {
        "energy_keV": energy_keV,
        "seed": seed,
        "phase_error": err["phase_error"],
        "phase_gain": err["phase_gain"],
        "holds": bool(err["phase_error"] < PHASE_ERROR_THRESHOLD),
        **sensitivity_columns(res.parameters),
    }


def energy_lines(rows: list[dict]) -> list[str]:
    """The paper-optics sweep as a table: one row per energy, the draws side by side."""
    lines = [
        "",
        "The paper's optics (256^2, P3000, 1e4 ph/px, L1 3 mm, L2 20 mm) at other energies, two diffuser draws",
        "(phase error / gain, shift / grain; `*` flagged):",
        "",
        "| keV | visibility | S | " + " | ".join(f"draw {s}" for s in ENERGY_SEEDS) + " |",
        "|---:|---:|---:|" + "---|" * len(ENERGY_SEEDS),
    ]
    for e in dict.fromkeys(r["energy_keV"] for r in rows):
        rs = [r for r in rows if r["energy_keV"] == e]
        cells = [
            f"{r['phase_error']:.3f} / {r['phase_gain']:.2f}, {r['speckle_shift_over_grain']:.4f}"
            + (" *" if r["flagged"] else "")
            for r in rs
        ]
        head = f"| {e:g} | {rs[0]['speckle_visibility_measured']:.3f} | {_sensitivity(rs[0])} | "
        lines.append(head + " | ".join(cells) + " |")
    return lines


#: the stability map's run that the check is read on: PWF as a user runs it, lengths calibrated
STABILITY_RUN = ("PWF K=1 calibrated", "pwf", 1, dict(max_iter=500, coherence_method="template"))


def stability_rows() -> list[dict]:
    """PWF, lengths calibrated, at every point of the stability map's scene axes (``pwf-dask
    bench stability``; not its PWF-only axes, whose points hand PWF wrong lengths or take its
    parts away): the map's error and what the check measured."""
    axes = {a: v for a, v in AXES.items() if a not in PWF_ONLY_AXES}
    return stability_map(axes=axes, methods=[STABILITY_RUN])


def stability_lines(rows: list[dict]) -> list[str]:
    """The stability map's points as a table, failures and flags named."""
    fails = [r for r in rows if not r["holds"]]
    flagged_fails = sum(r["flagged"] for r in fails)
    flagged_holds = sum(r["flagged"] for r in rows if r["holds"])
    lines = [
        "",
        "The stability map's scene axes (`pwf-dask bench stability`: the paper's 256^2 scene varied one axis",
        f"at a time), PWF with its lengths calibrated: {len(fails)} of {len(rows)} points fail, the warning flags "
        f"{flagged_fails} of them and {flagged_holds} holding points:",
        "",
        "| axis | value | phase error | gain | shift / grain | visibility | sample misfit | flagged | holds |",
        "|---|---|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['axis']} | {r['value']} | {r['phase_error']:.3f} | {r['phase_gain']:.2f} "
            f"| {r['speckle_shift_over_grain']:.4f} | {r['speckle_visibility_measured']:.3f} "
            f"| {_misfit(r)} | {'yes' if r['flagged'] else ''} | {'yes' if r['holds'] else ''} |"
        )
    return lines


def _misfit(row: dict) -> str:
    """The row's sample misfit, blank where it was not measured (rows written before session 84)."""
    value = float(row.get("sample_misfit", np.nan))
    return f"{value:.2f}" if np.isfinite(value) else ""


def _sensitivity(row: dict) -> str:
    """The row's phase sensitivity S, blank where it was not recorded (rows written before session 92)."""
    value = float(row.get("phase_sensitivity", np.nan))
    return f"{value:.1e}" if np.isfinite(value) else ""


def _set_name(scene: int) -> str:
    for lo, hi, name in SETS:
        if lo <= scene < hi:
            return name
    return f"{SETS[-1][1]}+ (held out)"


def _median(values) -> str:
    values = [v for v in values if np.isfinite(v)]
    return f"{np.median(values):.2f}" if values else "-"


def summary_rows(rows: list[dict]) -> list[dict]:
    """Per set: scenes retrieved, holding, failing, and what the warning flagged of each."""
    out = []
    for name in dict.fromkeys(_set_name(r["scene"]) for r in rows):
        rs = [r for r in rows if _set_name(r["scene"]) == name and not r["refused"]]
        holds = [r for r in rs if r["holds"]]
        fails = [r for r in rs if not r["holds"]]
        flagged_fails = [r for r in fails if r["flagged"]]
        out.append(
            {
                "set": name,
                "retrieved": len(rs),
                "refused": sum(1 for r in rows if _set_name(r["scene"]) == name and r["refused"]),
                "holds": len(holds),
                "flagged_holds": sum(r["flagged"] for r in holds),
                "fails": len(fails),
                "flagged_fails": len(flagged_fails),
                "gain_flagged": _median(r["phase_gain"] for r in flagged_fails),
                "gain_unflagged_fails": _median(r["phase_gain"] for r in fails if not r["flagged"]),
                "nearest_hold": min((r["speckle_shift_over_grain"] for r in holds), default=np.nan),
            }
        )
    return out


def write_report(
    rows: list[dict],
    out_dir: str | Path,
    device: str,
    energies: list[dict] | None = None,
    stability: list[dict] | None = None,
) -> None:
    limits = SensitivityLimits()
    lines = [
        f"# PWF's sensitivity warning on {len(rows)} random geometries ({device})",
        "",
        "`python -m benchmarks.sensitivity_check`: PWF with every default (coherence lengths calibrated) on the",
        "random geometries of `benchmarks.random_scenes` (one projection each; module docstring: the ranges).",
        "The warning (`RetrievalResult.parameters['sensitivity_warning']`, a run's one-line summary) fires where",
        f"the retrieved phase moves the speckle by under {limits.min_shift_over_grain:g} of its grain (99th",
        f"percentile), the reference's visibility, photon noise removed, is under {limits.min_visibility:g}, or its",
        f"phase sensitivity S (`calibration.phase_sensitivity`, session 92) is under {limits.min_phase_sensitivity:g}.",
        f"A scene holds below a relative phase error of {PHASE_ERROR_THRESHOLD:g} inside the sample.",
        "",
        "| scenes | retrieved | holds | flagged of them | fails | flagged of them | gain, flagged fails "
        "| gain, unflagged fails | smallest shift / grain that holds | calibration refused |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary_rows(rows):
        lines.append(
            f"| {s['set']} | {s['retrieved']} | {s['holds']} | {s['flagged_holds']} | {s['fails']} "
            f"| {s['flagged_fails']} | {s['gain_flagged']} | {s['gain_unflagged_fails']} | {s['nearest_hold']:.3f} "
            f"| {s['refused']} |"
        )
    lines += energy_lines(energies) if energies else []
    lines += stability_lines(stability) if stability else []
    lines += [
        "",
        "Every random scene (phase error / gain; shift / grain and visibility as the retrieval measured them):",
        "",
        "| scene | phase error | gain | shift / grain | visibility | S | sample misfit | flagged | holds |",
        "|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        if r["refused"]:
            lines.append(f"| {r['scene']} | refused | | | | | | | |")
            continue
        lines.append(
            f"| {r['scene']} | {r['phase_error']:.3f} | {r['phase_gain']:.2f} | {r['speckle_shift_over_grain']:.4f} "
            f"| {r['speckle_visibility_measured']:.3f} | {_sensitivity(r)} | {_misfit(r)} "
            f"| {'yes' if r['flagged'] else ''} | {'yes' if r['holds'] else ''} |"
        )
    Path(out_dir, "sensitivity_check.md").write_text("\n".join(lines) + "\n")


def plot(rows: list[dict], path: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    limits = SensitivityLimits()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (lo, hi, name), marker in zip(SETS, "o^sD"):
        pts = [r for r in rows if lo <= r["scene"] < hi and not r["refused"]]
        ax.scatter(
            [max(r["speckle_shift_over_grain"], 1e-4) for r in pts],
            [min(r["phase_error"], 3.0) for r in pts],
            marker=marker,
            c=["C3" if r["flagged"] else "C0" for r in pts],
            label=name,
            alpha=0.8,
        )
    ax.axhline(PHASE_ERROR_THRESHOLD, color="grey", lw=0.8, ls="--")
    ax.axvline(limits.min_shift_over_grain, color="C3", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("retrieved phase's speckle shift / speckle grain (99th percentile)")
    ax.set_ylabel("relative phase error in the sample (capped at 3)")
    ax.set_title("PWF's warning (red: flagged) against the truth")
    legend = ax.legend()
    for handle in legend.legend_handles:  # the marker names the set, the colour the flag
        handle.set_color("grey")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def random_scenes_pwf_rows(out_dir: str | Path) -> list[dict]:
    """PWF's rows of the held-out sets ``random_scenes --first N`` wrote to ``out_dir``
    (``random_scenes_N-M.csv``): the same ``scene_row`` with every default that this check runs."""
    rows = []
    for path in sorted(Path(out_dir).glob("random_scenes_*-*.csv")):
        rows += [r for r in read_rows_csv(out_dir, path.name) if r["method"] == "pwf"]
    return rows


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=SETS[-1][1])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument(
        "--only-stability",
        action="store_true",
        help="re-run only the stability map's points; the random scenes and the energy sweep are read back from --out",
    )
    ap.add_argument(
        "--add-scenes",
        action="store_true",
        help="run only the random scenes below --scenes that --out's rows lack (PWF's rows of a random_scenes_N-M.csv "
        "there count: the same run); the rest is read back from --out",
    )
    add_rerun_argument(ap)
    args = ap.parse_args(argv)
    if args.rerun:
        energies = read_rows_csv(args.out, "sensitivity_check_energies.csv")
        stability = read_rows_csv(args.out, "sensitivity_check_stability.csv")
        kept = rows_kept_but(args.out, "sensitivity_check.csv", args.rerun)
        report = partial(write_report, energies=energies, stability=stability)
        return run_and_report(range(args.scenes), ("pwf",), args.out, "sensitivity_check", report, plot, kept)
    if args.add_scenes:
        energies = read_rows_csv(args.out, "sensitivity_check_energies.csv")
        stability = read_rows_csv(args.out, "sensitivity_check_stability.csv")
        kept = read_rows_csv(args.out, "sensitivity_check.csv") + random_scenes_pwf_rows(args.out)
        report = partial(write_report, energies=energies, stability=stability)
        return run_and_report(range(args.scenes), ("pwf",), args.out, "sensitivity_check", report, plot, kept)
    stability = stability_rows()
    write_rows_csv(args.out, "sensitivity_check_stability.csv", stability)
    if args.only_stability:
        rows = read_rows_csv(args.out, "sensitivity_check.csv")
        energies = read_rows_csv(args.out, "sensitivity_check_energies.csv")
        write_report(rows, args.out, device_name(np), energies, stability)
        return rows
    energies = [energy_row(e, seed) for e in ENERGIES_KEV for seed in ENERGY_SEEDS]
    write_rows_csv(args.out, "sensitivity_check_energies.csv", energies)
    report = partial(write_report, energies=energies, stability=stability)
    return run_and_report(range(args.scenes), ("pwf",), args.out, "sensitivity_check", report, plot)


if __name__ == "__main__":
    main()
