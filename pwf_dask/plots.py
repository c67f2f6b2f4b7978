"""Figures a user looks at: projection panels (speckle, phase, attenuation, residual),
tomogram slices, FSC curves and benchmark charts."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (headless workers, CI)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path) -> Path:
    """Lay out, write at 90 dpi and close (figures are made in loops; close frees them)."""
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")
    pyplot().close(fig)
    return Path(path)


def projection_panels(
    path: str | Path, *, sample, reference, result, truth_phase=None, truth_attenuation=None, pixel_size_m: float = 1.0
) -> Path:
    """PNG of the speckle images, retrieved phase and attenuation, residual (and the truth)."""
    plt = pyplot()
    from .backend import to_numpy

    panels = [
        ("sample speckle", to_numpy(sample), "gray", ""),
        ("reference speckle", to_numpy(reference), "gray", ""),
        ("PWF phase", to_numpy(result.phase), "viridis", "rad"),
        ("PWF attenuation", to_numpy(result.attenuation), "magma", ""),
        ("residual |y - f|", to_numpy(result.residual), "inferno", "% of mean reference"),
    ]
    if truth_phase is not None:
        panels.insert(3, ("true phase", np.asarray(truth_phase), "viridis", "rad"))
    if truth_attenuation is not None:
        panels.insert(5, ("true attenuation", np.asarray(truth_attenuation), "magma", ""))
    ncol = 4
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 3.6 * nrow), squeeze=False)
    for ax, (title, img, cmap, unit) in zip(axes.flat, panels):
        ny, nx = img.shape
        ext_mm = [0, nx * pixel_size_m * 1e3, ny * pixel_size_m * 1e3, 0]
        vmin, vmax = np.percentile(img, [0.5, 99.5])
        im = ax.imshow(img, cmap=cmap, vmin=vmin, vmax=vmax, extent=ext_mm)
        ax.set_title(title)
        ax.set_xlabel("x (mm)")
        fig.colorbar(im, ax=ax, shrink=0.8, label=unit)
    for ax in list(axes.flat)[len(panels) :]:
        ax.axis("off")
    fig.suptitle(
        f"PWF: {result.iterations} iterations, converged={result.converged}, "
        f"residual RMSE {result.residual_rmse:.2f} % of the mean reference"
    )
    return save_figure(fig, path)


def bench_ratio_plot(path: str | Path, rows: list[dict]) -> Path:
    """Iteration time / FFT time per size, one line per variant (dotted: the line-by-line port)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4))
    for variant, threads in sorted({(r["variant"], r.get("fft_workers", 1)) for r in rows}):
        sel = [r for r in rows if r["variant"] == variant and r.get("fft_workers", 1) == threads]
        label = f"{variant}, {threads} thread{'s' if int(threads) > 1 else ''}"
        (line,) = ax.plot([r["pixels"] for r in sel], [r["ratio"] for r in sel], "o-", label=label)
        printed = [
            (r["pixels"], r["literal_ratio"]) for r in sel if math.isfinite(float(r.get("literal_ratio", "nan")))
        ]
        if printed:
            ax.plot(*zip(*printed), "x:", color=line.get_color())
    ax.plot([], [], "kx:", label="Algorithms S1/S2 as printed (same variant)")
    ax.set_xscale("log")
    ax.set_xlabel("pixels per projection")
    ax.set_ylabel("PWF iteration time / complex64 FFT time")
    ax.axhline(20, color="gray", ls="--", lw=1)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, path)


def tomogram_panels(path: str | Path, recon) -> Path:
    """delta and beta slices (middle row, every position) of a reconstruction dataset."""
    plt = pyplot()
    npos = recon.sizes["position"]
    mid = recon.sizes["y"] // 2
    fig, axes = plt.subplots(2, npos, figsize=(4.2 * npos, 7.2), squeeze=False)
    u = recon["u"].values * 1e6
    v = recon["v"].values * 1e6
    ext = [u[0], u[-1], v[0], v[-1]]
    for p in range(npos):
        for row, (name, cmap) in enumerate((("delta", "gray"), ("beta", "magma"))):
            img = recon[name][p, mid].values
            ax = axes[row, p]
            lo, hi = np.percentile(img, [1, 99.8])
            im = ax.imshow(img, origin="lower", cmap=cmap, extent=ext, vmin=lo, vmax=hi)
            ax.set_title(f"{name}, position {p}, y = {recon['y'].values[mid] * 1e6:.1f} um")
            ax.set_xlabel("u (um)")
            ax.set_ylabel("v (um)")
            fig.colorbar(im, ax=ax, shrink=0.8)
    return save_figure(fig, path)


def fsc_plot(path: str | Path, recon) -> Path:
    """FSC curves with their criteria and resolutions."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    f = recon["frequency"].values * 1e-6
    for ax, name in zip(axes, ("delta", "beta")):
        da = recon[f"fsc_{name}"]
        for i in range(da.sizes["split"]):
            ax.plot(f, da[i].values, color="C0", alpha=0.4)
        ax.plot(
            f,
            da.values.mean(axis=0),
            color="C0",
            lw=2,
            label=f"{da.attrs['split']}: {da.attrs['resolution_m'] * 1e6:.2f} um at {da.attrs['criterion']}",
        )
        ax.axhline(0.25, color="C0", ls=":")
        if f"fsc_{name}_truth" in recon:
            t = recon[f"fsc_{name}_truth"]
            ax.plot(
                f,
                t.values.mean(axis=0),
                color="C1",
                lw=2,
                label=f"vs truth: {t.attrs['resolution_m'] * 1e6:.2f} um at 1/2",
            )
            ax.axhline(0.5, color="C1", ls=":")
        ax.set_xlabel("spatial frequency (cycles/um)")
        ax.set_ylabel("FSC")
        ax.set_title(name)
        ax.set_ylim(-0.2, 1.05)
        ax.legend(fontsize=8)
    return save_figure(fig, path)
