"""Strongly absorbing samples on the random geometries: Re(alpha) against the sample's absorption.

The random geometries' sample is a cellulose rod with glass beads, a weak absorber at 8-30 keV
(its attenuation spans at most 0.66 of amplitude, 8 keV). Beamline samples absorb far more (bone,
metals, dense minerals at low energy), and the stability map's 10x absorption point failed
(docs/validation.md). Each random geometry of ``sensitivity_check.csv`` that holds at its own
absorption (a calibration that did not refuse, S at or above the warning's limit) is simulated
again with its sample's beta scaled so that the true attenuation spans each ``--ranges`` R
(amplitude: the intensity then falls to e^-2R at the darkest pixel), its phase, diffuser and
reference as drawn, and retrieved by

- PWF with every default (``alpha="sensitivity"``: Re(alpha) lowered where the sample's
  attenuation contrast exceeds :data:`pwf_dask.pwf.solver.TUNED_ATTENUATION_CONTRAST`);
- PWF with Re(alpha) as before session 105 (the paper's 0.1 whatever the absorption: the rule
  given an infinite ``tuned_contrast``);
- UMPA with the one image (K = 1), which fits a transmission per window.

PWF gets the committed row's calibrated coherence lengths (the reference is the same, so a
calibration would read them again).

    python -m benchmarks.absorbing_samples [--ranges 1 2] [--first 0] [--last 159] [--count 24]
                                           [--report-only] [--out benchmarks/results]

Takes the first ``--count`` such scenes from ``--first`` to ``--last``; writes
``absorbing_samples_<first>-<last>.md`` and ``.csv`` (about 12 min for 24 scenes on 2 cores).
"""

from __future__ import annotations

import argparse
from functools import lru_cache, partial
from pathlib import Path
from unittest import mock

import numpy as np

from benchmarks.random_scenes import DRAW_SEED, draw_setup, retrieve_scene
from benchmarks.reporting import command_line, device_name, read_rows_csv, rows_of, write_rows_csv
from benchmarks.stability import PHASE_ERROR_THRESHOLD, errors
from pwf_dask.calibration import SensitivityLimits
from pwf_dask.physics.materials import delta_beta
from pwf_dask.pwf import solver
from pwf_dask.simulation import Phantom, SpeckleSimulator, Sphere, default_phantom

#: the default phantom's materials: the rod's and the beads'
PHANTOM_MATERIALS = (Phantom.cylinder_material, Sphere.material)

METHODS = ("pwf", "pwf_fixed_re", "umpa")
#: the elements whose beta / delta bounds a real sample's at an energy: every one to uranium
ELEMENTS = range(1, 93)


@lru_cache(maxsize=512)
def largest_beta_over_delta(energy_keV: float) -> float:
    """The largest beta / delta of any element at ``energy_keV`` (xraydb; a ratio the density
    does not change): 0.20 at 10 keV (the rare earths above their L edges), 0.12 at 22, 0.07 at 30."""
    import xraydb

    ratios = (xraydb.xray_delta_beta(xraydb.atomic_symbol(z), 1.0, energy_keV * 1e3) for z in ELEMENTS)
    return float(max(b / d for d, b, _ in ratios))


def sample_beta_over_delta(energy_keV: float, beta_factor: float) -> float:
    """The scaled sample's largest beta / delta: the rod's or the beads', beta times the factor."""
    return beta_factor * max(b / d for d, b in (delta_beta(m, energy_keV * 1e3) for m in PHANTOM_MATERIALS))


def physical(row: dict) -> bool:
    """Whether a row's scaled sample absorbs no more for its phase than the most absorbing
    element does at its energy (:func:`largest_beta_over_delta`): beyond, no material is that
    dark for so little phase."""
    return sample_beta_over_delta(row["energy_keV"], row["beta_factor"]) <= largest_beta_over_delta(row["energy_keV"])


def holding_scenes(out_dir: str, first: int, last: int, count: int) -> list[dict]:
    """The first ``count`` committed PWF rows from scene ``first`` to ``last`` that hold, with
    a calibration that did not refuse and S at or above the warning's limit."""
    limit = SensitivityLimits().min_phase_sensitivity
    rows = [
        r
        for r in read_rows_csv(out_dir, "sensitivity_check.csv")
        if first <= r["scene"] <= last
        and not r["refused"]
        and r["phase_sensitivity"] >= limit
        and r["phase_error"] < PHASE_ERROR_THRESHOLD
    ]
    return sorted(rows, key=lambda r: r["scene"])[:count]


def absorbing_scene(i: int, attenuation_range: float):
    """Scene ``i`` (:func:`benchmarks.random_scenes.draw_scene`) with its sample's beta scaled so
    that the true attenuation spans ``attenuation_range``: (setup, sample, reference, phase,
    attenuation, background, the beta factor). The noise is drawn in the order
    ``simulate_projection`` draws it, so the factor 1 gives the committed scene's images."""
    setup = draw_setup(np.random.default_rng(DRAW_SEED + i))
    sim = SpeckleSimulator(setup, seed=i)
    fov = setup.shape[1] * setup.pixel_size_m
    phantom = default_phantom(fov, np.random.default_rng(i + 1), height_m=setup.shape[0] * setup.pixel_size_m)
    _, psi = sim.sample_field(phantom)
    attenuation = sim._bin(-psi.real)
    factor = attenuation_range / float(attenuation.max() - attenuation.min())
    psi = factor * psi.real + 1j * psi.imag
    sample = sim.noisy(sim.intensity(np.exp(psi), sim.diffuser()))
    reference = sim.reference()
    phase = sim._bin(psi.imag)
    background = np.abs(phase) < 1e-3 * np.abs(phase).max()
    return setup, sample, reference, phase, sim._bin(-psi.real), background, factor


class _Scene:
    """What :func:`benchmarks.random_scenes.retrieve_scene` reads of a simulated projection."""

    def __init__(self, sample, reference, setup):
        self.sample, self.reference, self._setup = sample, reference, setup

    def geometry(self) -> dict:
        return self._setup.geometry()


def scene_rows(base: dict, attenuation_range: float, methods: tuple[str, ...] = METHODS) -> list[dict]:
    """One row per method on ``base``'s scene with its attenuation spanning ``attenuation_range``."""
    i = int(base["scene"])
    setup, sample, reference, phase, attenuation, background, factor = absorbing_scene(i, attenuation_range)
    scene = _Scene(sample, reference, setup)
    lengths = {
        "coherence_length_x_m": base["coherence_x_um_used"] * 1e-6,
        "coherence_length_y_m": base["coherence_y_um_used"] * 1e-6,
    }
    rows = []
    for method in methods:
        if method == "pwf_fixed_re":
            # the rule as it was: Re(alpha) never lowered
            rule = partial(solver.sensitivity_alpha, tuned_contrast=np.inf)
            with mock.patch.object(solver, "sensitivity_alpha", rule):
                res = retrieve_scene(setup, scene, background, "pwf", **lengths)
        else:
            res = retrieve_scene(setup, scene, background, method, **({} if method == "umpa" else lengths))
        err = errors(res.phase, res.attenuation, phase, attenuation, background)
        alpha = complex(res.parameters.get("alpha", np.nan))
        rows.append(
            {
                "scene": i,
                "photons": setup.photons,
                "energy_keV": setup.energy_eV / 1e3,
                "attenuation_range": attenuation_range,
                "beta_factor": factor,
                "method": method,
                "attenuation_contrast": res.parameters.get("attenuation_contrast", np.nan),
                "alpha_real": alpha.real,
                "phase_error": err["phase_error"],
                "attenuation_error": err["attenuation_error"],
                "phase_gain": err["phase_gain"],
                "sample_misfit": res.parameters.get("sample_misfit", np.nan),
                "iterations": int(res.iterations),
                "base_error": base["phase_error"],
            }
        )
    return rows


def rerun_default(row: dict, bases: dict[int, dict]) -> dict:
    """``row`` as it was where its method is not ``pwf``; else PWF's row run again on its scene
    (``bases``: the committed rows by scene) after a change of a default, such as
    :data:`pwf_dask.pwf.solver.TUNED_ATTENUATION_CONTRAST`."""
    if row["method"] != "pwf":
        return row
    new = scene_rows(bases[row["scene"]], row["attenuation_range"], methods=("pwf",))[0]
    print(f"scene {row['scene']} range {row['attenuation_range']:g}: pwf {new['phase_error']:.3f}", flush=True)
    return new


def summary_lines(rows: list[dict]) -> list[str]:
    """Per range and method, over the scenes whose scaled sample is :func:`physical`: holds,
    gained / lost against PWF as before, median errors."""
    rows = [r for r in rows if physical(r)]
    lines = [
        "| attenuation range | method | scenes | holds | gained / lost vs Re(alpha) 0.1 | median phase error "
        "| median attenuation error | flagged by misfit |",
        "|---:|---|---:|---:|---|---:|---:|---:|",
    ]
    limit = SensitivityLimits().max_sample_misfit
    for rng_ in dict.fromkeys(r["attenuation_range"] for r in rows):
        before = {r["scene"]: r for r in rows if r["attenuation_range"] == rng_ and r["method"] == "pwf_fixed_re"}
        for method in METHODS:
            rs = [r for r in rows if r["attenuation_range"] == rng_ and r["method"] == method]
            holds = np.array([r["phase_error"] < PHASE_ERROR_THRESHOLD for r in rs])
            held = np.array([before[r["scene"]]["phase_error"] < PHASE_ERROR_THRESHOLD for r in rs])
            versus = "" if method == "pwf_fixed_re" else f"{np.sum(holds & ~held)} / {np.sum(held & ~holds)}"
            flagged = "" if method == "umpa" else str(sum(r["sample_misfit"] > limit for r in rs))
            lines.append(
                f"| {rng_:g} | {method} | {len(rs)} | {holds.sum()} | {versus} "
                f"| {np.median([r['phase_error'] for r in rs]):.3f} "
                f"| {np.median([r['attenuation_error'] for r in rs]):.3f} | {flagged} |"
            )
    return lines


def _ratio_cell(row: dict) -> str:
    ratio = f"{sample_beta_over_delta(row['energy_keV'], row['beta_factor']):.3f}"
    return ratio if physical(row) else f"**{ratio}**"


def write_report(rows: list[dict], out_dir: str, device: str, command: str, name: str) -> None:
    lines = [
        f"# Strongly absorbing samples on the random geometries ({device})",
        "",
        f"`{command}`: the random geometries that hold at their own absorption, their sample's beta",
        "scaled so that the true attenuation spans the range given (amplitude; module docstring).",
        f"A scene holds below a relative phase error of {PHASE_ERROR_THRESHOLD:g} inside the sample.",
        "`pwf`: every default (Re(alpha) lowered above the attenuation contrast "
        f"{solver.TUNED_ATTENUATION_CONTRAST:g}); `pwf_fixed_re`: Re(alpha) 0.1 as before; "
        "`umpa`: UMPA K = 1.",
        "",
        *summary_lines(rows),
        "",
        "The summary counts the scenes whose scaled sample absorbs no more for its phase than the most",
        "absorbing element at its energy (beta / delta at most its: 0.20 at 10 keV, 0.12 at 22, 0.07 at",
        "30); the table lists every scene, those beyond with their beta / delta in bold.",
        "",
        "| scene | keV | ph/px | range | beta / delta | contrast | own error | method | Re(alpha) | phase error "
        "| attenuation error | gain | misfit |",
        "|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    lines += [_table_row(r) for r in sorted(rows, key=lambda r: (r["scene"], r["attenuation_range"]))]
    Path(out_dir, f"{name}.md").write_text("\n".join(lines) + "\n")


def _table_row(r: dict) -> str:
    return (
        f"| {r['scene']} | {r['energy_keV']:.1f} | {r['photons']:.0f} | {r['attenuation_range']:g} "
        f"| {_ratio_cell(r)} | {r['attenuation_contrast']:.2f} | {r['base_error']:.3f} | {r['method']} "
        f"| {r['alpha_real']:.3g} | {r['phase_error']:.3f} | {r['attenuation_error']:.3f} "
        f"| {r['phase_gain']:.2f} | {r['sample_misfit']:.2f} |"
    )


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ranges", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--last", type=int, default=159)
    ap.add_argument("--count", type=int, default=24)
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from the committed csv")
    ap.add_argument(
        "--rerun-default",
        action="store_true",
        help="run the committed csv's pwf rows again (every default; the other methods do not change with it)",
    )
    args = ap.parse_args(argv)
    if min(args.ranges) <= 0 or args.count < 1 or args.last < args.first:
        ap.error("--ranges must be > 0, --count >= 1 and --last >= --first")
    name = f"absorbing_samples_{args.first}-{args.last}"

    def compute() -> list[dict]:
        rows = []
        for base in holding_scenes(args.out, args.first, args.last, args.count):
            for attenuation_range in args.ranges:
                rows += scene_rows(base, attenuation_range)
                got = ", ".join(f"{r['method']} {r['phase_error']:.3f}" for r in rows[-len(METHODS) :])
                print(f"scene {base['scene']} range {attenuation_range:g}: {got}", flush=True)
        return rows

    if args.rerun_default:
        bases = {r["scene"]: r for r in holding_scenes(args.out, args.first, args.last, args.count)}
        rows = [rerun_default(r, bases) for r in read_rows_csv(args.out, f"{name}.csv")]
        write_rows_csv(args.out, f"{name}.csv", rows)
    else:
        rows = rows_of(args.out, f"{name}.csv", args.report_only, compute)
    write_report(rows, args.out, device_name(np), command_line("benchmarks.absorbing_samples", argv), name)
    return rows


if __name__ == "__main__":
    main()
