"""PWF beside the speckle-tracking methods on one angle of your own scan: where each holds.

    python -m workflows.compare_methods SCAN.zarr --angle 0 --out compare/ [--methods pwf umpa lcs gf mist]

PWF and GF use one speckle image (diffuser position 0); UMPA, LCS and MIST combine the scan's K
diffuser positions of the angle (LCS needs K >= 3, MIST K >= 4; a method the scan cannot feed
is skipped with the reason). Real data has no ground truth, so the table
reports what can be measured on it: each method's phase and attenuation against PWF's (slope
and correlation over the frame; nan where a method has no such channel, as GF has no
attenuation), the phase range, the PWF residual, and the wall time. The figure puts the
phases side by side on one colour scale. A method that disagrees with the others where they
agree is the one to distrust; docs/validation.md says where each fails on simulated truth.

Every option of ``retrieve_projection`` that the scan does not fix keeps its default: this is the
comparison a user gets without tuning.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from pwf_dask.baselines.tracking import MIN_POSITIONS
from pwf_dask.retrieval import retrieve_projection
from pwf_dask.stores import scan_io

METHODS = ("pwf", "umpa", "lcs", "gf", "mist")
MULTI_IMAGE = ("umpa", "lcs", "mist")


def corrected_frames(ds, info: scan_io.ScanInfo, angle: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample and reference frames of one angle, every position, flat/dark-corrected: (K, y, x) each."""
    flat = ds["flat"].values if info.has_flat else None
    dark = ds["dark"].values if info.has_dark else None
    sample = scan_io.correct(ds["projections"][:, angle].values, flat, dark, info.flat_dark_corrected)
    reference = scan_io.correct(ds["reference"].values, flat, dark, info.flat_dark_corrected)
    return sample, reference


def agreement(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Least-squares slope of ``a`` on ``b`` and their correlation, both centred over the frame."""
    a = a - a.mean()
    b = b - b.mean()
    aa, bb = float(np.sum(a * a)), float(np.sum(b * b))
    if aa == 0 or bb == 0:  # a method without this channel (GF has no attenuation)
        return float("nan"), float("nan")
    return float(np.sum(a * b) / bb), float(np.sum(a * b) / np.sqrt(aa * bb))


def retrieve(method: str, sample, reference, geometry: dict):
    """One method's result, or the reason it cannot run on this scan."""
    if method in MIN_POSITIONS and sample.shape[0] < MIN_POSITIONS[method]:
        return f"needs K >= {MIN_POSITIONS[method]} diffuser positions, the scan has {sample.shape[0]}"
    k = slice(None) if method in MULTI_IMAGE else 0
    return retrieve_projection(sample[k], reference[k], method=method, **geometry)


def compare(scan_path: str, angle: int, methods: list[str]) -> tuple[list[dict], dict]:
    """Rows of the comparison table and each method's phase (skipped methods have none)."""
    ds, info = scan_io.open_scan(scan_path)
    if not 0 <= angle < len(info.angles_deg):
        raise ValueError(f"--angle {angle}: the scan has angles 0..{len(info.angles_deg) - 1}")
    sample, reference = corrected_frames(ds, info, angle)
    geometry = dict(
        energy_eV=info.energy_eV,
        pixel_size_m=info.pixel_size_m,
        sample_diffuser_distance_m=info.sample_diffuser_distance_m,
        diffuser_detector_distance_m=info.diffuser_detector_distance_m,
    )
    if info.coherence_length_x_m:
        geometry.update(coherence_length_x_m=info.coherence_length_x_m, coherence_length_y_m=info.coherence_length_y_m)
    rows, phases, results = [], {}, {}
    for method in methods:
        t0 = time.perf_counter()
        res = retrieve(method, sample, reference, geometry)
        wall = time.perf_counter() - t0
        if isinstance(res, str):
            rows.append({"method": method, "status": f"skipped: {res}"})
            continue
        results[method] = res
        phases[method] = np.asarray(res.phase)
        rows.append({"method": method, "status": "ran", "wall_s": wall, "phase_range_rad": float(np.ptp(res.phase))})
    if "pwf" in results:
        pwf = results["pwf"]
        for row in rows:
            res = results.get(row["method"])
            if res is None:
                continue
            row["phase_slope_vs_pwf"], row["phase_corr_vs_pwf"] = agreement(
                np.asarray(res.phase), np.asarray(pwf.phase)
            )
            row["attenuation_corr_vs_pwf"] = agreement(np.asarray(res.attenuation), np.asarray(pwf.attenuation))[1]
        rows[[r["method"] for r in rows].index("pwf")].update(
            iterations=pwf.iterations, converged=pwf.converged, residual_rmse_pct=pwf.residual_rmse
        )
    return rows, phases


def write_table(rows: list[dict], path: Path, scan_path: str, angle: int) -> None:
    cols = ["method", "status", "wall_s", "phase_range_rad", "phase_slope_vs_pwf", "phase_corr_vs_pwf",
            "attenuation_corr_vs_pwf", "iterations", "converged", "residual_rmse_pct"]  # fmt: skip
    lines = [
        f"# Methods side by side: {scan_path}, angle index {angle}",
        "",
        "Slopes and correlations are against PWF over the whole frame (no ground truth on real data).",
        "",
        "| " + " | ".join(cols) + " |",
        "|" + "---|" * len(cols),
    ]
    for r in rows:
        cells = [f"{r[c]:.4g}" if isinstance(r.get(c), float) else str(r.get(c, "")) for c in cols]
        lines.append("| " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


def write_figure(phases: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo = min(float(np.percentile(p, 1)) for p in phases.values())
    hi = max(float(np.percentile(p, 99)) for p in phases.values())
    fig, axes = plt.subplots(1, len(phases), figsize=(3.2 * len(phases), 3.4), squeeze=False)
    for ax, (method, phase) in zip(axes[0], phases.items()):
        im = ax.imshow(phase, cmap="gray", vmin=lo, vmax=hi)
        ax.set_title(f"{method.upper()} phase")
        ax.axis("off")
    fig.colorbar(im, ax=axes[0].tolist(), label="phase (rad)", shrink=0.8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scan", help="a scan store (pwf-dask ingest or simulate)")
    p.add_argument("--angle", type=int, default=0, help="index of the angle to compare (default 0)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS, help="methods to run")
    p.add_argument("--out", default="compare_methods", help="folder of the table and figure (created)")
    args = p.parse_args(argv)
    try:
        rows, phases = compare(args.scan, args.angle, args.methods)
    except ValueError as exc:
        print(f"compare_methods: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_table(rows, out / "methods.md", args.scan, args.angle)
    if phases:
        write_figure(phases, out / "phases.png")
    print((out / "methods.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
