"""Partial coherence from an extended source against the paper's detector blur.

PWF's model, Eq. (forwardModel), blurs the whole detector intensity by one IPSF, whose lengths
it calibrates from the reference. A source of finite size also moves the sample against the
speckle: by theta L1 with the diffuser L1 downstream, by theta d with it d upstream
(:mod:`pwf_dask.physics.source`). A checker simulating the source itself, or a real beamline,
therefore hands PWF data its model lacks. Per scene, seed and coherence model (the simulator's
``coherence_model``: ``detector``, the paper's model; ``source``, the extended source with the
same lengths at the diffuser's distance), one projection retrieved by PWF with every default
(calibrated lengths, ``"auto"``'s diffuser model and alpha rule) and by UMPA with the one image
(the single-shot baseline, whose model has no coherence blur), measured against the truth.

    python -m benchmarks.source_coherence [--out benchmarks/results]

Writes ``source_coherence.md`` and ``.csv`` (about 33 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.reporting import command_line, device_name, rows_of
from benchmarks.stability import PHASE_ERROR_THRESHOLD, errors
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, simulate_projection
from pwf_dask.simulation.speckle import sample_shift_sigma_m

#: scene name -> (SpeckleSetup fields, retrieve_projection options); 256^2, 1e4 ph/px, P3000
SCENES = {
    "paper (L1 3 mm, L2 20 mm)": ({}, {}),
    "L1 10 mm, L2 100 mm": ({"sample_diffuser_distance_m": 10e-3, "diffuser_detector_distance_m": 0.1}, {}),
    "L1 20 mm, L2 20 mm": ({"sample_diffuser_distance_m": 20e-3}, {}),
    "5 mm upstream, given": (
        {"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 5e-3},
        {"diffuser_upstream_m": 5e-3},
    ),
    "20 mm upstream, given": (
        {"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 20e-3},
        {"diffuser_upstream_m": 20e-3},
    ),
    "50 mm upstream, given": (
        {"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 50e-3},
        {"diffuser_upstream_m": 50e-3},
    ),
    "100 mm upstream, given": (
        {"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 0.1},
        {"diffuser_upstream_m": 0.1},
    ),
    "50 mm upstream, not given": ({"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 50e-3}, {}),
}
MODELS = ("detector", "source")
#: PWF with every default, and UMPA with the one image (the single-shot baseline)
METHODS = ("pwf", "umpa")
#: scenes that differ from another only in PWF's options: UMPA is not run again there
PWF_ONLY = ("50 mm upstream, not given",)
SEEDS = (1, 2, 3)
SHAPE = (256, 256)


def shift_sigma_px(setup: SpeckleSetup) -> float:
    """The rms shift of the sample against the speckle under the source (x, detector pixels)."""
    return abs(sample_shift_sigma_m(setup)[1]) / setup.pixel_size_m


def scene_rows(name: str, model: str, seed: int) -> list[dict]:
    """PWF with every default, and UMPA with the one image (not again where only PWF's
    options differ), on one simulated projection."""
    fields, options = SCENES[name]
    setup = SpeckleSetup(shape=SHAPE, coherence_model=model, **fields)
    t0 = time.perf_counter()
    sim = simulate_projection(setup, seed=seed)
    simulated = time.perf_counter() - t0
    rows = []
    for method in METHODS:
        if method == "umpa" and name in PWF_ONLY:
            continue
        t0 = time.perf_counter()
        if method == "pwf":
            r = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), **options)
        else:
            r = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), method="umpa")
        seconds = time.perf_counter() - t0
        attenuation = None if r.attenuation is None else np.asarray(r.attenuation)
        e = errors(np.asarray(r.phase), attenuation, sim.phase, sim.attenuation, np.abs(sim.phase) < 1e-6)
        pwf = method == "pwf"
        rows.append(
            {
                "scene": name,
                "model": model,
                "method": method,
                "seed": seed,
                "shift_sigma_px": shift_sigma_px(setup) if model == "source" else 0.0,
                "length_x_err": r.coherence_length_x_m / setup.coherence_length_x_m - 1 if pwf else float("nan"),
                "length_y_err": r.coherence_length_y_m / setup.coherence_length_y_m - 1 if pwf else float("nan"),
                "phase_gain": e["phase_gain"],
                "phase_error": e["phase_error"],
                "attenuation_error": e["attenuation_error"],
                "residual_pct": r.residual_rmse if pwf else float("nan"),
                "sample_misfit": r.parameters.get("sample_misfit", float("nan")) if pwf else float("nan"),
                "warned": bool(r.parameters.get("sensitivity_warning")),
                "diffuser_model": r.parameters.get("diffuser_model", ""),
                "iterations": r.iterations,
                "converged": r.converged,
                "simulate_s": simulated,
                "seconds": seconds,
            }
        )
    return rows


def _mean(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def summary_lines(rows: list[dict]) -> list[str]:
    """Per scene, method and coherence model, means over the seeds."""
    lines = [
        "| scene | method | coherence model | sample's rms shift (px) | lengths x / y | phase gain | phase error "
        "| attenuation error | residual % | sample misfit | warned |",
        "|---|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for method in METHODS:
            for model in MODELS:
                here = [r for r in rows if (r["scene"], r["model"], r.get("method", "pwf")) == (scene, model, method)]
                if not here:
                    continue
                lengths = (
                    f"{100 * _mean(here, 'length_x_err'):+.1f}% / {100 * _mean(here, 'length_y_err'):+.1f}%"
                    if method == "pwf"
                    else ""
                )
                pwf_only = (
                    f"{_mean(here, 'residual_pct'):.3f} | {_mean(here, 'sample_misfit'):.2f} "
                    f"| {sum(r['warned'] for r in here)}/{len(here)}"
                    if method == "pwf"
                    else " | | "
                )
                lines.append(
                    f"| {scene} | {'PWF' if method == 'pwf' else 'UMPA K = 1'} | {model} "
                    f"| {_mean(here, 'shift_sigma_px'):.2f} | {lengths} "
                    f"| {_mean(here, 'phase_gain'):.3f} | {_mean(here, 'phase_error'):.3f} "
                    f"| {_mean(here, 'attenuation_error'):.3f} | {pwf_only} |"
                )
    return lines


def write_markdown(rows: list[dict], path: str, command: str) -> None:
    seeds = ", ".join(str(s) for s in dict.fromkeys(r["seed"] for r in rows))
    lines = [
        "# Partial coherence from an extended source",
        "",
        f"`{command}` on {device_name(np)}: one {SHAPE[0]} x {SHAPE[1]} projection of the default bead",
        "phantom, 10 keV, 0.65 um pixels, P3000, 1e4 ph/px, coherence 3.47 / 4.31 um, seeds " + seeds + ",",
        "simulated under each coherence model (`SpeckleSetup(coherence_model=...)`: `detector`, the",
        "paper's IPSF on the detector intensity, which PWF's model is; `source`, an extended Gaussian",
        "source with the same lengths at the diffuser's distance, whose tilted waves also move the",
        "sample against the speckle by the rms shift given) and retrieved by PWF with every default",
        '(`retrieve_projection`: calibrated lengths, `diffuser_model="auto"`, the alpha rule) and by',
        'UMPA with the one image (`method="umpa"`, K = 1; not run again where only PWF\'s options differ).',
        "Lengths: calibrated against the source's. Phase and attenuation error: rms over the sample",
        "relative to the truth's rms (`benchmarks.stability.errors`). Sample misfit: the fit's residual",
        "inside the sample over its background's (warned above 1.3). Means over the seeds.",
        "",
        *summary_lines(rows),
        "",
        "## Every run",
        "",
        "| scene | method | model | seed | lengths x / y | phase gain | phase error | attenuation error "
        "| residual % | misfit | diffuser model | iterations | simulate s | retrieve s |",
        "|---|---|---|---:|---|---:|---:|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        pwf = r.get("method", "pwf") == "pwf"
        lengths = f"{100 * r['length_x_err']:+.1f}% / {100 * r['length_y_err']:+.1f}%" if pwf else ""
        fit = f"{r['residual_pct']:.3f} | {r['sample_misfit']:.2f}" if pwf else " | "
        lines.append(
            f"| {r['scene']} | {r.get('method', 'pwf')} | {r['model']} | {r['seed']} | {lengths} "
            f"| {r['phase_gain']:.3f} | {r['phase_error']:.3f} | {r['attenuation_error']:.3f} | {fit} "
            f"| {r['diffuser_model']} | {r['iterations']} | {r['simulate_s']:.1f} | {r['seconds']:.1f} |"
        )
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


#: random geometries (``benchmarks.random_scenes``, scenes 0-79) run under both models: the
#: ones whose sample moves most against the speckle under the source
RANDOM_SCENES = 80
RANDOM_LARGEST = 20


def random_shift_px(i: int) -> float:
    """The larger axis's rms shift of random scene ``i``'s sample against its speckle (px)."""
    from benchmarks.random_scenes import DRAW_SEED, draw_setup

    setup = replace(draw_setup(np.random.default_rng(DRAW_SEED + i)), coherence_model="source")
    return max(abs(s) for s in sample_shift_sigma_m(setup)) / setup.pixel_size_m


def random_rows(i: int) -> list[dict]:
    """Random scene ``i`` simulated under each coherence model, PWF with every default."""
    from benchmarks.random_scenes import DRAW_SEED, draw_setup, retrieve_scene

    drawn = draw_setup(np.random.default_rng(DRAW_SEED + i))
    rows = []
    for model in MODELS:
        setup = replace(drawn, coherence_model=model)
        sim = simulate_projection(setup, seed=i)
        background = np.abs(sim.phase) < 1e-3 * np.abs(sim.phase).max()
        t0 = time.perf_counter()
        try:
            r = retrieve_scene(setup, sim, background)
        except ValueError as exc:  # the calibration refuses the reference (random_scenes' "refused")
            rows.append({"scene": i, "model": model, "refused": str(exc).split(";")[0]})
            continue
        e = errors(r.phase, r.attenuation, sim.phase, sim.attenuation, background)
        rows.append(
            {
                "scene": i,
                "geometry": (
                    f"{drawn.diffuser_upstream_m * 1e3:.1f} mm upstream"
                    if drawn.diffuser_upstream_m
                    else f"L1 {drawn.sample_diffuser_distance_m * 1e3:.1f} mm"
                )
                + f", L2 {drawn.diffuser_detector_distance_m * 1e3:.1f} mm",
                "model": model,
                "shift_sigma_px": random_shift_px(i),
                "phase_error": e["phase_error"],
                "holds": bool(e["phase_error"] < PHASE_ERROR_THRESHOLD),
                "sample_misfit": r.parameters.get("sample_misfit", float("nan")),
                "warned": bool(r.parameters.get("sensitivity_warning")),
                "seconds": time.perf_counter() - t0,
            }
        )
    return rows


def write_random_markdown(rows: list[dict], path: str, command: str) -> None:
    pairs: dict = {}
    for r in rows:
        if not r.get("refused"):
            pairs.setdefault(r["scene"], {})[r["model"]] = r
    refused = sorted({r["scene"] for r in rows if r.get("refused")})
    both = [p for p in pairs.values() if len(p) == 2]
    held = {m: sum(p[m]["holds"] for p in both) for m in MODELS}
    warned = {m: sum(p[m]["warned"] for p in both) for m in MODELS}
    lines = [
        "# Partial coherence from an extended source: random geometries",
        "",
        f"`{command}` on {device_name(np)}: of the random geometries 0-{RANDOM_SCENES - 1}",
        "(`benchmarks.random_scenes`: 8-30 keV, 0.3-3 um pixels, L2 5-200 mm, coherence 1-8 um, 1e2-1e6",
        f"ph/px, grains, upstream diffusers), the {RANDOM_LARGEST} whose sample moves most against the speckle",
        "under an extended source, each simulated under both coherence models and retrieved by PWF with",
        f"every default. Holds: phase error below {PHASE_ERROR_THRESHOLD}.",
        "",
        f"Holds: detector {held['detector']} of {len(both)}, source {held['source']}; warned: detector "
        f"{warned['detector']}, source {warned['source']}."
        + (
            f" Refused by the calibration (too few frequencies above the noise): scene {', '.join(map(str, refused))}."
            if refused
            else ""
        ),
        "",
        "| scene | geometry | shift (px) | phase error, detector / source | holds | sample misfit | warned |",
        "|---:|---|---:|---|---|---|---|",
    ]
    for i, p in sorted(
        ((i, p) for i, p in pairs.items() if len(p) == 2), key=lambda kv: -kv[1]["source"]["shift_sigma_px"]
    ):
        d, s = p["detector"], p["source"]
        lines.append(
            f"| {i} | {d['geometry']} | {s['shift_sigma_px']:.2f} | {d['phase_error']:.3f} / {s['phase_error']:.3f} "
            f"| {'yes' if d['holds'] else 'no'} / {'yes' if s['holds'] else 'no'} "
            f"| {d['sample_misfit']:.2f} / {s['sample_misfit']:.2f} "
            f"| {'yes' if d['warned'] else 'no'} / {'yes' if s['warned'] else 'no'} |"
        )
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results", help="folder for source_coherence.md and .csv")
    ap.add_argument("--scenes", nargs="*", choices=list(SCENES), help="a subset of the scenes (default: all)")
    ap.add_argument("--seeds", type=int, nargs="*", default=list(SEEDS))
    ap.add_argument("--report-only", action="store_true", help="re-write the report from the CSV")
    ap.add_argument(
        "--random",
        action="store_true",
        help=f"the {RANDOM_LARGEST} random geometries of 0-{RANDOM_SCENES - 1} whose sample moves most, instead",
    )
    a = ap.parse_args(argv)
    if a.random:
        largest = sorted(range(RANDOM_SCENES), key=random_shift_px)[-RANDOM_LARGEST:]

        def compute_random() -> list[dict]:
            out = []
            for i in largest:
                out += random_rows(i)
                print(out[-len(MODELS) :], flush=True)
            return out

        rows = rows_of(a.out, "source_coherence_random.csv", a.report_only, compute_random)
        name = "source_coherence_random.md"
        write_random_markdown(rows, f"{a.out}/{name}", command_line("benchmarks.source_coherence", argv))
        return

    def compute() -> list[dict]:
        out = []
        for scene in a.scenes or SCENES:
            for seed in a.seeds:
                for model in MODELS:
                    out += scene_rows(scene, model, seed)
                    print(out[-len(MODELS) :], flush=True)
        return out

    rows = rows_of(a.out, "source_coherence.csv", a.report_only, compute)
    write_markdown(rows, f"{a.out}/source_coherence.md", command_line("benchmarks.source_coherence", argv))


if __name__ == "__main__":
    main()
