"""The demo scan's wide weak cylinder over diffuser draws, on P3000, finer and coarser grains (issue #27).

Sessions 76-79 read the demo scan's cylinder (seed 0) 11 % deep in the bare slice on 1.2 um
grains and 4 % shallow on P3000, and took the sign for the grain's. This benchmark asks how
much of that one number is the draw. It simulates the demo scan (48 x 128 px, 31 angles, the
rotation axis 2.5 px off centre, raw counts, 2 diffuser positions, the paper's optics, 1e4
ph/px) for each seed and grain, reconstructs it with every default, and reads the cylinder's
delta and beta in its bead-free core (:func:`benchmarks.demo_dose.cylinder_values`) at each
position, under the default slice background ("auto") and the paper's fit ("quadratic"), and
in the mean of the two positions' tomograms. The cylinder sits on the rotation axis, so every
angle of a position projects it onto the same pixels of the same diffuser: a draw's error is
common to its angles and averages only over positions.

    python -m benchmarks.cylinder_draws [--out benchmarks/results] [--seeds 0 1 ...] [--photons 1e3] [--rows 96]
    python -m benchmarks.cylinder_draws --why [--out benchmarks/results]

Writes ``cylinder_draws.md`` and ``.csv`` (about 21 min on 2 cores for 8 seeds and 3 grains; at another
``--photons`` ``cylinder_draws_1e3.md``, at another ``--rows`` ``cylinder_draws_96rows.md``). ``--why``
(``cylinder_draws_why.md`` and ``.csv``, about 6 min) takes the draw apart on single
projections at 0 deg on the detector grid (oversample 1, so that the true diffuser is a t PWF's
grid can hold), noise-free, with the true lengths, the phantom fixed and only the diffuser
drawn anew: the default diffuser estimate, the true t, and the true t at a fiftieth of the
default phase regularization, each to convergence or 3000 iterations.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.cylinder_rows import GRAINS as ALL_GRAINS
from benchmarks.cylinder_rows import cylinder_measures, true_diffuser
from benchmarks.reporting import command_line, device_name, write_rows_csv

#: the paper's P3000, a finer grain (1.2 um) and a coarser sandpaper (P2000, 10.3 um grains)
GRAINS = {g: ALL_GRAINS[g] for g in ("P3000", "1.2 um", "P2000")}
SEEDS = tuple(range(8))
ANGLES = 31
AXIS_OFFSET_PX = 2.5
SLICE_BACKGROUNDS = ("auto", "quadratic")
#: what each scan reports (the row keys' prefixes) and how the tables name it
QUANTITIES = {"delta": "cylinder delta", "beta": "cylinder beta", "bead_delta": "bead delta", "bead_beta": "bead beta"}
#: the demo preset's dose (ph/px) and frame; ``--photons`` and ``--rows`` write files of their own beside
PHOTONS = 1e4
ROWS, WIDTH_PX = 48, 128
#: --why: the diffuser draws (the phantom stays seed 0's) and the cases
WHY_SEEDS = tuple(range(8))
WHY_ALPHA = 0.1 + 0.001j
WHY_MAX_ITER = 3000


def core_errors(ds) -> dict:
    """The cylinder's core delta and beta against cellulose, and the largest bead's (within half
    its radius) against glass, at each position and in the mean of the positions' tomograms
    (relative errors)."""
    from benchmarks.demo_dose import cylinder_values
    from benchmarks.speed_accuracy import largest_bead_core
    from pwf_dask.physics.materials import delta_beta
    from pwf_dask.simulation import phantom_from_json

    dc, bc = delta_beta("cellulose", ds.attrs["energy_eV"])
    dg, bg = delta_beta("soda-lime glass", ds.attrs["energy_eV"])
    bead = largest_bead_core(phantom_from_json(ds.attrs["simulation_phantom"]), ds)
    mean = ds.mean("position", keepdims=True, keep_attrs=True)
    out = {}
    for name, d_s, p in [*((f"p{p}", ds, p) for p in range(ds.sizes["position"])), ("mean", mean, 0)]:
        d, b = cylinder_values(d_s, p)
        out[f"delta_err_{name}"], out[f"beta_err_{name}"] = d / dc - 1, b / bc - 1
        out[f"bead_delta_err_{name}"] = float(d_s.delta[p].values[bead].mean() / dg - 1)
        out[f"bead_beta_err_{name}"] = float(d_s.beta[p].values[bead].mean() / bg - 1)
    return out


def scan_rows(work: Path, grain: str, seed: int, photons: float = PHOTONS, frame_rows: int = ROWS) -> list[dict]:
    """One demo scan of ``grain`` and ``seed`` through retrieve and tomo, a row per slice mode."""
    import xarray as xr

    from pwf_dask.pipeline.workflow import retrieve_scan, tomo_scan
    from pwf_dask.simulation import simulate_scan

    scan, recon = work / f"scan_{seed}.zarr", work / f"recon_{seed}.zarr"
    simulate_scan(
        scan,
        preset="demo",
        angles=ANGLES,
        seed=seed,
        rotation_axis_offset_px=AXIS_OFFSET_PX,
        photons=photons,
        shape=(frame_rows, WIDTH_PX),
        progress=False,
        **GRAINS[grain],
    )
    t0 = time.perf_counter()
    retrieve_scan(scan, recon)
    out = []
    for mode in SLICE_BACKGROUNDS:
        tomo_scan(recon, slice_background=mode)
        ds = xr.open_zarr(recon)
        out.append(
            {
                "grain": grain,
                "seed": seed,
                "photons": photons,
                "rows": frame_rows,
                "slice_background": mode,
                **core_errors(ds[["delta", "beta"]].load().assign_attrs(ds.attrs)),
                "converged": float(ds.converged.values.mean()),
                "wall_s": time.perf_counter() - t0,
            }
        )
    return out


def why_rows(grain: str, seed: int) -> list[dict]:
    """One diffuser draw on the detector grid, noise-free, true lengths: what the draw is."""
    from pwf_dask.retrieval import retrieve_projection
    from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, scan_phantom

    shape = (ROWS, WIDTH_PX)
    setup = SpeckleSetup(shape=shape, photons=np.inf, oversample=1, margin_px=64, **GRAINS[grain])
    setup.rotation_axis_offset_m = AXIS_OFFSET_PX * setup.pixel_size_m
    phantom = dataclasses.replace(scan_phantom(shape, setup.pixel_size_m, seed=0), spheres=())
    sim = SpeckleSimulator(setup, seed=seed)
    t = sim.diffuser()
    reference, (field_, psi) = sim.intensity(None, t), sim.sample_field(phantom, 0.0)
    sample, truth = sim.intensity(field_, t).astype(np.float32), sim._bin(psi.imag)
    lengths = dict(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    exact = dict(diffuser=true_diffuser(t, setup, lengths), field_upsample=1, max_iter=WHY_MAX_ITER)
    cases = {"estimated t": {}, "true t": exact, f"true t, alpha {WHY_ALPHA}": dict(exact, alpha=WHY_ALPHA)}
    out = []
    for case, opts in cases.items():
        res = retrieve_projection(sample, reference.astype(np.float32), **setup.geometry(), **lengths, **opts)
        gain = cylinder_measures(np.asarray(res.phase), truth)["gain"]
        out.append({"grain": grain, "seed": seed, "case": case, "gain": gain, "iterations": res.iterations})
        print(f"why {grain} diffuser seed {seed} {case}: gain {gain:.3f} ({res.iterations} its)", flush=True)
    return out


def dose(photons: float) -> str:
    """1e3 for 1000 ph/px: the files' and the tables' way of naming a dose."""
    mantissa, exponent = f"{photons:e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


def spread(values) -> str:
    """median, rms about 0 and range of relative errors, in %."""
    v = 100 * np.asarray(values)
    return f"{np.median(v):+.1f} | {np.sqrt(np.mean(v**2)):.1f} | {v.min():+.1f} to {v.max():+.1f}"


def summary_lines(rows: list[dict], seeds, command: str = "python -m benchmarks.cylinder_draws") -> list[str]:
    quantities = [q for q in QUANTITIES if f"{q}_err_p0" in rows[0]]  # files before the bead have none
    lines = [
        f"# The demo's wide weak cylinder over diffuser draws ({device_name(np)})",
        "",
        f"`{command}`: the demo scan ({rows[0].get('rows', ROWS)} x {WIDTH_PX} px, {ANGLES} angles, "
        f"axis {AXIS_OFFSET_PX} px off centre, "
        f"raw counts, 2 positions, {dose(rows[0]['photons'])} ph/px, every default), "
        f"seeds {', '.join(map(str, seeds))}; the cylinder's "
        "bead-free core against cellulose, the largest bead's (within half its radius) against glass. "
        "Single positions: both positions of every seed; mean: the two "
        "positions' tomograms averaged, one value per seed; rms about zero.",
        "",
        "| grain | slice background | quantity | median % | rms % | range % |",
        "|---|---|---|---:|---:|---|",
    ]
    for grain in dict.fromkeys(r["grain"] for r in rows):
        for mode in SLICE_BACKGROUNDS:
            rs = [r for r in rows if r["grain"] == grain and r["slice_background"] == mode]
            for q in quantities:
                single = [r[f"{q}_err_p{p}"] for r in rs for p in (0, 1)]
                mean = [r[f"{q}_err_mean"] for r in rs]
                for label, values in (
                    (f"{QUANTITIES[q]}, single positions", single),
                    (f"{QUANTITIES[q]}, mean of 2", mean),
                ):
                    lines.append(f"| {grain} | {mode} | {label} | {spread(values)} |")
    lines += [
        "",
        "| grain | seed | slice background | "
        + " | ".join(f"{QUANTITIES[q]} p0 / p1 / mean %" for q in quantities)
        + " |",
        "|---|---:|---|" + "---|" * len(quantities),
    ]
    for r in rows:
        cells = (" / ".join(f"{100 * r[f'{q}_err_{k}']:+.1f}" for k in ("p0", "p1", "mean")) for q in quantities)
        lines.append(f"| {r['grain']} | {r['seed']} | {r['slice_background']} | " + " | ".join(cells) + " |")
    return lines


def why_lines(rows: list[dict]) -> list[str]:
    lines = [
        f"# What the cylinder's draw is: one projection per diffuser draw ({device_name(np)})",
        "",
        "`python -m benchmarks.cylinder_draws --why`: the demo's cylinder alone at 0 deg (phantom seed 0, "
        f"axis {AXIS_OFFSET_PX} px off centre), 48 x 128 px on the detector grid, noise-free, the true "
        f"lengths; only the diffuser is drawn anew. The true t runs to convergence or {WHY_MAX_ITER} iterations.",
        "",
        "| grain | case | gain: median | range | each draw |",
        "|---|---|---:|---|---|",
    ]
    for grain in dict.fromkeys(r["grain"] for r in rows):
        for case in dict.fromkeys(r["case"] for r in rows):
            g = [r["gain"] for r in rows if r["grain"] == grain and r["case"] == case]
            lines.append(
                f"| {grain} | {case} | {np.median(g):.3f} | {min(g):.3f}-{max(g):.3f} | "
                + " ".join(f"{x:.2f}" for x in g)
                + " |"
            )
    return lines


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--grains", nargs="+", default=list(GRAINS), choices=list(GRAINS))
    ap.add_argument("--photons", type=float, default=PHOTONS, help="the scans' dose, ph/px")
    ap.add_argument("--rows", type=int, default=ROWS, help="the frame's height (the demo's is 48 x 128 px)")
    ap.add_argument("--why", action="store_true", help="take the draw apart on single projections instead")
    args = ap.parse_args(argv)
    if args.why:
        rows = [r for g in args.grains for s in WHY_SEEDS for r in why_rows(g, s)]
        out = write_rows_csv(args.out, "cylinder_draws_why.csv", rows)
        (out / "cylinder_draws_why.md").write_text("\n".join(why_lines(rows)) + "\n")
        return rows
    rows = []
    with tempfile.TemporaryDirectory(prefix="pwf-cylinder-draws-") as tmp:
        for grain in args.grains:
            for seed in args.seeds:
                for r in scan_rows(Path(tmp) / grain.replace(" ", ""), grain, seed, args.photons, args.rows):
                    rows.append(r)
                    print(
                        f"{grain} seed {seed} {r['slice_background']}: delta {100 * r['delta_err_p0']:+.1f} / "
                        f"{100 * r['delta_err_p1']:+.1f} / mean {100 * r['delta_err_mean']:+.1f} %",
                        flush=True,
                    )
    name = "cylinder_draws" + ("" if args.photons == PHOTONS else f"_{dose(args.photons)}")
    name += "" if args.rows == ROWS else f"_{args.rows}rows"
    out = write_rows_csv(args.out, f"{name}.csv", rows)
    command = command_line("benchmarks.cylinder_draws", argv)
    (out / f"{name}.md").write_text("\n".join(summary_lines(rows, args.seeds, command)) + "\n")
    return rows


if __name__ == "__main__":
    main()
