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
    python -m benchmarks.cylinder_draws --edge [--out benchmarks/results]

Writes ``cylinder_draws.md`` and ``.csv`` (about 21 min on 2 cores for 8 seeds and 3 grains; at another
``--photons`` ``cylinder_draws_1e3.md``, at another ``--rows`` ``cylinder_draws_96rows.md``). ``--why``
(``cylinder_draws_why.md`` and ``.csv``, about 6 min) takes the draw apart on single
projections at 0 deg on the detector grid (oversample 1, so that the true diffuser is a t PWF's
grid can hold), noise-free, with the true lengths, the phantom fixed and only the diffuser
drawn anew: the default diffuser estimate, the true t, and the true t at a fiftieth of the
default phase regularization, each to convergence or 3000 iterations. ``--edge``
(``cylinder_draws_edge.md`` and ``.csv``, about 6 min) keeps the true t and varies the body
instead: its outline softened (psi smoothed across the axis), its depth scaled, a weaker phase
regularization, and the pixels PWF misfits most (the edge's) left out of the data term; then
the sharp cylinder at 1e4 ph/px as a user's run sees it, without and with the single-material
prior. ``--single-material`` retrieves the scans with that prior (cellulose; the demo's glass
beads are a second material): ``cylinder_draws_single_material.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.cylinder_rows import FREE_RAD, cylinder_measures, true_diffuser
from benchmarks.cylinder_rows import GRAINS as ALL_GRAINS
from benchmarks.reporting import command_line, device_name, write_rows_csv
from benchmarks.stability import calibrated_lengths

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
#: the retrieval options of the single-material prior for the cylinder's one material
CELLULOSE_PRIOR = {"single_material": True, "sample_material": "cellulose"}


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
    phantom = phantom_from_json(ds.attrs["simulation_phantom"])
    bead = largest_bead_core(phantom, ds) if phantom.spheres else None
    mean = ds.mean("position", keepdims=True, keep_attrs=True)
    out = {}
    for name, d_s, p in [*((f"p{p}", ds, p) for p in range(ds.sizes["position"])), ("mean", mean, 0)]:
        d, b = cylinder_values(d_s, p)
        out[f"delta_err_{name}"], out[f"beta_err_{name}"] = d / dc - 1, b / bc - 1
        if bead is not None:  # a scan without beads (``--no-beads``) has the cylinder alone
            out[f"bead_delta_err_{name}"] = float(d_s.delta[p].values[bead].mean() / dg - 1)
            out[f"bead_beta_err_{name}"] = float(d_s.beta[p].values[bead].mean() / bg - 1)
    return out


def scan_rows(
    work: Path,
    grain: str,
    seed: int,
    photons: float = PHOTONS,
    frame_rows: int = ROWS,
    single_material: bool = False,
    beads: bool = True,
) -> list[dict]:
    """One demo scan of ``grain`` and ``seed`` through retrieve and tomo, a row per slice mode;
    ``single_material``: the retrieval's single-material prior, the cylinder's cellulose;
    ``beads=False``: the cylinder alone (a sample of one material)."""
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
        beads=beads,
        progress=False,
        **GRAINS[grain],
    )
    t0 = time.perf_counter()
    retrieve_scan(scan, recon, **(CELLULOSE_PRIOR if single_material else {}))
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
                "single_material": single_material,
                "beads": beads,
                **core_errors(ds[["delta", "beta"]].load().assign_attrs(ds.attrs)),
                "converged": float(ds.converged.values.mean()),
                "wall_s": time.perf_counter() - t0,
            }
        )
    return out


def why_scene(grain: str, seed: int):
    """The ``--why`` and ``--edge`` scene: the demo's cylinder alone at 0 deg on the detector grid
    (oversample 1), noise-free, diffuser draw ``seed``: (setup, simulator, t, psi on the simulator's
    grid, reference, the true lengths, the options that pass the true t)."""
    from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator, scan_phantom

    shape = (ROWS, WIDTH_PX)
    setup = SpeckleSetup(shape=shape, photons=np.inf, oversample=1, margin_px=64, **GRAINS[grain])
    setup.rotation_axis_offset_m = AXIS_OFFSET_PX * setup.pixel_size_m
    phantom = dataclasses.replace(scan_phantom(shape, setup.pixel_size_m, seed=0), spheres=())
    sim = SpeckleSimulator(setup, seed=seed)
    t = sim.diffuser()
    reference, (_, psi) = sim.intensity(None, t).astype(np.float32), sim.sample_field(phantom, 0.0)
    lengths = dict(coherence_length_x_m=setup.coherence_length_x_m, coherence_length_y_m=setup.coherence_length_y_m)
    exact = dict(diffuser=true_diffuser(t, setup, lengths), field_upsample=1, max_iter=WHY_MAX_ITER)
    return setup, sim, t, psi, reference, lengths, exact


def why_rows(grain: str, seed: int) -> list[dict]:
    """One diffuser draw on the detector grid, noise-free, true lengths: what the draw is."""
    from pwf_dask.retrieval import retrieve_projection

    setup, sim, t, psi, reference, lengths, exact = why_scene(grain, seed)
    sample, truth = sim.intensity(np.exp(psi), t).astype(np.float32), sim._bin(psi.imag)
    cases = {"estimated t": {}, "true t": exact, f"true t, alpha {WHY_ALPHA}": dict(exact, alpha=WHY_ALPHA)}
    out = []
    for case, opts in cases.items():
        res = retrieve_projection(sample, reference, **setup.geometry(), **lengths, **opts)
        gain = cylinder_measures(np.asarray(res.phase), truth)["gain"]
        out.append({"grain": grain, "seed": seed, "case": case, "gain": gain, "iterations": res.iterations})
        print(f"why {grain} diffuser seed {seed} {case}: gain {gain:.3f} ({res.iterations} its)", flush=True)
    return out


#: --edge: (case, edge softening sigma px, depth scale, alpha or None for the default); the last
#: case adds the sharp cylinder with the pixels its default run misfits most left out of the data
EDGE_CASES = (
    ("sharp (the phantom's)", 0.0, 1.0, None),
    ("edge softened, sigma 2 px", 2.0, 1.0, None),
    ("edge softened, sigma 6 px", 6.0, 1.0, None),
    ("sharp, a quarter of the depth", 0.0, 0.25, None),
    ("sharp, twice the depth", 0.0, 2.0, None),
    ("sharp, alpha 0.1+0.01j", 0.0, 1.0, 0.1 + 0.01j),
    ("edge softened 6 px, alpha 0.1+0.01j", 6.0, 1.0, 0.1 + 0.01j),
)
EDGE_MISFIT_RMS = 3.0
EDGE_LEFT_OUT = f"sharp, pixels misfit > {EDGE_MISFIT_RMS:g} rms left out"
#: and the sharp cylinder at the demo's dose with every default, without and with the
#: single-material prior of its one material
EDGE_NOISY_CASES = {
    "sharp, 1e4 ph/px, every default": {},
    "sharp, 1e4 ph/px, single-material prior (cellulose)": CELLULOSE_PRIOR,
}


def softened(psi: np.ndarray, sigma_px: float, depth_scale: float = 1.0) -> np.ndarray:
    """The sample's psi scaled by ``depth_scale`` and smoothed across the cylinder's axis (x) by a
    Gaussian of ``sigma_px`` simulator pixels: the same body with a blunter outline (0: as is)."""
    from scipy.ndimage import gaussian_filter1d

    psi = depth_scale * psi
    if sigma_px == 0:
        return psi
    return gaussian_filter1d(psi.real, sigma_px, axis=1) + 1j * gaussian_filter1d(psi.imag, sigma_px, axis=1)


def core_gain(phase: np.ndarray, truth: np.ndarray) -> float:
    """The phase's level in the central half of the cylinder's width against the truth's, each
    above the sample-free background's median (the tomogram's core, in projection)."""
    cols = np.nonzero((truth < FREE_RAD).any(axis=0))[0]
    quarter = (cols[-1] - cols[0]) // 4
    core = slice(cols[0] + quarter, cols[-1] - quarter + 1)
    level = np.median(phase[:, core]) - np.median(phase[truth > FREE_RAD])
    return float(level / np.median(truth[:, core]))


def edge_rows(grain: str, seed: int) -> list[dict]:
    """One diffuser draw, noise-free, true t and lengths, the cylinder's outline and depth varied."""
    from pwf_dask.retrieval import retrieve_projection

    setup, sim, t, psi0, reference, lengths, exact = why_scene(grain, seed)
    out = []

    def row(case, phase, truth, res):
        out.append(
            {
                "grain": grain,
                "seed": seed,
                "case": case,
                "gain": cylinder_measures(phase, truth)["gain"],
                "core_gain": core_gain(phase, truth),
                "depth_rad": float(-truth.min()),
                "max_gradient_rad_px": float(np.abs(np.diff(truth, axis=1)).max()),
                "iterations": res.iterations,
                "left_out_pct": 0.0,
            }
        )
        print(f"edge {grain} seed {seed} {case}: gain {out[-1]['gain']:.3f} ({res.iterations} its)", flush=True)

    for case, sigma, scale, alpha in EDGE_CASES:
        psi = softened(psi0, sigma, scale)
        sample, truth = sim.intensity(np.exp(psi), t).astype(np.float32), sim._bin(psi.imag)
        opts = exact if alpha is None else dict(exact, alpha=alpha)
        res = retrieve_projection(sample, reference, **setup.geometry(), **lengths, **opts)
        row(case, np.asarray(res.phase), truth, res)
        if case == EDGE_CASES[0][0]:
            sharp = (sample, truth, np.asarray(res.residual))
    sample, truth, residual = sharp
    misfit = residual > EDGE_MISFIT_RMS * np.sqrt(np.mean(residual**2))
    res = retrieve_projection(sample, reference, **setup.geometry(), **lengths, **exact, bad_pixels=misfit)
    row(EDGE_LEFT_OUT, np.asarray(res.phase), truth, res)
    out[-1]["left_out_pct"] = float(100 * misfit.mean())
    # as a user's run sees the sharp cylinder: counts, its own lengths and diffuser estimate
    rng = np.random.default_rng(100 + seed)
    noisy = [(rng.poisson(a * PHOTONS) / PHOTONS).astype(np.float32) for a in (reference, sample)]
    calibrated = calibrated_lengths(noisy[0], dataclasses.replace(setup, photons=PHOTONS))
    for case, opts in EDGE_NOISY_CASES.items():
        res = retrieve_projection(noisy[1], noisy[0], **setup.geometry(), **calibrated, **opts)
        row(case, np.asarray(res.phase), truth, res)
    return out


def dose(photons: float) -> str:
    """1e3 for 1000 ph/px: the files' and the tables' way of naming a dose."""
    mantissa, exponent = f"{photons:e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


def spread(values) -> str:
    """median, rms about 0 and range of relative errors, in %."""
    v = 100 * np.asarray(values)
    return f"{np.median(v):+.1f} | {np.sqrt(np.mean(v**2)):.1f} | {v.min():+.1f} to {v.max():+.1f}"


PRIOR_TEXT = "the single-material prior (cellulose), every default otherwise"
BEAD_TEXT = ", the largest bead's (within half its radius) against glass"


def summary_lines(rows: list[dict], seeds, command: str = "python -m benchmarks.cylinder_draws") -> list[str]:
    quantities = [q for q in QUANTITIES if f"{q}_err_p0" in rows[0]]  # files before the bead have none
    lines = [
        f"# The demo's wide weak cylinder over diffuser draws ({device_name(np)})",
        "",
        f"`{command}`: the demo scan{'' if rows[0].get('beads', True) in (True, 'True') else ' without its beads'} "
        f"({rows[0].get('rows', ROWS)} x {WIDTH_PX} px, {ANGLES} angles, "
        f"axis {AXIS_OFFSET_PX} px off centre, "
        f"raw counts, 2 positions, {dose(rows[0]['photons'])} ph/px, "
        f"{PRIOR_TEXT if rows[0].get('single_material') in (True, 'True') else 'every default'}), "
        f"seeds {', '.join(map(str, seeds))}; the cylinder's "
        f"bead-free core against cellulose{BEAD_TEXT if 'bead_delta' in quantities else ''}. "
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


def table_head(title: str, text: str, columns: str) -> list[str]:
    """A results file's title (with the device), its paragraph and its table's header lines."""
    return [f"# {title} ({device_name(np)})", "", text, "", *columns.split("\n")]


def by_grain_and_case(rows: list[dict]):
    """(grain, case, its rows) in the order the rows first name them: the tables' row groups."""
    for grain in dict.fromkeys(r["grain"] for r in rows):
        for case in dict.fromkeys(r["case"] for r in rows):
            yield grain, case, [r for r in rows if r["grain"] == grain and r["case"] == case]


def why_lines(rows: list[dict]) -> list[str]:
    lines = table_head(
        "What the cylinder's draw is: one projection per diffuser draw",
        "`python -m benchmarks.cylinder_draws --why`: the demo's cylinder alone at 0 deg (phantom seed 0, "
        f"axis {AXIS_OFFSET_PX} px off centre), 48 x 128 px on the detector grid, noise-free, the true "
        f"lengths; only the diffuser is drawn anew. The true t runs to convergence or {WHY_MAX_ITER} iterations.",
        "| grain | case | gain: median | range | each draw |\n|---|---|---:|---|---|",
    )
    for grain, case, rs in by_grain_and_case(rows):
        g = [r["gain"] for r in rs]
        lines.append(
            f"| {grain} | {case} | {np.median(g):.3f} | {min(g):.3f}-{max(g):.3f} | "
            + " ".join(f"{x:.2f}" for x in g)
            + " |"
        )
    return lines


def edge_lines(rows: list[dict]) -> list[str]:
    lines = table_head(
        "Where the cylinder's level goes: its outline, not its depth",
        "`python -m benchmarks.cylinder_draws --edge`: the `--why` scene (the demo's cylinder alone at 0 deg, "
        f"{ROWS} x {WIDTH_PX} px on the detector grid, noise-free, the true lengths and the true t, "
        f"to convergence or {WHY_MAX_ITER} iterations), draws {', '.join(map(str, WHY_SEEDS))}; the same body "
        "with its psi smoothed across the axis (sigma, simulator pixels) or scaled in depth. Gain: the "
        "least-squares slope on the truth where it is below -0.3 rad; core: the level of the central half of "
        f"its width. The last case leaves out of the data term the pixels the sharp cylinder's run misfits by "
        f"more than {EDGE_MISFIT_RMS:g} x the rms (its edge columns). The two {dose(PHOTONS)} ph/px cases take "
        "Poisson counts of the same images and a user's run: lengths calibrated, the diffuser estimated, the "
        "default stop, without and with the single-material prior.",
        "| grain | case | depth rad | max gradient rad/px | gain: median | range | core: median | range | "
        "iterations (median) | each draw's gain |\n|---|---|---:|---:|---:|---|---:|---|---:|---|",
    )
    for grain, case, rs in by_grain_and_case(rows):
        g, c = [r["gain"] for r in rs], [r["core_gain"] for r in rs]
        lines.append(
            f"| {grain} | {case} | {np.median([r['depth_rad'] for r in rs]):.2f} | "
            f"{np.median([r['max_gradient_rad_px'] for r in rs]):.2f} | {np.median(g):.3f} | "
            f"{min(g):.2f}-{max(g):.2f} | {np.median(c):.3f} | {min(c):.2f}-{max(c):.2f} | "
            f"{np.median([r['iterations'] for r in rs]):.0f} | " + " ".join(f"{x:.2f}" for x in g) + " |"
        )
    return lines


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(SEEDS))
    ap.add_argument("--grains", nargs="+", default=list(GRAINS), choices=list(GRAINS))
    ap.add_argument("--photons", type=float, default=PHOTONS, help="the scans' dose, ph/px")
    ap.add_argument("--rows", type=int, default=ROWS, help="the frame's height (the demo's is 48 x 128 px)")
    ap.add_argument(
        "--single-material", action="store_true", help="the scans retrieved with the single-material prior (cellulose)"
    )
    ap.add_argument("--no-beads", action="store_true", help="the demo's cylinder alone, without its glass beads")
    ap.add_argument("--why", action="store_true", help="take the draw apart on single projections instead")
    ap.add_argument("--edge", action="store_true", help="the cylinder's outline and depth varied instead")
    args = ap.parse_args(argv)
    if args.edge:
        rows = [r for g in args.grains for s in WHY_SEEDS for r in edge_rows(g, s)]
        out = write_rows_csv(args.out, "cylinder_draws_edge.csv", rows)
        (out / "cylinder_draws_edge.md").write_text("\n".join(edge_lines(rows)) + "\n")
        return rows
    if args.why:
        rows = [r for g in args.grains for s in WHY_SEEDS for r in why_rows(g, s)]
        out = write_rows_csv(args.out, "cylinder_draws_why.csv", rows)
        (out / "cylinder_draws_why.md").write_text("\n".join(why_lines(rows)) + "\n")
        return rows
    rows = []
    with tempfile.TemporaryDirectory(prefix="pwf-cylinder-draws-") as tmp:
        for grain in args.grains:
            for seed in args.seeds:
                work = Path(tmp) / grain.replace(" ", "")
                for r in scan_rows(work, grain, seed, args.photons, args.rows, args.single_material, not args.no_beads):
                    rows.append(r)
                    print(
                        f"{grain} seed {seed} {r['slice_background']}: delta {100 * r['delta_err_p0']:+.1f} / "
                        f"{100 * r['delta_err_p1']:+.1f} / mean {100 * r['delta_err_mean']:+.1f} %",
                        flush=True,
                    )
    name = "cylinder_draws" + ("" if args.photons == PHOTONS else f"_{dose(args.photons)}")
    name += "" if args.rows == ROWS else f"_{args.rows}rows"
    name += "_single_material" if args.single_material else ""
    name += "_no_beads" if args.no_beads else ""
    out = write_rows_csv(args.out, f"{name}.csv", rows)
    command = command_line("benchmarks.cylinder_draws", argv)
    (out / f"{name}.md").write_text("\n".join(summary_lines(rows, args.seeds, command)) + "\n")
    return rows


if __name__ == "__main__":
    main()
