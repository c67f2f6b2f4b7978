"""Command line: parses and calls; every computation lives in the library modules.

Implemented now: ``pwf-dask demo`` (one simulated projection, retrieved and plotted) and
``pwf-dask bench iteration``. The scan commands of CONTRACT §3 (simulate, retrieve, tomo,
fsc, run) come with the Dask workflow.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def _demo(args) -> int:
    import numpy as np

    from . import retrieve_projection
    from .plots import projection_panels
    from .simulation import SpeckleSetup, simulate_projection

    out = Path(args.dir)
    out.mkdir(parents=True, exist_ok=True)
    n = args.size
    print(f"simulating a {n} x {n} speckle projection (paper geometry, sub-pixel sandpaper, {args.photons:g} ph/px)")
    sim = simulate_projection(SpeckleSetup(shape=(n, n), photons=args.photons), seed=args.seed)
    t0 = time.perf_counter()
    res = retrieve_projection(
        sim.sample,
        sim.reference,
        energy_eV=sim.energy_eV,
        pixel_size_m=sim.pixel_size_m,
        sample_diffuser_distance_m=sim.sample_diffuser_distance_m,
        diffuser_detector_distance_m=sim.diffuser_detector_distance_m,
        max_iter=args.max_iter,
    )
    dt = time.perf_counter() - t0
    inside = sim.phase < -0.5
    gain = float(np.polyfit(sim.phase[inside], res.phase[inside], 1)[0])
    ins_a = sim.attenuation > 0.2 * sim.attenuation.max()
    gain_a = float(np.polyfit(sim.attenuation[ins_a], res.attenuation[ins_a], 1)[0])
    fig = projection_panels(
        out / "projection.png",
        sample=sim.sample,
        reference=sim.reference,
        result=res,
        truth_phase=sim.phase,
        truth_attenuation=sim.attenuation,
        pixel_size_m=sim.pixel_size_m,
    )
    np.savez_compressed(
        out / "projection.npz",
        sample=sim.sample,
        reference=sim.reference,
        phase=res.phase,
        attenuation=res.attenuation,
        true_phase=sim.phase,
        true_attenuation=sim.attenuation,
    )
    print(
        f"PWF: {res.iterations} iterations in {dt:.1f} s, converged={res.converged}, "
        f"residual RMSE {res.residual_rmse:.2f} % (photon noise {100 / np.sqrt(args.photons):.2f} %)"
    )
    print(
        f"coherence lengths calibrated: {res.coherence_length_x_m * 1e6:.2f} x {res.coherence_length_y_m * 1e6:.2f} um "
        f"(simulated {sim.coherence_length_x_m * 1e6:.2f} x {sim.coherence_length_y_m * 1e6:.2f} um)"
    )
    print(f"phase gain {gain:.3f}, attenuation gain {gain_a:.3f} (1 = exact)")
    print(f"wrote {fig} and {out / 'projection.npz'}")
    return 0


def _bench(args) -> int:
    from .bench import run_iteration_benchmark

    if args.what == "iteration":
        run_iteration_benchmark(args.out, device=args.device, quick=args.quick)
        print(f"results written to {args.out}")
        return 0
    raise SystemExit(f"pwf-dask bench: unknown benchmark {args.what!r}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pwf-dask", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser("demo", help="simulate a projection, retrieve it with PWF, write figures")
    d.add_argument("dir", nargs="?", default="pwf-dask-demo", help="output folder (default ./pwf-dask-demo)")
    d.add_argument("--size", type=int, default=384, help="detector pixels per side (default 384)")
    d.add_argument("--photons", type=float, default=1e4, help="photons per pixel (default 1e4)")
    d.add_argument("--max-iter", type=int, default=2000)
    d.add_argument("--seed", type=int, default=1)
    d.set_defaults(func=_demo)
    b = sub.add_parser("bench", help="benchmarks; results to workflows/results/")
    b.add_argument("what", choices=["iteration"], help="iteration: PWF iteration time / FFT time per size")
    b.add_argument("--device", default="cpu", choices=["cpu", "gpu", "auto"])
    b.add_argument("--out", default="workflows/results")
    b.add_argument("--quick", action="store_true", help="one small size (smoke test)")
    b.set_defaults(func=_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError, RuntimeError) as exc:
        print(f"pwf-dask {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
