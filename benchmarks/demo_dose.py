"""The demo scan against dose: PWF with one image per angle beside LCS with twelve (docs/validation.md,
the demo's speed-accuracy table, "Where the demo's 0.25 comes from").

The demo scene (48 x 128 px, 61 angles, the paper's optics and four layers of P3000, the
rotation axis 2.5 px off centre, raw counts) at 1e3-1e6 photons per pixel; PWF K = 1 with every
default (coherence lengths calibrated), LCS from K = 12. Each run is retrieve + tomo + fsc.
Reported: delta RMSE inside the sample, the largest bead's delta and beta, and PWF's median data
residual against the photon noise 100 / sqrt(photons) %. PWF's error does not fall with dose, and
its residual stays above the noise at high dose: a model error, not noise.

    python -m benchmarks.demo_dose [--out benchmarks/results]

Each reconstruction's tomograms are made under the default slice background ("auto") and
the paper's fit ("quadratic"), a row each. Writes ``demo_dose.md`` and ``.csv`` (about 8
minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from benchmarks.speed_accuracy import _tomogram_errors

DOSES = (1e3, 1e4, 1e5, 1e6)
RUNS = (("pwf", 1), ("lcs", 12))
#: each reconstruction's tomograms under the default slice background and the paper's fit
SLICE_BACKGROUNDS = ("auto", "quadratic")


def run(work: Path, photons: float, method: str, k: int) -> dict:
    """One scan of the demo scene at ``photons``, reconstructed by ``method`` from ``k`` positions."""
    import xarray as xr

    from pwf_dask.pipeline.workflow import fsc_scan, retrieve_scan, tomo_scan
    from pwf_dask.simulation import simulate_scan

    scan, recon = work / f"scan_k{k}_{photons:.0e}.zarr", work / f"recon_{method}_{photons:.0e}.zarr"
    simulate_scan(
        scan, preset="demo", positions=k, seed=0, rotation_axis_offset_px=2.5, photons=photons, progress=False
    )
    t0 = time.perf_counter()
    retrieve_scan(scan, recon, method=method)
    rows = []
    for mode in SLICE_BACKGROUNDS:  # the default first: the wall time is its run's
        tomo_scan(recon, slice_background=mode)
        fsc_scan(recon)
        wall = time.perf_counter() - t0
        ds = xr.open_zarr(recon)
        residual = float(np.median(ds.residual_rmse.values)) if method == "pwf" else float("nan")
        rows.append(
            {
                "photons": photons,
                "method": method,
                "K": k,
                "slice_background": mode,
                "wall_s": wall if mode == SLICE_BACKGROUNDS[0] else float("nan"),
                "residual_pct": residual,
                "noise_pct": 100 / np.sqrt(photons),
                **_cylinder_errors(ds),
                **_tomogram_errors(recon),
            }
        )
    return rows


def cylinder_values(ds, p: int = 0) -> tuple[float, float]:
    """Mean delta and beta of a reconstruction's simulated cylinder inside half its radius, its
    beads' voxels left out (:meth:`~pwf_dask.simulation.Phantom.cylinder_core`), at diffuser
    position ``p``: glass's beta is ten times cellulose's, and a quarter of the demo's core is bead."""
    from pwf_dask.simulation.phantoms import CORE_BEAD_MARGIN_PX, phantom_from_json

    ph = phantom_from_json(ds.attrs["simulation_phantom"])
    margin_m = CORE_BEAD_MARGIN_PX * ds.attrs["pixel_size_m"]
    core = ph.cylinder_core(ds.y.values, ds.v.values, ds.u.values, bead_margin_m=margin_m)
    return float(ds.delta[p].values[core].mean()), float(ds.beta[p].values[core].mean())


def _cylinder_errors(ds) -> dict:
    """The cylinder's delta and beta (:func:`cylinder_values`, position 0) against xraydb's cellulose."""
    from pwf_dask.physics.materials import delta_beta

    (d, b), (dc, bc) = cylinder_values(ds), delta_beta("cellulose", ds.attrs["energy_eV"])
    return {"cylinder_delta_err": d / dc - 1, "cylinder_beta_err": b / bc - 1}


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="pwf-demo-dose-"))
    rows = []
    try:
        for photons in DOSES:
            for method, k in RUNS:
                for r in run(work, photons, method, k):
                    rows.append(r)
                    print(
                        f"{photons:.0e} {method} K={k} {r['slice_background']}: delta RMSE {r['delta_rmse_rel']:.3f}, "
                        f"cylinder {r['cylinder_delta_err']:+.3f} / {r['cylinder_beta_err']:+.3f}, "
                        f"bead delta {r['bead_delta_err']:+.3f}, "
                        f"residual {r['residual_pct']:.2f} %",
                        flush=True,
                    )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    out = write_rows_csv(args.out, "demo_dose.csv", rows)
    lines = [
        f"# The demo scan against dose ({device_name(np)})",
        "",
        "`python -m benchmarks.demo_dose`: the demo scene (48 x 128 px, 61 angles, beads of 12 px radius,",
        "four layers of P3000, raw counts), PWF K = 1 with every default (calibrated coherence) beside",
        "LCS K = 12. Delta RMSE inside the sample relative to its mean; the largest bead's delta and beta",
        "(relative); PWF's median data residual against the photon noise (% of the mean reference).",
        "Each reconstruction's tomograms under the default slice background (auto) and the paper's",
        "fit (quadratic); the cylinder's delta and beta are the means of its bead-free core (half its",
        "radius, beads + 3 px left out) against cellulose; wall time: retrieve + tomo + fsc under the default.",
        "",
        "| photons / px | method | K | slice background | delta RMSE | cylinder delta | cylinder beta | bead delta "
        "| bead beta | FSC truth (µm) | residual (%) | noise (%) | wall (s) |",
        "|---:|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        residual = "" if np.isnan(r["residual_pct"]) else f"{r['residual_pct']:.2f}"
        wall = "" if np.isnan(r["wall_s"]) else f"{r['wall_s']:.0f}"
        lines.append(
            f"| {r['photons']:.0e} | {r['method'].upper()} | {r['K']} | {r['slice_background']} | "
            f"{r['delta_rmse_rel']:.3f} | {r['cylinder_delta_err']:+.3f} | {r['cylinder_beta_err']:+.3f} | "
            f"{r['bead_delta_err']:+.3f} | "
            f"{r['bead_beta_err']:+.3f} | {r['fsc_truth_delta_um']:.2f} | {residual} | {r['noise_pct']:.2f} | {wall} |"
        )
    (out / "demo_dose.md").write_text("\n".join(lines) + "\n")
    return rows


if __name__ == "__main__":
    main()
