"""Coherence-length calibration across diffusers and geometries: the template fit against the
paper's Gaussian alone (docs/methods.md, "Coherence calibration"; issue #27).

One 384 x 384 reference per case (seed 1), fully coherent speckle of a diffuser blurred by the
IOTF of known lengths (3.47 / 4.31 um unless the case says otherwise), pixel-integrated, with
Poisson noise. Cases: median grain radius 1, 3.2 (P3000) and 5 um, each at the paper's L2 = 20
mm, at 10 and 100 mm, and at 1e3 and 1e5 photons per pixel; then P3000 at 2/2.5 and 8/8 um
coherence lengths, 20 keV, 1 um pixels and a diffuser 10 mm upstream of the sample; and the
regime of the issue's real data (25 keV, 6.5 um pixels, 0.7 m, 50 mm upstream, 25 / 20 um
coherence) with P3000, P2000, P1200 and P800 grains (0.5-1.7 px across in radius).

Four diffuser families, two of them outside the templates' own (mixed round and faceted grains):

- ``spheres``: :mod:`pwf_dask.physics.diffusers` spherical grains, FEPA spread (the simulator's default);
- ``faceted``: pyramidal grains only (crushed SiC);
- ``rough``: spheres of a wider size spread (0.6) with a sub-pixel surface texture (0.5 um rms,
  0.15 um correlation): "structure below the pixel";
- ``blobs``: thresholded smooth Gaussian random fields: grains without sharp edges, whose
  speckle spectrum falls like a Gaussian and is expected to read long.

    python -m benchmarks.calibration_sweep [--out benchmarks/results]

Writes ``calibration_sweep.md`` and ``.csv`` (about 35 s on 2 cores, session 49).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from scipy import ndimage

from benchmarks.frame_size import STRIP_SETUP
from benchmarks.reporting import device_name, write_rows_csv
from pwf_dask.calibration import fit_coherence_lengths
from pwf_dask.physics import diffusers
from pwf_dask.physics.diffusers import grit_radius_m
from pwf_dask.physics.geometry import GEOMETRY_KEYS
from pwf_dask.simulation import SpeckleSetup, SpeckleSimulator

SHAPE = (384, 384)
#: the optics of :data:`benchmarks.frame_size.STRIP_SETUP`, the regime of the issue's real data
REAL_DATA = {
    name: getattr(STRIP_SETUP, name)
    for name in (*GEOMETRY_KEYS, "diffuser_upstream_m", "coherence_length_x_m", "coherence_length_y_m")
}
REAL_DATA_GRITS = ("P3000", "P2000", "P1200", "P800")
FAMILIES = ("spheres", "faceted", "rough", "blobs")


def rough_spheres(shape, spacing_m, rng, radius_m, layers):
    t = diffusers.grain_thickness(shape, spacing_m, rng, radius_median_m=radius_m, radius_spread=0.6, layers=layers)
    texture = ndimage.gaussian_filter(rng.standard_normal(shape), 0.15e-6 / spacing_m, mode="wrap")
    texture *= 0.5e-6 / texture.std()
    return np.clip(t + texture * (t > 0), 0, None)


def blobs(shape, spacing_m, rng, radius_m, layers):
    out = np.zeros(shape)
    for _ in range(int(layers)):
        g = ndimage.gaussian_filter(rng.standard_normal(shape), 0.7 * radius_m / spacing_m, mode="wrap")
        out += np.clip(g / g.std() - 0.3, 0, None) * 1.5 * radius_m
    return out


def reference(setup: SpeckleSetup, family: str, seed: int = 1) -> np.ndarray:
    """One noisy reference of ``setup`` with the diffuser of ``family``."""
    if family in ("spheres", "faceted"):
        sim = SpeckleSimulator(replace(setup, diffuser_grain_shape=family), seed=seed)
    else:
        sim = SpeckleSimulator(setup, seed=seed)
        make = rough_spheres if family == "rough" else blobs
        sim.diffuser_thickness = make(
            sim.fine_shape, sim.spacing, np.random.default_rng(seed + 777), setup.diffuser_radius_median_m, 4
        )
    return sim.reference()


def cases() -> list[tuple[str, dict]]:
    out = []
    for r_um in (1.0, 3.2, 5.0):
        r = dict(diffuser_radius_median_m=r_um * 1e-6)
        out += [
            (f"r {r_um} um", r),
            (f"r {r_um} um, L2 10 mm", {**r, "diffuser_detector_distance_m": 10e-3}),
            (f"r {r_um} um, L2 100 mm", {**r, "diffuser_detector_distance_m": 100e-3}),
            (f"r {r_um} um, 1e3 ph/px", {**r, "photons": 1e3}),
            (f"r {r_um} um, 1e5 ph/px", {**r, "photons": 1e5}),
        ]
    p3000 = dict(diffuser_radius_median_m=3.25e-6)
    out += [
        ("P3000, coherence 2 / 2.5 um", {**p3000, "coherence_length_x_m": 2e-6, "coherence_length_y_m": 2.5e-6}),
        ("P3000, coherence 8 / 8 um", {**p3000, "coherence_length_x_m": 8e-6, "coherence_length_y_m": 8e-6}),
        ("P3000, 20 keV", {**p3000, "energy_eV": 20_000.0}),
        ("P3000, 1 um pixels", {**p3000, "pixel_size_m": 1e-6}),
        ("P3000, 10 mm upstream", {**p3000, "sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 10e-3}),
    ]
    # the regime of the real data (benchmarks.frame_size's strip): 25 keV, 6.5 um pixels,
    # the diffuser 50 mm upstream of the sample, L2 = 0.7 m, 25 / 20 um coherence: grains under 2 px
    for grit in REAL_DATA_GRITS:
        out.append((f"real-data regime, {grit}", {**REAL_DATA, "diffuser_radius_median_m": grit_radius_m(grit)}))
    return out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    rows = []
    for family in FAMILIES:
        for label, kw in cases():
            setup = SpeckleSetup(shape=SHAPE, **kw)
            ref = reference(setup, family)
            truth = (setup.coherence_length_x_m, setup.coherence_length_y_m)
            distance = setup.diffuser_detector_distance_m + setup.diffuser_upstream_m
            row = {"family": family, "case": label}
            for method in ("template", "gaussian"):
                t0 = time.perf_counter()
                fit = fit_coherence_lengths(
                    ref,
                    setup.pixel_size_m,
                    energy_eV=setup.energy_eV,
                    diffuser_detector_distance_m=distance,
                    method=method,
                )
                row[f"{method}_x_error"] = fit.x_m / truth[0] - 1
                row[f"{method}_y_error"] = fit.y_m / truth[1] - 1
                row[f"{method}_s"] = time.perf_counter() - t0
                if method == "template":
                    row["template"] = fit.template
                    row["grain_radius_um"] = fit.grain_radius_m * 1e6 if fit.grain_radius_m else float("nan")
            rows.append(row)
            print(
                f"{family:8s} {label:32s} template {row['template_x_error']:+.1%} / {row['template_y_error']:+.1%}  "
                f"gaussian {row['gaussian_x_error']:+.1%} / {row['gaussian_y_error']:+.1%}",
                flush=True,
            )
    out = write_rows_csv(args.out, "calibration_sweep.csv", rows)
    lines = [
        f"# Coherence-length calibration across diffusers and geometries ({device_name(np)})",
        "",
        "`python -m benchmarks.calibration_sweep`: 384 x 384 references, seed 1, fitted / true - 1 along x / y.",
        "The template fit (`fit_coherence_lengths`, the default) against the paper's Gaussian alone. Its",
        "templates are mixed round and faceted grains; `rough` and `blobs` are diffusers outside them. The",
        "template fit's cold-start time (simulating its templates at a new geometry) is in `template_s`.",
        "",
    ]
    for family in FAMILIES:
        sel = [r for r in rows if r["family"] == family]
        worst_t = max(max(abs(r["template_x_error"]), abs(r["template_y_error"])) for r in sel)
        worst_g = max(max(abs(r["gaussian_x_error"]), abs(r["gaussian_y_error"])) for r in sel)
        lines += [
            f"## {family}: largest error template {worst_t:.1%}, Gaussian alone {worst_g:.1%}",
            "",
            "| case | template x / y | chosen | Gaussian alone x / y |",
            "|---|---|---|---|",
        ]
        for r in sel:
            chosen = r["template"] + (f" {r['grain_radius_um']:.2f} um" if r["template"] == "mixed grains" else "")
            lines.append(
                f"| {r['case']} | {r['template_x_error']:+.1%} / {r['template_y_error']:+.1%} | {chosen} "
                f"| {r['gaussian_x_error']:+.1%} / {r['gaussian_y_error']:+.1%} |"
            )
        lines.append("")
    (out / "calibration_sweep.md").write_text("\n".join(lines))
    return rows


if __name__ == "__main__":
    main()
