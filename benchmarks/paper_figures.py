"""The paper's Fig. 2 and Fig. 3 on simulated scenes: PWF (one image) beside LCS (K images) and the truth.

    python -m benchmarks.paper_figures --out benchmarks/results [--quick]

* Fig. 2, one projection: the paper's optics and diffuser (10 keV, 0.65 um pixels, L1 = 3 mm,
  L2 = 20 mm, four layers of P3000), beads in a cylinder, 1e4 ph/px, 256 x 256 px. PWF from
  one image with its coherence lengths calibrated from the reference (as a user runs it, the
  lengths are never given) beside LCS with K = 12 diffuser positions; phase and attenuation
  against the truth, a line through the largest bead. Writes ``paper_fig2.png|csv``.
* Fig. 3, tomography: the demo scan's geometry (48 x 128 px, 61 angles, beads of 12 px radius,
  rotation axis 2.5 px off centre) through ``retrieve``, ``tomo`` and ``fsc``: PWF K = 1
  against LCS K = 12. delta and beta slices through the largest bead against the truth, the
  bead's delta profile, and the FSC curves (even/odd angle halves, the 1/4 criterion of the
  paper for two independent reconstructions). Writes ``paper_fig3.png|csv``.

The numbers are in ``paper_figures.md`` with the command, the device and the commit.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.reporting import device_name, write_rows_csv
from benchmarks.stability import Scene, errors
from pwf_dask.plots import pyplot, save_figure
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.simulation import SpeckleSetup, default_phantom

FIG2_SHAPE = (256, 256)
FIG2_LCS_POSITIONS = 12
FIG3_SCAN = dict(preset="demo", angles=61, rotation_axis_offset_px=2.5)
PHOTONS = 1e4


def fig2_projection(shape: tuple[int, int] = FIG2_SHAPE, seed: int = 0) -> tuple[list[dict], dict]:
    """Rows (one per method) of errors against the truth, and the images of the figure."""
    setup = SpeckleSetup(shape=shape)
    fov_m = shape[1] * setup.pixel_size_m
    phantom = default_phantom(fov_m, np.random.default_rng(seed + 1), height_m=shape[0] * setup.pixel_size_m)
    scene = Scene(setup, phantom, 1.0, FIG2_LCS_POSITIONS, seed)
    sample, reference = scene.images(PHOTONS, FIG2_LCS_POSITIONS, seed=seed + 7)
    geometry = dict(
        energy_eV=setup.energy_eV,
        pixel_size_m=setup.pixel_size_m,
        sample_diffuser_distance_m=setup.sample_diffuser_distance_m,
        diffuser_detector_distance_m=setup.diffuser_detector_distance_m,
    )
    runs = {"PWF K=1": ("pwf", sample[0], reference[0]), f"LCS K={FIG2_LCS_POSITIONS}": ("lcs", sample, reference)}
    rows, images = [], {"truth": (scene.phase, scene.attenuation)}
    for label, (method, s, r) in runs.items():
        t0 = time.perf_counter()
        res = retrieve_projection(s, r, method=method, **geometry)
        wall = time.perf_counter() - t0
        err = errors(res.phase, res.attenuation, scene.phase, scene.attenuation, scene.background, scene.bead)
        rows.append({"figure": "2", "method": label, "wall_s": wall, **err})
        images[label] = (np.asarray(res.phase), np.asarray(res.attenuation))
    return rows, images


def plot_fig2(path: Path, images: dict) -> Path:
    plt = pyplot()
    labels = list(images)
    truth_phase = images["truth"][0]
    row = int(np.argmin(truth_phase.min(axis=1)))  # the line through the deepest phase: the largest bead
    fig, axes = plt.subplots(2, len(labels) + 1, figsize=(3.3 * (len(labels) + 1), 6.4))
    for i, (name, unit) in enumerate((("phase", "rad"), ("attenuation", ""))):
        lo, hi = float(images["truth"][i].min()), float(images["truth"][i].max())
        for j, label in enumerate(labels):
            im = axes[i, j].imshow(images[label][i], cmap="gray", vmin=lo, vmax=hi)
            axes[i, j].set_title(f"{label}: {name}", fontsize=9)
            axes[i, j].axhline(row, color="tab:orange", lw=0.6)
            axes[i, j].axis("off")
        fig.colorbar(im, ax=axes[i, len(labels) - 1], shrink=0.8, label=f"{name} {unit}".strip())
        ax = axes[i, -1]
        for label in labels:
            ax.plot(images[label][i][row], lw=1.0 if label != "truth" else 1.6, label=label)
        ax.set_xlabel("x (px)")
        ax.set_title(f"{name} along the line", fontsize=9)
        ax.legend(fontsize=7)
    return save_figure(fig, path)


def fig3_tomography(work: Path, quick: bool = False) -> tuple[list[dict], dict]:
    """Rows of errors against the truth and FSC, and the reconstruction stores, for PWF and LCS."""
    from benchmarks.speed_accuracy import _tomogram_errors
    from pwf_dask.pipeline.workflow import fsc_scan, retrieve_scan, tomo_scan
    from pwf_dask.simulation import simulate_scan

    scan_options = dict(FIG3_SCAN, angles=21) if quick else FIG3_SCAN
    runs = {"PWF K=1": ("pwf", 1), f"LCS K={FIG2_LCS_POSITIONS}": ("lcs", FIG2_LCS_POSITIONS)}
    rows, recons = [], {}
    for label, (method, k) in runs.items():
        scan = work / f"scan_k{k}.zarr"
        if not scan.exists():
            simulate_scan(scan, **scan_options, positions=k, seed=0, progress=False)
        recon = work / f"recon_{method}.zarr"
        t0 = time.perf_counter()
        retrieve_scan(scan, recon, method=method)
        tomo_scan(recon)
        fsc = fsc_scan(recon, split="even-odd")
        wall = time.perf_counter() - t0
        rows.append(
            {
                "figure": "3",
                "method": label,
                "wall_s": wall,
                "fsc_halves_delta_um": fsc["delta"] * 1e6,
                **_tomogram_errors(recon),
            }
        )
        recons[label] = recon
    return rows, recons


def plot_fig3(path: Path, recons: dict) -> Path:
    import xarray as xr

    from pwf_dask.simulation import phantom_from_json, refractive_index_volume

    plt = pyplot()
    sets = {label: xr.open_zarr(r) for label, r in recons.items()}
    first = next(iter(sets.values()))
    phantom = phantom_from_json(first.attrs["simulation_phantom"])
    bead = max(phantom.spheres, key=lambda s: s.radius_m)
    iy = int(np.argmin(np.abs(first.y.values - bead.y_m)))
    truth_d, truth_b = refractive_index_volume(
        phantom, first.y.values[iy : iy + 1], first.v.values, first.u.values, float(first.attrs["energy_eV"])
    )
    iv = int(np.argmin(np.abs(first.v.values - bead.v_m)))
    slices = {"truth": (truth_d[0], truth_b[0])}
    slices.update({label: (ds.delta[0, iy].values, ds.beta[0, iy].values) for label, ds in sets.items()})
    labels = list(slices)
    fig, axes = plt.subplots(2, len(labels) + 1, figsize=(3.3 * (len(labels) + 1), 6.4))
    for i, name in enumerate(("delta", "beta")):
        lo, hi = float(slices["truth"][i].min()), float(slices["truth"][i].max())
        for j, label in enumerate(labels):
            im = axes[i, j].imshow(slices[label][i], cmap="gray", vmin=lo, vmax=hi)
            axes[i, j].set_title(f"{label}: {name}", fontsize=9)
            axes[i, j].axis("off")
        fig.colorbar(im, ax=axes[i, len(labels) - 1], shrink=0.8, label=name)
    ax = axes[0, -1]
    for label in labels:
        ax.plot(first.u.values * 1e6, slices[label][0][iv], label=label, lw=1.6 if label == "truth" else 1.0)
    ax.set_xlabel("u (µm)")
    ax.set_title("delta through the largest bead", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1, -1]
    for label, ds in sets.items():
        curve = ds["fsc_delta"]
        ax.plot(curve.frequency.values * 1e-6, curve.values.mean(axis=0), label=label)
    ax.axhline(0.25, color="k", lw=0.6, ls="--", label="1/4")
    ax.set_xlabel("spatial frequency (cycles/µm)")
    ax.set_title("FSC of delta, even/odd angles", fontsize=9)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def write_summary(out: Path, rows: list[dict], command: str, shape: tuple[int, int]) -> None:
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    lines = [
        f"# The paper's Fig. 2 and Fig. 3 on simulated scenes ({device_name(np)}, commit {commit})",
        "",
        f"`{command}`. PWF's coherence lengths are calibrated from each reference (never given).",
        "",
        f"Fig. 2 (one projection, {shape[0]} x {shape[1]}, paper optics, P3000): errors against the truth",
        "(RMS over the frame relative to the truth's RMS; gain = least-squares slope on the truth inside",
        "the sample).",
        "",
        "| method | wall (s) | phase error | phase gain | attenuation error | bead contrast error |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in (r for r in rows if r["figure"] == "2"):
        lines.append(
            f"| {r['method']} | {r['wall_s']:.1f} | {r['phase_error']:.3f} | {r['phase_gain']:.3f} | "
            f"{r['attenuation_error']:.3f} | {100 * r['bead_contrast_error']:+.1f} % |"
        )
    lines += [
        "",
        "Fig. 3 (tomography of the demo geometry): delta RMSE inside the sample (relative), the largest",
        "bead's delta and beta (relative error), FSC against the truth (1/2) and between even/odd halves (1/4).",
        "",
        "| method | wall (s) | delta RMSE | bead delta | bead beta | FSC truth (µm) | FSC halves (µm) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in (r for r in rows if r["figure"] == "3"):
        lines.append(
            f"| {r['method']} | {r['wall_s']:.1f} | {r['delta_rmse_rel']:.3f} | {r['bead_delta_err']:+.3f} | "
            f"{r['bead_beta_err']:+.3f} | {r['fsc_truth_delta_um']:.2f} | {r['fsc_halves_delta_um']:.2f} |"
        )
    lines += ["", "![Fig. 2](paper_fig2.png)", "", "![Fig. 3](paper_fig3.png)"]
    (out / "paper_figures.md").write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="benchmarks/results", help="folder of the figures and tables")
    p.add_argument("--work-dir", default=None, help="folder of the scans and reconstructions (default: temporary)")
    p.add_argument("--quick", action="store_true", help="128 x 128 projection and 21 angles (smoke test)")
    args = p.parse_args(argv)
    out = Path(args.out)
    work = Path(args.work_dir or tempfile.mkdtemp(prefix="pwf-paper-figures-"))
    work.mkdir(parents=True, exist_ok=True)
    shape = (128, 128) if args.quick else FIG2_SHAPE
    rows2, images = fig2_projection(shape)
    rows3, recons = fig3_tomography(work, quick=args.quick)
    write_rows_csv(
        out, "paper_figures.csv", [{k: r.get(k, "") for k in {**rows2[0], **rows3[0]}} for r in rows2 + rows3]
    )
    plot_fig2(out / "paper_fig2.png", images)
    plot_fig3(out / "paper_fig3.png", recons)
    command = "python -m benchmarks.paper_figures" + (" --quick" if args.quick else "")
    write_summary(out, rows2 + rows3, command, shape)
    print((out / "paper_figures.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
