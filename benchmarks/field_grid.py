"""The field grid an aliasing diffuser needs: accuracy and cost of 1, 1.25, 1.5 and 2x grids.

On the paper's diffuser (four layers of P3000 at 0.65 um pixels) the fitted transmission's
spectrum fills the detector band, and ``field_upsample="auto"`` puts the field on a finer grid
(docs/methods.md, The diffuser estimate and its field grid). This measures which factor the
default needs:

1. accuracy: the bead scene of the tests (10 keV, L1 = 3 mm, L2 = 20 mm, P3000, 1e4 ph/px,
   calibrated coherence, default alpha) at 256^2 (seeds 1-3) and 512^2 (seed 1), each grid
   fixed: phase gain, the largest bead's phase contrast, attenuation gain, iterations, time;
2. cost: one iteration (``pwf-dask bench``'s loop, one FFT thread) per grid at 1024^2 and on the
   padded full-width slab of ``pwf-dask bench fullwidth`` (32 x 2560), in FFTs of the detector grid,
   with exp(psi) on the field grid (the default) and on the detector grid
   (``sample_field_grid="detector"``, :func:`pwf_dask.pwf.model.build_model`), timed in one run.

    python -m benchmarks.field_grid [--out benchmarks/results] [--part all|cost|detector|scenes|random|report]

3. exp(psi) on either grid across scenes (``--part scenes``): the geometry sweep's scenes that take
   a field grid and the real-data regime's 160 x 700 strip, relative phase error and gain.
4. exp(psi) on either grid on ``benchmarks.random_scenes``' 80 random geometries (``--part random``,
   calibrated coherence, every default): each scene once on the field grid, and again with
   exp(psi) on the detector grid where ``field_upsample="auto"`` took a finer grid (that grid
   given: under "auto" a grid taken for coarse pixels keeps exp(psi) on it since session 100,
   :func:`pwf_dask.retrieval.sample_field_grid_on`, which these rows measured); split by
   what the alpha rule did (lowered Im(alpha) and its model probe let it stand, or the default
   alpha), as the scenes above all ran under the default alpha.

Writes ``field_grid.md``, ``field_grid.csv``, ``field_grid_rod.csv``, ``field_grid_scenes.csv``,
``field_grid_random.csv`` and ``field_grid_cost.csv`` (about 12 minutes on 2 cores without the
random scenes; ``--part scenes`` about 4, ``--part random`` about 35).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, read_rows_csv, write_rows_csv
from benchmarks.speed import iteration_benchmark
from pwf_dask.pwf import solver
from pwf_dask.retrieval import DIFFUSER_FIELD_UPSAMPLE, retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection

GRIDS = (1, 1.25, 1.5, 2)
SCENES = (((256, 256), 1), ((256, 256), 2), ((256, 256), 3), ((512, 512), 1))


def gain(recovered: np.ndarray, true: np.ndarray, inside: np.ndarray) -> float:
    """Regression slope of recovered on true values over ``inside`` (offset free)."""
    return float(np.polyfit(true[inside], recovered[inside], 1)[0])


def bead_contrast(image: np.ndarray, sim, sphere) -> float:
    """Mean over the bead's central disk minus the mean over a ring around it."""
    ny, nx = image.shape
    p = sim.pixel_size_m
    yy, xx = np.mgrid[0:ny, 0:nx]
    r = np.hypot(xx - (sphere.u_m / p + (nx - 1) / 2), yy - (sphere.y_m / p + (ny - 1) / 2)) * p / sphere.radius_m
    return float(np.mean(image[r < 0.5]) - np.mean(image[(r > 1.2) & (r < 1.6)]))


#: (field grid, where exp(psi) is formed) of the accuracy rows
VARIANTS = tuple((s, "field") for s in GRIDS) + ((DIFFUSER_FIELD_UPSAMPLE, "detector"),)


def accuracy_rows(variants=VARIANTS) -> list[dict]:
    rows = []
    for shape, seed in SCENES:
        sim = simulate_projection(SpeckleSetup(shape=shape, photons=1e4), seed=seed)
        bead = max(sim.phantom.spheres, key=lambda s: s.radius_m)
        inside = sim.attenuation > 0.2 * sim.attenuation.max()
        for s, where in variants:
            t0 = time.perf_counter()
            res = retrieve_projection(
                sim.sample, sim.reference, **sim.geometry(), field_upsample=s, sample_field_grid=where
            )
            seconds = time.perf_counter() - t0
            rows.append(
                {
                    "frame": f"{shape[0]} x {shape[1]}",
                    "seed": seed,
                    "field_grid": s,
                    "sample_field_grid": where,
                    "phase_gain": gain(res.phase, sim.phase, sim.phase < -0.5),
                    "bead_contrast_err_pct": 100
                    * (bead_contrast(res.phase, sim, bead) / bead_contrast(sim.phase, sim, bead) - 1),
                    "attenuation_gain": gain(res.attenuation, sim.attenuation, inside),
                    "iterations": res.iterations,
                    "converged": bool(res.converged),
                    "seconds": seconds,
                }
            )
            print(rows[-1], flush=True)
    return rows


def rod_rows(rows_px: int = 96) -> list[dict]:
    """The ``paper`` preset's rod (``benchmarks.edge_step``'s scene, ``rows_px`` x 2560, defaults,
    calibrated coherence) with exp(psi) on the field grid and on the detector grid: sharp edges
    (a ~16 rad step inside a pixel) are where the two differ."""
    from dataclasses import replace

    from benchmarks.edge_step import CAMERA_SHAPE, rod_offsets
    from benchmarks.frame_size import phase_gain
    from pwf_dask.simulation import SpeckleSimulator
    from pwf_dask.simulation.phantoms import PAPER_BEAD_RADIUS_M, scan_phantom

    setup = replace(SpeckleSetup(), shape=(rows_px, CAMERA_SHAPE[1]))
    phantom = scan_phantom(CAMERA_SHAPE, setup.pixel_size_m, 0, bead_radius_range_m=PAPER_BEAD_RADIUS_M)
    sim = SpeckleSimulator(setup, seed=0)
    sample, phase, _ = sim.project(phantom)
    reference = sim.reference()
    out = []
    for where in ("field", "detector"):
        t0 = time.perf_counter()
        r = retrieve_projection(sample, reference, **setup.geometry(), sample_field_grid=where)
        seconds = time.perf_counter() - t0
        recovered = np.asarray(r.phase)
        recovered = recovered - recovered[np.abs(phase) < 1e-6].mean()
        inside, rim = rod_offsets(recovered, phase)
        out.append(
            {
                "frame": f"{rows_px} x {CAMERA_SHAPE[1]} rod",
                "sample_field_grid": where,
                "field_grid": r.parameters["field_upsample"],
                "phase_gain": phase_gain(recovered, phase),
                "rms_error_rad": float(np.sqrt(np.mean((recovered - phase) ** 2))),
                "offset_inside_rad": inside,
                "offset_rim_rad": rim,
                "iterations": r.iterations,
                "converged": bool(r.converged),
                "seconds": seconds,
            }
        )
        print(out[-1], flush=True)
    return out


#: geometry_sweep's scenes whose aliasing diffuser puts the field on a finer grid ("auto"), named as there
DETECTOR_SCENES = (
    "the paper's (10 keV, 0.65 um, L1 3 mm, L2 20 mm)",
    "1.3 um pixels",
    "15 keV, 1 um pixels, L2 50 mm",
    "L1 10 mm, L2 100 mm",
    "diffuser 5 mm upstream (L1 = 0), distance given",
)


def _scenes():
    """(name, sample, reference, geometry, true phase, true attenuation, options): the
    geometry sweep's field-grid scenes (defaults) and the real-data regime's 160 x 700 strip."""
    from benchmarks.frame_size import STRIP_SETUP, strip_crop, strip_projection
    from benchmarks.geometry_sweep import RUNS, simulated

    for name, changes, options in RUNS:
        if name in DETECTOR_SCENES and not options:
            sim, upstream = simulated(changes)
            yield name, sim.sample, sim.reference, sim.geometry(), sim.phase, sim.attenuation, upstream
    sample, reference, phase, attenuation = strip_projection(STRIP_SETUP, seed=1)
    crop = strip_crop(STRIP_SETUP, 160, 700)
    # the single-material fit, as frame_size measures the strip (zero phase is "auto"'s choice at 25 keV)
    extra = {"diffuser_model": "single-material", "diffuser_upstream_m": STRIP_SETUP.diffuser_upstream_m}
    name = "strip 160 x 700 (25 keV, 6.5 um)"
    yield name, sample[crop], reference[crop], STRIP_SETUP.geometry(), phase[crop], attenuation[crop], extra


def scene_rows() -> list[dict]:
    """exp(psi) on the field grid and on the detector grid, per scene of :func:`_scenes`:
    relative phase error inside the sample and gain (``benchmarks.stability.errors``)."""
    from benchmarks.stability import errors

    rows = []
    for name, sample, reference, geometry, phase, attenuation, extra in _scenes():
        background = np.abs(phase) < 1e-3 * np.abs(phase).max()
        grid = {}  # the detector-grid run on the field run's grid, given (as random_rows)
        for where in ("field", "detector"):
            t0 = time.perf_counter()
            r = retrieve_projection(
                sample, reference, **geometry, background_mask=background, sample_field_grid=where, **grid, **extra
            )
            seconds = time.perf_counter() - t0
            grid = {"field_upsample": r.parameters["field_upsample"]}
            err = errors(r.phase, r.attenuation, phase, attenuation, background)
            rows.append(
                {
                    "scene": name,
                    "sample_field_grid": where,
                    "field_grid": r.parameters["field_upsample"],
                    "phase_error": err["phase_error"],
                    "phase_gain": err["phase_gain"],
                    "attenuation_error": err["attenuation_error"],
                    "iterations": r.iterations,
                    "converged": bool(r.converged),
                    "seconds": seconds,
                }
            )
            print(rows[-1], flush=True)
    return rows


def alpha_rule_outcome(parameters: dict) -> str:
    """What the alpha rule did in a retrieval: "lowered" (Im(alpha) under the default, the
    model probe letting it stand or not asked), "kept default" (the probe kept it), or
    "not lowered" (S at or above the rule's limit)."""
    if parameters.get("alpha_rule_kept_default"):
        return "kept default"
    return "lowered" if complex(parameters["alpha"]).imag < solver.DEFAULT_ALPHA.imag else "not lowered"


def random_rows(scenes=range(80)) -> list[dict]:
    """exp(psi) on the field grid, and on the detector grid where the field grid is finer, on
    ``benchmarks.random_scenes``' scenes (PWF, calibrated coherence, every default)."""
    from benchmarks.random_scenes import draw_scene, retrieve_scene
    from benchmarks.stability import errors

    rows = []
    for i in scenes:
        setup, sim, background = draw_scene(i)
        grid = {}  # the detector-grid run on the field run's grid, given: "auto" keeps coarse pixels on the field
        for where in ("field", "detector"):
            t0 = time.perf_counter()
            try:
                r = retrieve_scene(setup, sim, background, sample_field_grid=where, **grid)
            except ValueError:
                break  # refused (random_scenes records why); either grid refuses alike
            err = errors(r.phase, r.attenuation, sim.phase, sim.attenuation, background)
            rows.append(
                {
                    "scene": i,
                    "shape": f"{setup.shape[0]}x{setup.shape[1]}",
                    "sample_field_grid": where,
                    "field_grid": r.parameters["field_upsample"],
                    "alpha": r.parameters["alpha"],
                    "alpha_rule": alpha_rule_outcome(r.parameters),
                    "phase_sensitivity": r.parameters.get("phase_sensitivity", np.nan),
                    "diffuser_model": r.parameters["diffuser_model"],
                    "phase_error": err["phase_error"],
                    "phase_gain": err["phase_gain"],
                    "iterations": int(r.iterations),
                    "converged": bool(r.converged),
                    "seconds": time.perf_counter() - t0,
                }
            )
            print(rows[-1], flush=True)
            if float(r.parameters["field_upsample"]) == 1:
                break  # one grid: exp(psi) on the detector grid is the same model
            grid = {"field_upsample": r.parameters["field_upsample"]}
    return rows


def cost_rows() -> list[dict]:
    rows = []
    pad = 2 * 17
    for label, shape in (("1024 x 1024", (1024, 1024)), ("32 x 2560 slab", (32, 2560))):
        grid = (solver.fast_len(shape[0] + pad), solver.fast_len(shape[1] + pad))
        for s, where in [(s, "field") for s in GRIDS] + [(s, "detector") for s in GRIDS if s > 1]:
            r = iteration_benchmark(grid, field_upsample=s, repeat=3, fft_workers=1, sample_field_grid=where)
            rows.append(
                {
                    "frame": label,
                    "grid": f"{grid[0]} x {grid[1]}",
                    "field_grid": s,
                    "sample_field_grid": where,
                    "field_shape": "x".join(map(str, solver.field_grid(grid, s))),
                    "iteration_ms": r["iteration_ms"],
                    "fft_ms": r["fft_ms"],
                    "fft_times": r["ratio"],
                }
            )
            print(rows[-1], flush=True)
    return rows


def random_pairs(rows: list[dict]) -> list[tuple[dict, dict]]:
    """(field-grid row, detector-grid row) per random scene that ran on both."""
    det = {r["scene"]: r for r in rows if r["sample_field_grid"] == "detector"}
    return [(r, det[r["scene"]]) for r in rows if r["sample_field_grid"] == "field" and r["scene"] in det]


def random_lines(rows: list[dict]) -> list[str]:
    """The random scenes' section: a summary by what the alpha rule did, then each pair."""
    from benchmarks.stability import PHASE_ERROR_THRESHOLD as limit

    pairs = random_pairs(rows)
    lines = [
        "",
        "exp(psi) on either grid on the random geometries (`--part random`: `benchmarks.random_scenes`' 80",
        f"scenes, PWF, calibrated coherence, every default; {len(pairs)} of {len({r['scene'] for r in rows})} "
        "took a finer field grid and ran again with exp(psi) on the detector grid). Holds: phase error under "
        f"{limit}; better / worse: the detector grid's error lower / higher by more than 0.01; wall time: the "
        "group's retrievals summed, one run, 2 cores.",
        "",
        "| alpha rule | scenes | holds (field / detector grid) | median error (field / detector) "
        "| detector better / worse | iterations (field / detector, mean) | wall time, detector / field |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for outcome in ("lowered", "kept default", "not lowered"):
        group = [(f, d) for f, d in pairs if f["alpha_rule"] == outcome]
        if not group:
            continue
        ef, ed = (np.array([p[k]["phase_error"] for p in group]) for k in (0, 1))
        itf, itd = (np.mean([p[k]["iterations"] for p in group]) for k in (0, 1))
        wall = sum(d["seconds"] for _, d in group) / sum(f["seconds"] for f, _ in group)
        lines.append(
            f"| {outcome} | {len(group)} | {(ef < limit).sum()} / {(ed < limit).sum()} "
            f"| {np.median(ef):.3f} / {np.median(ed):.3f} | {(ed < ef - 0.01).sum()} / {(ed > ef + 0.01).sum()} "
            f"| {itf:.0f} / {itd:.0f} | {wall:.2f} |"
        )
    lines += [
        "",
        "| scene | frame | S | alpha rule | field grid | diffuser | phase error (field / detector) "
        "| phase gain (field / detector) | iterations (field / detector) |",
        "|---:|---|---:|---|---:|---|---:|---:|---:|",
    ]
    cap = {True: "", False: " (cap)"}
    lines += [
        f"| {f['scene']} | {f['shape']} | {f['phase_sensitivity']:.2g} | {f['alpha_rule']} | {f['field_grid']:g}x "
        f"| {f['diffuser_model']} | {f['phase_error']:.3f} / {d['phase_error']:.3f} "
        f"| {f['phase_gain']:.3f} / {d['phase_gain']:.3f} "
        f"| {f['iterations']}{cap[f['converged']]} / {d['iterations']}{cap[d['converged']]} |"
        for f, d in pairs
    ]
    return lines


def write_markdown(
    acc: list[dict],
    cost: list[dict],
    path: str,
    rod: list[dict] | None = None,
    scenes: list[dict] | None = None,
    random: list[dict] | None = None,
) -> None:
    lines = [
        "# The field grid for an aliasing diffuser",
        "",
        f"`python -m benchmarks.field_grid` on {device_name(np)}. The paper's geometry and diffuser (four",
        "layers of P3000, 1e4 ph/px), calibrated coherence, default alpha; each field grid fixed",
        "(`field_upsample`). Bead = the largest bead's phase contrast against the truth.",
        "",
        "| frame | seed | field grid | phase gain | bead | attenuation gain | iterations | s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    lines += [
        f"| {r['frame']} | {r['seed']} | {r['field_grid']:g}x"
        + (", exp(psi) on the detector grid" if r.get("sample_field_grid") == "detector" else "")
        + f" | {r['phase_gain']:.3f} | {r['bead_contrast_err_pct']:+.1f} % | {r['attenuation_gain']:.3f} "
        f"| {r['iterations']} | {r['seconds']:.1f} |"
        for r in acc
    ]
    if rod:
        lines += [
            "",
            "The `paper` preset's rod (`benchmarks.edge_step`'s scene, defaults, calibrated coherence; phase",
            "offsets of the recovered against the true phase, rad, deep inside the rod and at its rim):",
            "",
            "| frame | exp(psi) on | field grid | phase gain | rms error (rad) | offset inside | offset at rim "
            "| iterations | s |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {r['frame']} | {r['sample_field_grid']} grid | {r['field_grid']:g}x | {r['phase_gain']:.3f} "
            f"| {r['rms_error_rad']:.2f} | {r['offset_inside_rad']:+.2f} | {r['offset_rim_rad']:+.2f} "
            f"| {r['iterations']} | {r['seconds']:.0f} |"
            for r in rod
        ]
    if scenes:
        lines += [
            "",
            "exp(psi) on the field grid and on the detector grid across scenes (`--part scenes`: the",
            "geometry sweep's scenes that take a field grid, 256^2, seed 1, and the real-data regime's strip;",
            "defaults, calibrated coherence; phase error relative inside the sample, as `benchmarks.stability`):",
            "",
            "| scene | exp(psi) on | field grid | phase error | phase gain | attenuation error | iterations | s |",
            "|---|---|---:|---:|---:|---:|---:|---:|",
        ]
        lines += [
            f"| {r['scene']} | {r['sample_field_grid']} grid | {r['field_grid']:g}x | {r['phase_error']:.3f} "
            f"| {r['phase_gain']:.3f} | {r['attenuation_error']:.3f} "
            f"| {r['iterations']}{'' if r['converged'] else ' (cap)'} | {r['seconds']:.1f} |"
            for r in scenes
        ]
    if random:
        lines += random_lines(random)
    lines += [
        "",
        "One iteration (one FFT thread), in FFTs of the padded detector grid:",
        "",
        "| frame | padded grid | field grid | exp(psi) on | field shape | iteration (ms) | FFT-times |",
        "|---|---|---:|---|---|---:|---:|",
    ]
    lines += [
        f"| {r['frame']} | {r['grid']} | {r['field_grid']:g}x | {r.get('sample_field_grid', 'field')} grid "
        f"| {r['field_shape']} | {r['iteration_ms']:.1f} | {r['fft_times']:.1f} |"
        for r in cost
    ]
    lines += ["", f'`field_upsample="auto"` takes {DIFFUSER_FIELD_UPSAMPLE:g}x for an aliasing diffuser.']
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def _kept(out: str, name: str) -> list[dict] | None:
    """The rows of an earlier run's csv, or None where there is none."""
    return read_rows_csv(out, name) if (Path(out) / name).exists() else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument(
        "--part",
        default="all",
        choices=["all", "cost", "detector", "scenes", "random", "report"],
        help="cost: re-time the iterations alone, keeping the accuracy rows of OUT/field_grid.csv; detector: "
        "add the rows of exp(psi) on the detector grid to them and re-run the rod; scenes: exp(psi) on either "
        "grid across the geometry sweep's field-grid scenes and the strip, keeping every other row; random: "
        "exp(psi) on either grid on the 80 random geometries, keeping every other row; report: re-write "
        "field_grid.md from the csv files, running nothing",
    )
    args = ap.parse_args()
    if args.part in ("scenes", "random", "report"):
        if args.part == "scenes":
            write_rows_csv(args.out, "field_grid_scenes.csv", scene_rows())
        elif args.part == "random":
            write_rows_csv(args.out, "field_grid_random.csv", random_rows())
        acc = read_rows_csv(args.out, "field_grid.csv")
    elif args.part == "all":
        acc = accuracy_rows()
    else:
        kept = read_rows_csv(args.out, "field_grid.csv")  # rows before session 49 formed exp(psi) on the field grid
        acc = [{"sample_field_grid": "field", **r} for r in kept if r.get("sample_field_grid") != "detector"]
        if args.part == "detector":
            acc += accuracy_rows([v for v in VARIANTS if v[1] == "detector"])
    write_rows_csv(args.out, "field_grid.csv", acc)
    if args.part in ("all", "detector"):
        write_rows_csv(args.out, "field_grid_rod.csv", rod_rows())
    if args.part == "all":
        write_rows_csv(args.out, "field_grid_scenes.csv", scene_rows())
        write_rows_csv(args.out, "field_grid_random.csv", random_rows())
    rod, scenes, random = (_kept(args.out, f"field_grid_{part}.csv") for part in ("rod", "scenes", "random"))
    cost = cost_rows() if args.part in ("all", "cost") else read_rows_csv(args.out, "field_grid_cost.csv")
    write_rows_csv(args.out, "field_grid_cost.csv", cost)
    write_markdown(acc, cost, f"{args.out}/field_grid.md", rod, scenes, random)
    kept_rows = {
        "cost": "the accuracy rows",
        "detector": "the accuracy rows of exp(psi) on the field grid",
        "scenes": "every table but the scenes' (the detector-grid rows from an earlier `--part detector`)",
        "random": "every table but the random scenes'",
        "report": "every table (re-written from the csv files)",
    }
    if args.part in kept_rows:
        with open(f"{args.out}/field_grid.md", "a") as f:
            f.write(
                f"\n(`--part {args.part}`: {kept_rows[args.part]} kept from an earlier run of this benchmark, their"
                " seconds from that run's machine; seconds compare within one run only.)\n"
            )


if __name__ == "__main__":
    main()
