"""PWF and UMPA on random beamline geometries: where each holds, over parameters a user cannot choose.

The stability map and the geometry sweep move one parameter at a time from the paper's scene.
Here every parameter is drawn at once, independently, over the ranges beamlines span
(docs/validation.md, "Random geometries"): frames of 64-259 px per side (not square), 8-30 keV,
0.3-3 µm pixels, L1 = 0 or 0.5-10 mm (a quarter of the scenes with the diffuser 1-20 mm
*upstream*, its distance given), L2 5-200 mm, coherence lengths 1-8 µm per axis, 1e2-1e6
ph/px, sandpaper grains of 0.8-6 µm median radius (round, faceted or mixed), the default
cellulose rod with glass beads. Each scene is one projection with its reference; methods get
the contract's entry point, ``retrieve_projection``:

- PWF with its defaults, the coherence lengths calibrated from the reference (as a user gets them);
- PWF given the true lengths (what the calibration costs);
- UMPA with the one image (K = 1, the single-shot baseline; no lengths needed).

Reported: relative phase error inside the sample and phase gain (background zeroed on the true
sample-free pixels), iterations, the calibration's refusal where it refuses; and the scene's
own numbers that decide it: the 99th percentile of the speckle displacement the sample causes
(lambda L2 |grad phi| / 2 pi p, pixels), the speckle grain (FWHM of the reference's
autocorrelation, pixels) and the reference's visibility (rms / mean); and for PWF what its own
check of the data measured (``speckle_shift_over_grain`` of the retrieved phase,
``speckle_visibility_measured``, ``sample_misfit``, ``flagged``: benchmarks/sensitivity_check.py).

    python -m benchmarks.random_scenes [--scenes 80] [--first 0] [--discrepancy] [--rerun SCENE ...]
                                       [--out benchmarks/results]

``--first N`` runs scenes N to N + scenes - 1, drawn from the same ranges, and names its files
``random_scenes_<N>-<last>``: scenes 160-239 are session 102's held-out set, run once after
every choice they check had been made (docs/validation.md, "A fresh held-out set").
``--discrepancy`` adds PWF with ``alpha="discrepancy"`` and a line comparing it with the
default alpha (2.3x PWF's time). ``--rerun`` runs the scenes named again (every method) and
keeps the set's other rows: after a change that binds on those scenes alone (session 106: the
alpha rule's noise bound, scenes 53 and 237).

Writes ``random_scenes.md``, ``.csv`` and ``.png`` (about 18 min for 80 scenes on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, read_rows_csv, write_rows_csv
from benchmarks.stability import PHASE_ERROR_THRESHOLD, displacement_px, errors, sensitivity_columns, speckle_grain_px
from pwf_dask.physics import optics
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

#: scene i draws its parameters from default_rng(DRAW_SEED + i) and simulates with seed i
DRAW_SEED = 1000
METHODS = ("pwf", "pwf_true_lengths", "umpa")
#: with ``--discrepancy``: PWF with Im(alpha) chosen by the discrepancy principle as well
DISCREPANCY = "pwf_discrepancy"


def draw_setup(rng: np.random.Generator) -> SpeckleSetup:
    """One random set-up (module docstring: the ranges)."""
    upstream = rng.random() < 0.25
    l1 = 0.0 if upstream else float(rng.choice([0.0, rng.uniform(0.5e-3, 10e-3)]))
    return SpeckleSetup(
        shape=(int(rng.integers(64, 260)), int(rng.integers(64, 260))),
        energy_eV=float(rng.uniform(8e3, 30e3)),
        pixel_size_m=float(10 ** rng.uniform(np.log10(0.3e-6), np.log10(3e-6))),
        sample_diffuser_distance_m=l1,
        diffuser_detector_distance_m=float(10 ** rng.uniform(np.log10(5e-3), np.log10(200e-3))),
        coherence_length_x_m=float(rng.uniform(1e-6, 8e-6)),
        coherence_length_y_m=float(rng.uniform(1e-6, 8e-6)),
        photons=float(10 ** rng.uniform(2, 6)),
        diffuser_radius_median_m=float(rng.uniform(0.8e-6, 6e-6)),
        diffuser_grain_shape=str(rng.choice(["spheres", "faceted", "mixed"])),
        diffuser_upstream_m=float(rng.uniform(1e-3, 20e-3)) if upstream else 0.0,
    )


def _method_options(method: str, setup: SpeckleSetup) -> dict:
    opts: dict = {"diffuser_upstream_m": setup.diffuser_upstream_m} if setup.diffuser_upstream_m else {}
    if method == DISCREPANCY:
        opts["alpha"] = "discrepancy"
    if method == "pwf_true_lengths":
        opts.update(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    if method == "umpa":
        opts = {"method": "umpa"}
    return opts


def draw_scene(i: int, photons: float | None = None):
    """Scene ``i``: its set-up, its simulated projection and the true sample-free pixels;
    ``photons``: its dose instead of the drawn one (the rest of the draw as it was)."""
    setup = draw_setup(np.random.default_rng(DRAW_SEED + i))
    if photons is not None:
        setup = replace(setup, photons=photons)
    sim = simulate_projection(setup, seed=i)
    return setup, sim, np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()


def retrieve_scene(setup: SpeckleSetup, sim, background, method: str = "pwf", **options):
    """:func:`retrieve_projection` on a drawn scene (:func:`draw_scene`) with ``method``'s
    options and ``options`` over them."""
    return retrieve_projection(
        sim.sample,
        sim.reference,
        **sim.geometry(),
        background_mask=background,
        **{**_method_options(method, setup), **options},
    )


def scene_row(i: int, methods: tuple[str, ...] = METHODS) -> list[dict]:
    """The rows of scene ``i``: one per method."""
    setup, sim, background = draw_scene(i)
    wavelength = optics.wavelength_m(setup.energy_eV)
    scene = {
        "scene": i,
        "shape": f"{setup.shape[0]}x{setup.shape[1]}",
        "energy_keV": setup.energy_eV / 1e3,
        "pixel_um": setup.pixel_size_m * 1e6,
        "l1_mm": setup.sample_diffuser_distance_m * 1e3,
        "upstream_mm": setup.diffuser_upstream_m * 1e3,
        "l2_mm": setup.diffuser_detector_distance_m * 1e3,
        "coherence_x_um": setup.coherence_length_x_m * 1e6,
        "coherence_y_um": setup.coherence_length_y_m * 1e6,
        "photons": setup.photons,
        "grain_radius_um": setup.diffuser_radius_median_m * 1e6,
        "grain_shape": setup.diffuser_grain_shape,
        "max_phase_rad": float(np.abs(sim.phase).max()),
        "displacement_px": displacement_px(
            sim.phase, wavelength, setup.diffuser_detector_distance_m, setup.pixel_size_m
        ),
        "speckle_grain_px": speckle_grain_px(sim.reference),
        "visibility": float(sim.reference.std() / sim.reference.mean()),
    }
    rows = []
    for method in methods:
        row = {**scene, "method": method, "refused": ""}
        t0 = time.perf_counter()
        try:
            res = retrieve_scene(setup, sim, background, method)
        except ValueError as exc:
            row.update(refused=str(exc).split(";")[0], phase_error=np.nan, phase_gain=np.nan, iterations=0)
        else:
            err = errors(res.phase, res.attenuation, sim.phase, sim.attenuation, background)
            row.update(
                phase_error=err["phase_error"],
                phase_gain=err["phase_gain"],
                iterations=int(res.iterations),
                converged=bool(res.converged),
                coherence_x_um_used=res.coherence_length_x_m * 1e6 if res.coherence_length_x_m else np.nan,
                coherence_y_um_used=res.coherence_length_y_m * 1e6 if res.coherence_length_y_m else np.nan,
                # PWF's own check of what the data carry (NaN for the trackers: not measured)
                **sensitivity_columns(res.parameters),
            )
        row["wall_s"] = time.perf_counter() - t0
        row["holds"] = bool(row["phase_error"] < PHASE_ERROR_THRESHOLD)
        rows.append(row)
    return rows


def _bins(rows: list[dict]) -> list[tuple[str, list[dict]]]:
    """Scenes grouped by the displacement's size relative to the speckle grain."""
    edges = [(0, 0.02, "< 0.02"), (0.02, 0.1, "0.02-0.1"), (0.1, 0.5, "0.1-0.5"), (0.5, np.inf, ">= 0.5")]
    return [
        (label, [r for r in rows if lo <= r["displacement_px"] / r["speckle_grain_px"] < hi]) for lo, hi, label in edges
    ]


def _median_error(rows: list[dict]) -> str:
    values = [r["phase_error"] for r in rows if np.isfinite(r["phase_error"])]
    return f"{np.median(values):.3f}" if values else "-"


def results_name(first: int, scenes: int) -> str:
    """The file stem of scenes ``first`` to ``first + scenes - 1``: ``random_scenes`` from 0."""
    return "random_scenes" if first == 0 else f"random_scenes_{first}-{first + scenes - 1}"


def write_report(rows: list[dict], out_dir: str | Path, device: str, name: str = "random_scenes") -> None:
    out = Path(out_dir)
    ids = sorted({r["scene"] for r in rows})
    span = f", scenes {ids[0]}-{ids[-1]}" if ids and ids[0] else ""
    lines = [
        f"# PWF and UMPA on {len(ids)} random geometries ({device}{span})",
        "",
        "`python -m benchmarks.random_scenes`: each scene draws every parameter at once (module docstring:",
        "8-30 keV, 0.3-3 µm pixels, L1 0-10 mm or the diffuser 1-20 mm upstream, L2 5-200 mm, coherence",
        "1-8 µm per axis, 1e2-1e6 ph/px, grains 0.8-6 µm, frames 64-259 px); one projection of the default",
        "rod with beads. Phase error: relative RMSE inside the sample, background zeroed on the true",
        f"sample-free pixels; a method holds below {PHASE_ERROR_THRESHOLD}. d/g: the 99th-percentile speckle",
        "displacement over the speckle grain.",
        "",
        "| d / g | scenes | PWF holds | PWF, true lengths, holds | UMPA K = 1 holds | PWF median error "
        "| UMPA median error | calibration refused |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, group in _bins(rows):
        by = {m: [r for r in group if r["method"] == m] for m in METHODS}
        n = len(by["pwf"])
        if not n:
            continue

        held = {m: sum(r["holds"] for r in by[m]) for m in METHODS}
        medians = {m: _median_error(by[m]) for m in METHODS}
        refused = sum(bool(r["refused"]) for r in by["pwf"])
        lines.append(
            f"| {label} | {n} | {held['pwf']} | {held['pwf_true_lengths']} | {held['umpa']} "
            f"| {medians['pwf']} | {medians['umpa']} | {refused} |"
        )
    lines += [
        "",
        "Every scene (PWF = defaults with calibrated lengths; true = given the true lengths; phase error / gain):",
        "",
        "| scene | frame | keV | pixel µm | L1 / upstream mm | L2 mm | coherence µm | ph/px | grain µm | d px | g px "
        "| visibility | PWF | PWF, true lengths | UMPA K = 1 |",
        "|---:|---|---:|---:|---|---:|---|---:|---|---:|---:|---:|---|---|---|",
    ]
    for i in sorted({r["scene"] for r in rows}):
        by = {r["method"]: r for r in rows if r["scene"] == i}
        s = by["pwf"]

        def cell(r):
            if r["refused"]:
                return "refused: " + r["refused"].replace("coherence-length fit failed: ", "")[:60]
            its = "" if r["method"] == "umpa" else f", {r['iterations']}" + ("" if r.get("converged") else " (cap)")
            return f"{r['phase_error']:.3f} / {r['phase_gain']:.2f}{its}"

        where = f"up {s['upstream_mm']:.1f}" if s["upstream_mm"] else f"{s['l1_mm']:.1f}"
        lines.append(
            f"| {i} | {s['shape']} | {s['energy_keV']:.1f} | {s['pixel_um']:.2f} | {where} | {s['l2_mm']:.0f} "
            f"| {s['coherence_x_um']:.1f} / {s['coherence_y_um']:.1f} | {s['photons']:.0e} "
            f"| {s['grain_radius_um']:.1f} {s['grain_shape'][:3]} | {s['displacement_px']:.2f} "
            f"| {s['speckle_grain_px']:.1f} | {s['visibility']:.2f} "
            f"| {cell(s)} | {cell(by['pwf_true_lengths'])} | {cell(by['umpa'])} |"
        )
    lines += _discrepancy_lines(rows)
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")


def _discrepancy_lines(rows: list[dict]) -> list[str]:
    """The discrepancy rule against the default alpha, scene by scene, where it was run."""
    pairs = {}
    for r in rows:
        if r["method"] in ("pwf", DISCREPANCY) and not r["refused"]:
            pairs.setdefault(r["scene"], {})[r["method"]] = r["phase_error"]
    both = [(p["pwf"], p[DISCREPANCY]) for p in pairs.values() if len(p) == 2]
    if not both:
        return []
    default, rule = np.array(both).T
    return [
        "",
        f'`alpha="discrepancy"` (`--discrepancy`) on the {len(both)} scenes both ran: holds on '
        f"{int(np.sum(rule < PHASE_ERROR_THRESHOLD))} against the default alpha's "
        f"{int(np.sum(default < PHASE_ERROR_THRESHOLD))}; better by more than 0.02 on "
        f"{int(np.sum(rule < default - 0.02))}, worse on {int(np.sum(rule > default + 0.02))}; median error "
        f"{np.median(rule):.3f} against {np.median(default):.3f}.",
    ]


def plot(rows: list[dict], path: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    styles = {"pwf": ("o", "C0", "PWF (calibrated lengths)"), "umpa": ("x", "C3", "UMPA K = 1")}
    for method, (marker, colour, label) in styles.items():
        pts = [r for r in rows if r["method"] == method and np.isfinite(r["phase_error"])]
        ax.scatter(
            [r["displacement_px"] / r["speckle_grain_px"] for r in pts],
            [min(r["phase_error"], 3.0) for r in pts],
            marker=marker,
            color=colour,
            label=label,
            alpha=0.8,
        )
    ax.axhline(PHASE_ERROR_THRESHOLD, color="grey", lw=0.8, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("speckle displacement / speckle grain (99th percentile)")
    ax.set_ylabel("relative phase error in the sample (capped at 3)")
    ax.set_title(f"{len({r['scene'] for r in rows})} random geometries, one projection each")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=80)
    ap.add_argument("--first", type=int, default=0, help="the first scene (0: random_scenes.*; else a set of its own)")
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--discrepancy", action="store_true", help="also PWF with alpha='discrepancy'")
    add_rerun_argument(ap)
    args = ap.parse_args(argv)
    methods = METHODS + ((DISCREPANCY,) if args.discrepancy else ())
    name = results_name(args.first, args.scenes)
    report = partial(write_report, name=name)
    kept = rows_kept_but(args.out, f"{name}.csv", args.rerun)
    scenes = range(args.first, args.first + args.scenes)
    return run_and_report(scenes, methods, args.out, name, report, plot, kept)


def add_rerun_argument(ap: argparse.ArgumentParser) -> None:
    """``--rerun SCENE ...`` (:func:`rows_kept_but`)."""
    ap.add_argument(
        "--rerun",
        type=int,
        nargs="+",
        default=(),
        metavar="SCENE",
        help="run only these scenes again, after a change that only they show; the others' rows are kept",
    )


def rows_kept_but(out_dir, csv_name: str, rerun: Sequence[int]) -> list[dict]:
    """The rows of ``csv_name`` in ``out_dir`` but those of the scenes in ``rerun``, which
    :func:`run_and_report` then runs again; nothing kept where nothing is re-run."""
    if not rerun:
        return []
    path = Path(out_dir) / csv_name
    if not path.exists():
        raise ValueError(f"--rerun re-runs part of a set, but {path} does not exist: run the set")
    return [r for r in read_rows_csv(out_dir, csv_name) if r["scene"] not in set(rerun)]


def run_and_report(
    scenes: range, methods: tuple[str, ...], out_dir, name: str, report, figure, kept: Sequence[dict] = ()
) -> list[dict]:
    """``scenes`` by every method, one progress line a scene, then ``name``.csv,
    ``report(rows, out, device)`` and ``figure(rows, name.png)``. ``kept``: rows of earlier
    runs, reported with the new ones; their scenes are not run again."""
    rows = list(kept)
    done = {r["scene"] for r in rows}
    for i in (i for i in scenes if i not in done):
        scene_rows = scene_row(i, methods)
        rows += scene_rows
        print(
            f"scene {i}: " + ", ".join(f"{r['method']} {r['phase_error']:.3f} {_flag(r)}" for r in scene_rows),
            flush=True,
        )
    rows.sort(key=lambda r: r["scene"])  # stable: a re-run scene's rows go back in their place
    out = write_rows_csv(out_dir, f"{name}.csv", rows)
    report(rows, out, device_name(np))
    figure(rows, Path(out, f"{name}.png"))
    return rows


def _flag(row: dict) -> str:
    return "(flagged)" if row.get("flagged") else ""


if __name__ == "__main__":
    main()
