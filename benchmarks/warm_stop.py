"""How far the stop rule's J test (``jtol``) can go, judged against the true projected phase
(docs/methods.md, "jtol 3e-5, judged against the truth"; issues #27 and #31).

On the full-width bench's scan (``pwf-dask bench fullwidth --work-dir DIR``: 801 angles x 32 x
2560, the paper's optics), selected projections are retrieved from zero and warm-started
from the projection before them in their chain of 8 (the stored psi, as ``pwf-dask run``
does), at each ``jtol``, and compared with the phantom's true projected phase (line integrals
averaged over 4 x 4 sub-pixels). The stop's iterations, the true phase error (rad rms over
the frame) and the phase gain (least-squares slope on the truth) per run.

    python -m benchmarks.warm_stop DIR [--items 0:4,60:5] [--jtol 1e-5,3e-5,1e-4,3e-4] [--out benchmarks/results]

Writes ``warm_stop.md`` and ``.csv`` (about 3 minutes on 2 cores for the defaults).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.pipeline import workflow
from pwf_dask.simulation.phantoms import phantom_from_json

#: hc in eV m: the wavelength of the scan's energy
HC_EV_M = 1.239841984e-6


def true_phase(scan_group, angle_index: int, subpixels: int = 4) -> np.ndarray:
    """-k times the phantom's delta line integral at ``angle_index``, averaged over
    ``subpixels`` x ``subpixels`` points of each detector pixel (the sign of Im psi)."""
    attrs = scan_group.attrs
    phantom = phantom_from_json(attrs["simulation_phantom"])
    energy_eV, pixel_m = float(attrs["energy_eV"]), float(attrs["pixel_size_m"])
    x, y = scan_group["x"][:], scan_group["y"][:]
    offsets = ((np.arange(subpixels) + 0.5) / subpixels - 0.5) * pixel_m
    xs, ys = (x[:, None] + offsets).ravel(), (y[:, None] + offsets).ravel()
    delta, _ = phantom.line_integrals(float(scan_group["angle"][angle_index]), xs, ys, energy_eV)
    delta = delta.reshape(y.size, subpixels, x.size, subpixels).mean(axis=(1, 3))
    return -2.0 * np.pi * energy_eV / HC_EV_M * delta


def main(argv=None) -> list[dict]:
    import zarr

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work_dir", help="the full-width bench's --work-dir (scan.zarr and recon.zarr)")
    ap.add_argument("--items", default="0:4,60:5", help="chain:index pairs (index >= 1: the start is index - 1)")
    ap.add_argument("--jtol", default="1e-5,3e-5,1e-4,3e-4")
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    scan, recon = Path(args.work_dir) / "scan.zarr", Path(args.work_dir) / "recon.zarr"
    g = zarr.open_group(str(scan), mode="r", use_consolidated=False)
    if "simulation_phantom" not in g.attrs:
        raise SystemExit(f"{scan} is not a simulated scan: its truth is unknown")
    done = zarr.open_group(str(recon), mode="r", use_consolidated=False)
    coherence = [tuple(c) for c in json.loads(done.attrs["coherence_lengths_per_position_m"])]
    chains = workflow.angle_chains(g["angle"][:], g["projections"].shape[0], 8)
    rows = []
    for pair in args.items.split(","):
        chain, index = (int(v) for v in pair.split(":"))
        item, before = chains[chain][index], chains[chain][index - 1]
        truth = true_phase(g, item[1])
        for start, start_from in (("zero", None), ("warm", before)):
            for jtol in (float(v) for v in args.jtol.split(",")):
                t0 = time.perf_counter()
                r = workflow._retrieve_item(
                    item, scan, recon, {"method": "pwf", "jtol": jtol}, "cpu", 1, coherence, start_from=start_from
                )
                row = {
                    "angle_index": item[1],
                    "start": start,
                    "jtol": jtol,
                    "iterations": r.iterations,
                    "converged": bool(r.converged),
                    "J": r.loss_history[-1],
                    "true_error_rad": float(np.sqrt(np.mean((r.phase - truth) ** 2))),
                    "gain": float(np.sum(r.phase * truth) / np.sum(truth * truth)),
                    "seconds": time.perf_counter() - t0,
                }
                rows.append(row)
                print(
                    f"angle {item[1]} {start} jtol {jtol:g}: {row['iterations']} it, true error "
                    f"{row['true_error_rad']:.3f} rad, gain {row['gain']:.4f}",
                    flush=True,
                )
    out = write_rows_csv(args.out, "warm_stop.csv", rows)
    rms_truth = float(np.sqrt(np.mean(true_phase(g, chains[0][0][1]) ** 2)))
    lines = [
        f"# The stop's J test against the true phase ({device_name(np)}, one FFT thread)",
        "",
        f"`python -m benchmarks.warm_stop {args.work_dir}`: projections of the full-width bench's scan "
        f"({g['projections'].shape[1]} angles x {g['projections'].shape[2]} x {g['projections'].shape[3]}, "
        f"true phase ~{rms_truth:.0f} rad rms), retrieved from zero and warm-started from the projection "
        "before in their chain of 8, at each `jtol`; true error = rms(phase - truth) over the frame, "
        "gain = least-squares slope on the truth.",
        "",
        "| angle | start | jtol | iterations | true error (rad) | gain | J | s |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['angle_index']} | {r['start']} | {r['jtol']:g} | {r['iterations']} | {r['true_error_rad']:.3f} "
            f"| {r['gain']:.4f} | {r['J']:.6g} | {r['seconds']:.1f} |"
        )
    (out / "warm_stop.md").write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
