"""Do PWF's high-dose scenes fail more often, or only the scenes below the sensitivity limit?

Session 103 read, over the 227 calibrated random scenes 0-239 (:mod:`benchmarks.sensitivity_check`),
that the scenes whose reference is cleanest (Wiener NSR below 3e-5, median 2e5 ph/px) held 14
of 29 against 49 of 72 between 3e-5 and 1e-3: high dose looked worse. This separates dose from
what the speckle can carry. For each random geometry it measures the reference's phase
sensitivity S (:func:`pwf_dask.calibration.phase_sensitivity`) once more at a dose where its
noise no longer matters (``--photons``, 1e5 ph/px by default; the geometry, diffuser and sample
are the draw's own, :func:`benchmarks.random_scenes.draw_scene`), beside the S measured at the
scene's own dose and the verdict of every default (both from the committed
``sensitivity_check.csv``; no retrieval runs). The report counts, per decade of dose, the
scenes refused by the calibration, those whose S lies below the warning limit
(:class:`pwf_dask.calibration.SensitivityLimits`, where PWF warns that the data do not carry the
phase), and how many of the rest hold. Where noise puts a scene's own S on the other side of
the limit from its clean S, PWF is run on it twice, with S as read and with S patched to the
clean value (the alpha rule's Im(alpha) follows S, :func:`pwf_dask.pwf.solver.sensitivity_alpha`):
what the misreading costs.

    python -m benchmarks.holds_by_dose [--photons 1e5] [--out benchmarks/results] [--report-only]

Writes ``holds_by_dose.csv``, ``holds_by_dose_misread.csv`` and ``holds_by_dose.md`` (about two
minutes on 2 cores: one simulation per scene, two retrievals per misread one).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from unittest import mock

import numpy as np

from benchmarks.random_scenes import draw_scene, retrieve_scene
from benchmarks.reporting import command_line, read_rows_csv, rows_of
from benchmarks.stability import errors
from pwf_dask.calibration import SensitivityLimits, phase_sensitivity
from pwf_dask.calibration import sensitivity as sensitivity_module
from pwf_dask.physics import optics

#: the decades of dose (ph/px) the report keeps apart: the random draw spans 1e2-1e6
DOSE_BINS = ((1e2, 1e3), (1e3, 1e4), (1e4, 1e5), (1e5, 1e6))


def sensitivity_at_dose(scene: int, photons: float) -> float:
    """S of random geometry ``scene`` with its images simulated at ``photons`` per pixel."""
    _, sim, _ = draw_scene(scene, photons=photons)
    return phase_sensitivity(
        sim.reference, optics.wavelength_m(sim.energy_eV), sim.diffuser_detector_distance_m, sim.pixel_size_m
    )


def scene_rows(committed: list[dict], photons: float) -> list[dict]:
    """One row per committed ``sensitivity_check`` scene: its dose, refusal, verdict, S as it
    was measured and S at ``photons``."""
    return [
        {
            "scene": r["scene"],
            "photons": r["photons"],
            "refused": bool(r["refused"]),
            "holds": r["holds"] is True,
            "phase_sensitivity": r["phase_sensitivity"],
            "phase_sensitivity_clean": sensitivity_at_dose(int(r["scene"]), photons),
            "clean_photons": photons,
        }
        for r in committed
    ]


def _below(s, limit: float) -> bool:
    return isinstance(s, float) and np.isfinite(s) and s < limit


def dose_table(rows: list[dict], limit: float) -> list[str]:
    """The report's table: per decade of dose, scenes, refused, below the limit (S at the
    clean dose; at the scene's own), and holds among the scenes above it, and among all."""
    lines = [
        "| dose (ph/px) | scenes | refused | below the limit (clean S / own S) | hold above it | hold, all retrieved |",
        "|---|---:|---:|---|---:|---:|",
    ]
    for lo, hi in DOSE_BINS:
        rs = [r for r in rows if lo <= r["photons"] < hi]
        run = [r for r in rs if not r["refused"]]
        above = [r for r in run if not _below(r["phase_sensitivity_clean"], limit)]
        lines.append(
            f"| {lo:.0e}-{hi:.0e} | {len(rs)} | {sum(r['refused'] for r in rs)} "
            f"| {sum(_below(r['phase_sensitivity_clean'], limit) for r in rs)} / "
            f"{sum(_below(r['phase_sensitivity'], limit) for r in run)} "
            f"| {sum(r['holds'] for r in above)} of {len(above)} | {sum(r['holds'] for r in run)} of {len(run)} |"
        )
    return lines


def misread_scenes(rows: list[dict], limit: float) -> list[int]:
    """Retrieved scenes whose S at their own dose clears the limit while the clean S does not
    (the warning missed through noise), or the other way round."""
    return [
        r["scene"]
        for r in rows
        if not r["refused"] and _below(r["phase_sensitivity"], limit) != _below(r["phase_sensitivity_clean"], limit)
    ]


def misread_rows(rows: list[dict], limit: float) -> list[dict]:
    """PWF with every default on each :func:`misread_scenes` scene, with its S as read and with
    S patched to the clean value (so Im(alpha) and the warning follow the clean S)."""
    clean = {r["scene"]: r["phase_sensitivity_clean"] for r in rows}
    out = []
    for scene in misread_scenes(rows, limit):
        setup, sim, background = draw_scene(scene)
        for label, patch in (("as read", None), ("clean", clean[scene])):
            if patch is None:
                res = retrieve_scene(setup, sim, background)
            else:
                with mock.patch.object(sensitivity_module, "phase_sensitivity", lambda *a, s=patch, **k: s):
                    res = retrieve_scene(setup, sim, background)
            err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
            out.append(
                {
                    "scene": scene,
                    "photons": setup.photons,
                    "S": label,
                    "phase_sensitivity": res.parameters["phase_sensitivity"],
                    "alpha_imag": complex(res.parameters["alpha"]).imag,
                    "phase_error": err["phase_error"],
                    "phase_gain": err["phase_gain"],
                }
            )
    return out


def misread_table(rows: list[dict]) -> list[str]:
    lines = [
        "| scene | ph/px | S as read | Im(alpha) | phase error, gain | S clean | Im(alpha) | phase error, gain |",
        "|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    for read, clean in zip(rows[::2], rows[1::2]):
        lines.append(
            f"| {read['scene']} | {read['photons']:.0f} | {read['phase_sensitivity']:.2g} | {read['alpha_imag']:.2g} "
            f"| {read['phase_error']:.3f}, {read['phase_gain']:.2f} | {clean['phase_sensitivity']:.2g} "
            f"| {clean['alpha_imag']:.2g} | {clean['phase_error']:.3f}, {clean['phase_gain']:.2f} |"
        )
    return lines


def write_report(rows: list[dict], misread: list[dict], out_dir: str | Path, command: str) -> None:
    limit = SensitivityLimits().min_phase_sensitivity
    below = [r for r in rows if not r["refused"] and _below(r["phase_sensitivity_clean"], limit)]
    lines = [
        "# Holds by dose, with the sensitivity limit apart",
        "",
        f"`{command}`: the random geometries 0-239 of `sensitivity_check.csv` (every default,",
        "lengths calibrated; a scene holds below a relative phase error of 0.25 inside the sample),",
        f"their reference's phase sensitivity S measured again at {rows[0]['clean_photons']:.0e} ph/px",
        f"(the draw's geometry, diffuser and sample). PWF warns below S = {limit:g}.",
        "",
        *dose_table(rows, limit),
        "",
        f"- Retrieved scenes below the limit by their clean S: {len(below)}, of which "
        f"{sum(r['holds'] for r in below)} hold.",
        f"- Scenes whose own-dose S and clean S fall on different sides of the limit: "
        f"{', '.join(map(str, misread_scenes(rows, limit))) or 'none'}; PWF on each with S as read",
        "and with S patched to the clean value (Im(alpha) follows it; where S reads none, the rule",
        "takes its noise bound from 1e-4 up, solver.rule_sensitivity, session 106):",
        "",
        *misread_table(misread),
    ]
    (Path(out_dir) / "holds_by_dose.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=float, default=1e5, help="the dose S is measured again at (ph/px)")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from holds_by_dose.csv")
    args = ap.parse_args(argv)
    committed = read_rows_csv(args.out, "sensitivity_check.csv")
    rows = rows_of(args.out, "holds_by_dose.csv", args.report_only, lambda: scene_rows(committed, args.photons))
    limit = SensitivityLimits().min_phase_sensitivity
    misread = rows_of(args.out, "holds_by_dose_misread.csv", args.report_only, lambda: misread_rows(rows, limit))
    write_report(rows, misread, args.out, command_line("benchmarks.holds_by_dose", argv))
    return rows


if __name__ == "__main__":
    main()
