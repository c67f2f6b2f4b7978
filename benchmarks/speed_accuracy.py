"""Speed against accuracy on one simulated scan: PWF beside LCS, UMPA, GF and MIST (``pwf-dask bench accuracy``).

Each method runs the whole pipeline (retrieval, tomography) on the same scan; errors are
measured against the phantom's refractive-index volume, times as wall seconds of the run.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.pwf import solver
from pwf_dask.retrieval import AUTHORS_RELEASE
from pwf_dask.tomo import tomography


def largest_bead_core(phantom, ds) -> np.ndarray:
    """The voxels of ``ds``'s (y, v, u) grid within half the radius of the phantom's largest bead."""
    bead = max(phantom.spheres, key=lambda s: s.radius_m)
    Y, V, U = np.meshgrid(ds.y.values, ds.v.values, ds.u.values, indexing="ij")
    return (Y - bead.y_m) ** 2 + (V - bead.v_m) ** 2 + (U - bead.u_m) ** 2 < (0.5 * bead.radius_m) ** 2


def _tomogram_errors(recon_path) -> dict:
    """Errors of a reconstruction of a simulated scan against its analytic truth."""
    import xarray as xr

    from pwf_dask.physics.materials import delta_beta
    from pwf_dask.simulation import phantom_from_json, refractive_index_volume

    ds = xr.open_zarr(recon_path)
    ph = phantom_from_json(ds.attrs["simulation_phantom"])
    e = float(ds.attrs["energy_eV"])
    td, tb = refractive_index_volume(ph, ds.y.values, ds.v.values, ds.u.values, e)
    d = ds.delta[0].values
    b = ds.beta[0].values
    inside = td > 0
    dg, bg = delta_beta("soda-lime glass", e)
    core = largest_bead_core(ph, ds)
    return {
        "delta_rmse_rel": float(np.sqrt(np.mean((d - td)[inside] ** 2)) / np.mean(td[inside])),
        "bead_delta_err": float(d[core].mean() / dg - 1),
        "bead_beta_err": float(b[core].mean() / bg - 1),
        "fsc_truth_delta_um": float(ds["fsc_delta_truth"].attrs["resolution_m"] * 1e6),
    }


ACCURACY_RUNS = [
    # (label, method, K, options)
    ("PWF 100 it", "pwf", 1, dict(max_iter=100)),
    ("PWF 300 it", "pwf", 1, dict(max_iter=300)),
    # no cap: the stop rule alone (at most 2000), and a looser stationarity tolerance
    ("PWF stop rule", "pwf", 1, {}),
    # the paper's Siegert fit (a Gaussian alone) in place of the template calibration
    ("PWF stop rule, Gaussian calibration", "pwf", 1, dict(coherence_method="gaussian")),
    ("PWF jtol 1e-4", "pwf", 1, dict(jtol=1e-4)),
    # every projection from zero, as the paper (the default warm-starts chains of 8 angles)
    ("PWF 300 it from zero", "pwf", 1, dict(max_iter=300, angle_chain=1)),
    ("PWF 300 it float64", "pwf", 1, dict(max_iter=300, precision="double")),
    ("PWF 300 it kappa 4", "pwf", 1, dict(max_iter=300, phase_scale=4.0)),
    ("PWF 300 it paper alpha", "pwf", 1, dict(max_iter=300, alpha=solver.PAPER_ALPHA)),
    ("PWF 300 it discrepancy alpha", "pwf", 1, dict(max_iter=300, alpha="discrepancy")),
    # the authors' released choices (zero-phase diffuser, (max|t|^2)^2, eta = 1, first-pass stop)
    ("PWF authors' release", "pwf", 1, {**AUTHORS_RELEASE, "angle_chain": 1}),
    ("LCS K=3", "lcs", 3, {}),
    ("LCS K=6", "lcs", 6, {}),
    ("LCS K=12", "lcs", 12, {}),
    ("UMPA K=1 w7", "umpa", 1, {}),
    ("UMPA K=12 w5", "umpa", 12, dict(tracking_options={"window": 5})),
    ("UMPA K=12 w9", "umpa", 12, dict(tracking_options={"window": 9})),
    ("GF K=1", "gf", 1, {}),
    ("MIST K=4", "mist", 4, {}),
    ("MIST K=12", "mist", 12, {}),
]


#: the scenes of ``pwf-dask bench accuracy --preset``: simulate_scan options, the runs, the
#: results' file stem and the scene's words in the table
ACCURACY_SCENES = {
    "demo": dict(
        scan=dict(preset="demo"),
        runs=ACCURACY_RUNS,
        stem="speed_accuracy",
        words="demo geometry (48 x 128 px, 61 angles, beads of 12 px radius",
    ),
    # the default scan (a bead of the paper's size), 61 of its 121 angles; the runs that
    # matter for the comparison, to keep it near a quarter of an hour on 2 cores
    "beads": dict(
        scan=dict(preset="beads", angles=61),
        runs=[
            r
            for r in ACCURACY_RUNS
            if r[0]
            in {
                "PWF 300 it",
                "PWF stop rule",
                "PWF stop rule, Gaussian calibration",
                "PWF 300 it paper alpha",
                "PWF authors' release",
                "LCS K=6",
                "LCS K=12",
                "UMPA K=12 w9",
                "GF K=1",
                "MIST K=12",
            }
        ],
        stem="speed_accuracy_beads",
        words="the default scan, preset beads (160 x 320 px, 61 of its 121 angles, one bead of 64 px radius",
    ),
}


def run_accuracy_benchmark(
    out_dir: str | Path, work_dir: str | Path | None = None, runs=None, preset: str = "demo"
) -> list[dict]:
    """``pwf-dask bench accuracy``: wall time against error for every method on one phantom.

    Scans of the ``preset``'s scene (:data:`ACCURACY_SCENES`: the ``demo`` geometry, 48 x 128 px
    and 61 angles, or the default ``beads`` scan, 1e4 ph/px, rotation axis 2.5 px off centre)
    with K = 1, 3, 6, 12 diffuser positions share the phantom and the first diffusers. Each run
    is retrieve + tomo + fsc on the threaded scheduler; errors are against the truth rasterised
    from the analytic phantom. Writes speed_accuracy[_beads].csv, .md and .png (Pareto front).
    """
    if preset not in ACCURACY_SCENES:
        raise ValueError(f"bench accuracy: no scene for preset {preset!r}; choose one of {', '.join(ACCURACY_SCENES)}")
    scene = ACCURACY_SCENES[preset]
    runs = runs or scene["runs"]
    import shutil
    import tempfile

    from pwf_dask.pipeline.workflow import fsc_scan, retrieve_scan, tomo_scan
    from pwf_dask.simulation import simulate_scan

    tmp = Path(work_dir or tempfile.mkdtemp(prefix="pwf-accuracy-"))
    scans = {}
    for k in sorted({r[2] for r in runs}):
        scans[k] = tmp / f"scan_{preset}_k{k}.zarr"
        if not scans[k].exists():
            simulate_scan(scans[k], **scene["scan"], positions=k, seed=0, rotation_axis_offset_px=2.5, progress=False)
    rows = []
    for label, method, k, opts in runs:
        name = "".join(c for c in label.replace(" ", "_") if c.isalnum() or c in "_.")
        recon = tmp / f"recon_{name}.zarr"
        shutil.rmtree(recon, ignore_errors=True)
        t0 = time.perf_counter()
        opts = dict(opts)
        tracking_options = opts.pop("tracking_options", None)
        if tracking_options:
            opts["tracking_options"] = tracking_options
        retrieve_scan(scans[k], recon, method=method, **opts)
        t_ret = time.perf_counter() - t0
        tomo_scan(recon)
        fsc_scan(recon)
        wall = time.perf_counter() - t0
        row = {
            "label": label,
            "method": method,
            "K": k,
            "calibration_s": _calibration_seconds(recon),
            "retrieval_s": t_ret,
            "wall_s": wall,
            **_tomogram_errors(recon),
        }
        rows.append(row)
        print(
            f"{label:<20} {wall:7.1f} s  delta RMSE {row['delta_rmse_rel']:.3f}"
            f"  bead delta {row['bead_delta_err']:+.3f}"
            f"  bead beta {row['bead_beta_err']:+.3f}  FSC(truth) {row['fsc_truth_delta_um']:.2f} um",
            flush=True,
        )
    out = write_rows_csv(out_dir, f"{scene['stem']}.csv", rows)
    pareto = _pareto([(r["wall_s"], r["delta_rmse_rel"]) for r in rows])
    lines = [
        f"# Speed and accuracy of PWF and the speckle-tracking baselines ({device_name(np)})",
        "",
        f"`pwf-dask bench accuracy --preset {preset}`: {scene['words']}, 1e4 ph/px, paper optics and",
        "diffuser: four layers of P3000), same phantom for every run; wall time of retrieve + tomo + fsc",
        "on 2 cores. Errors against the analytic truth: delta RMSE inside the sample relative to its mean,",
        "largest bead's delta and beta (relative), FSC resolution against the truth (1/2). Tomograms",
        f"under the default slice background ({tomography.DEFAULT_SLICE_BACKGROUND}; results before session 75:",
        "the paper's quadratic fit).",
        "* = on the Pareto front of time vs delta RMSE.",
        "",
        "Calibration: seconds of the coherence-length fit (PWF's; inside the wall time; templates are",
        "simulated once per geometry and process, so the first PWF run pays for them).",
        "",
        "| run | K | wall (s) | calibration (s) | delta RMSE | bead delta | bead beta | FSC truth (um) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for i, r in enumerate(rows):
        star = "*" if i in pareto else ""
        calib = "" if np.isnan(r["calibration_s"]) else f"{r['calibration_s']:.2f}"
        lines.append(
            f"| {r['label']}{star} | {r['K']} | {r['wall_s']:.1f} | {calib} | {r['delta_rmse_rel']:.3f} | "
            f"{r['bead_delta_err']:+.3f} | {r['bead_beta_err']:+.3f} | {r['fsc_truth_delta_um']:.2f} |"
        )
    (out / f"{scene['stem']}.md").write_text("\n".join(lines) + "\n")
    _speed_accuracy_plot(out / f"{scene['stem']}.png", rows, pareto)
    return rows


def _calibration_seconds(recon) -> float:
    """Seconds the coherence fits of a reconstruction took in all (NaN: none was run)."""
    import zarr

    fits = zarr.open_group(str(recon), mode="r").attrs.get("coherence_fits_per_position", "n/a")
    return float(sum(f.get("seconds", 0.0) for f in json.loads(fits))) if fits != "n/a" else float("nan")


def _pareto(points) -> set[int]:
    """Indices not dominated in (time, error), both to be minimised."""
    keep = set()
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in points):
            keep.add(i)
    return keep


def _speed_accuracy_plot(path, rows, pareto) -> None:
    from pwf_dask.plots import pyplot, save_figure

    plt = pyplot()

    fig, (ax, key_ax) = plt.subplots(1, 2, figsize=(10, 5), gridspec_kw={"width_ratios": [3, 1]})
    colors = {"pwf": "C0", "lcs": "C1", "umpa": "C2", "gf": "C3", "mist": "C4"}
    key = []
    for i, r in enumerate(rows):
        ax.scatter(
            r["wall_s"],
            r["delta_rmse_rel"],
            color=colors[r["method"]],
            s=60 if i in pareto else 25,
            edgecolor="k" if i in pareto else "none",
            zorder=3,
        )
        # points crowd where PWF variants cost about the same: numbers on the chart, names in a key
        ax.annotate(
            str(i + 1), (r["wall_s"], r["delta_rmse_rel"]), fontsize=7, xytext=(3, 2), textcoords="offset points"
        )
        key.append(f"{i + 1:>2}  {r['label']}{' *' if i in pareto else ''}")
    key_ax.axis("off")
    key_ax.text(0.0, 1.0, "\n".join(key), fontsize=8, family="monospace", va="top", transform=key_ax.transAxes)
    front = sorted((rows[i]["wall_s"], rows[i]["delta_rmse_rel"]) for i in pareto)
    ax.plot(*zip(*front), "k--", lw=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time, retrieve + tomo + fsc (s)")
    ax.set_ylabel("delta RMSE / mean delta (inside the sample)")
    ax.legend()
    save_figure(fig, path)
