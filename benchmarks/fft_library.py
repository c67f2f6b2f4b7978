"""Which CPU FFT library pays: a PWF iteration with Intel MKL's FFTs against scipy's pocketfft.

``PWF_DASK_FFT=auto`` picks the library (:func:`pwf_dask.backend.resolve_fft_library`). Each row
times one PWF iteration (the solver's own loop, as ``pwf-dask bench iteration`` times it: the
difference of a short and a long run) of the paper's optics on the grid the pipeline builds for a
frame (padded 17 px a side, :func:`pwf_dask.pwf.model.fast_len`), with each library, interleaved
in one run, on one and on two FFT threads, and how far the two runs' psi end apart. Transforms
alone mislead here: on the AMD EPYC of session 107 MKL was 1.1-1.6x slower than pocketfft on
two threads at scipy's old lengths (a 2-D real transform of 2200 x 2625: 19.4 ms against 12.4),
and the iteration there 0.88x; on the lengths the pipeline uses it was faster. But its
two-thread transforms of 2048 x 2048 came out wrong there (docs/benchmarks.md), so threaded
FFTs off Intel stay pocketfft's.

    python -m benchmarks.fft_library [--out benchmarks/results] [--quick]

Writes ``fft_library.md`` and ``.csv`` (about 8 min on 2 cores; ``--quick``: the square frames
on the detector grid only). Needs ``mkl-fft`` (installed on x86-64 Linux).
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.reporting import command_line, device_name, interleaved_min, write_rows_csv
from pwf_dask import backend
from pwf_dask.backend import FFT
from pwf_dask.pipeline import estimate
from pwf_dask.pwf import solver

FRAMES = [(512, 512), (1024, 1024), (1536, 1536), (2160, 2560)]
FIELD_UPSAMPLES = (1.0, 1.5)
THREADS = (1, 2)


def row(frame, field_upsample: float, workers: int) -> dict:
    """One frame, one field grid, one thread budget: the iteration with each library."""
    grid = estimate.padded_grid(frame)
    big = grid[0] * grid[1] * field_upsample**2 > 2e6
    short, long = (1, 3) if big else (2, 6)
    runs, psi, field_shape = [], [], None
    for library in ("scipy", "mkl"):
        model, y = estimate.timing_problem(grid, FFT.for_module(np, workers, library), field_upsample=field_upsample)
        field_shape = model.field_shape or grid
        for n in (short, long):
            runs.append(
                lambda n=n, model=model, y=y: solver.pwf(y, model, max_iter=n, tol=0, step=1e-3, step_search=False)
            )
        psi.append(runs[-1]().psi)  # the same iterations from the same start with either library
    t = interleaved_min(runs, lambda: None, rounds=2 if big else 3, min_time=0.1)
    scipy_s, mkl_s = (t[1] - t[0]) / (long - short), (t[3] - t[2]) / (long - short)
    disagreement = float(np.max(np.abs(psi[1] - psi[0])) / np.max(np.abs(psi[0])))
    return {
        "frame": "x".join(map(str, frame)),
        "field_upsample": field_upsample,
        "grid": "x".join(map(str, grid)),
        "field_grid": "x".join(map(str, field_shape)),
        "fft_workers": workers,
        "scipy_iteration_ms": scipy_s * 1e3,
        "mkl_iteration_ms": mkl_s * 1e3,
        "mkl_speedup": scipy_s / mkl_s,
        "psi_disagreement": disagreement,
        "auto": backend.resolve_fft_library("auto", workers),
    }


def write_report(out_dir, rows: list[dict], argv=None) -> None:
    write_rows_csv(out_dir, "fft_library.csv", rows)
    speedups = sorted(r["mkl_speedup"] for r in rows)
    lines = [
        f"# A PWF iteration with MKL's FFTs against scipy's pocketfft ({device_name(np)}, "
        f"vendor {backend.cpu_vendor() or 'unknown'})",
        "",
        f"`{command_line('benchmarks.fft_library', argv)}`: one iteration (the paper's optics, L1 > 0, single",
        "precision) on the pipeline's grid of each frame, each library timed interleaved in one run;",
        "*speed-up* is pocketfft's time over MKL's (above 1: MKL faster); *psi apart* the largest",
        "difference of the two runs' psi after the long run's iterations, over psi's largest value",
        "(float32 rounding grown over the iterations: ~1e-5; MKL's wrong transforms, where they happen, are left",
        "to pocketfft by `backend._mkl_agrees`). *auto* is what `PWF_DASK_FFT=auto` takes for that thread budget.",
        "",
        "| frame | field grid | FFT threads | pocketfft (ms) | MKL (ms) | speed-up | psi apart | auto |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    lines += [
        f"| {r['frame']} | {r['field_grid']} ({r['field_upsample']:g}x) | {r['fft_workers']} "
        f"| {r['scipy_iteration_ms']:.1f} | {r['mkl_iteration_ms']:.1f} | {r['mkl_speedup']:.2f} "
        f"| {r['psi_disagreement']:.1e} | {r['auto']} |"
        for r in rows
    ]
    lines += ["", f"Speed-up over all rows: {speedups[0]:.2f} to {speedups[-1]:.2f}, median {np.median(speedups):.2f}."]
    with open(f"{out_dir}/fft_library.md", "w") as f:
        f.write("\n".join(lines) + "\n")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    ap.add_argument("--quick", action="store_true", help="the square frames on the detector grid only")
    args = ap.parse_args(argv)
    if backend._mkl_scipy_fft() is None:
        raise SystemExit("fft_library: mkl_fft does not import here (pip install mkl-fft mkl-service)")
    rows = []
    for frame in FRAMES[:3] if args.quick else FRAMES:
        for field_upsample in FIELD_UPSAMPLES[:1] if args.quick else FIELD_UPSAMPLES:
            for workers in THREADS:
                rows.append(row(frame, field_upsample, workers))
                r = rows[-1]
                print(
                    f"{r['frame']} {r['field_grid']} {workers} thr: pocketfft {r['scipy_iteration_ms']:.1f} ms, "
                    f"MKL {r['mkl_iteration_ms']:.1f} ms ({r['mkl_speedup']:.2f})",
                    flush=True,
                )
    write_report(args.out, rows, argv)
    return rows


if __name__ == "__main__":
    main()
