"""Does PWF's own warning find the scenes whose data do not carry the phase?

Every PWF retrieval measures what its speckle could carry (:mod:`pwf_dask.calibration.sensitivity`):
the 99th percentile of the retrieved phase's speckle shift lambda L2 |grad phi| / 2 pi p over
the reference's speckle grain, and the reference's visibility with photon noise removed, and
warns below :class:`pwf_dask.calibration.SensitivityLimits`. A user has nothing else to tell a
faint, low result from a faint sample. This runs PWF with every default (lengths calibrated)
on the random geometries of :mod:`benchmarks.random_scenes` in three sets:

- scenes 0-79, those of ``random_scenes.md``, on which the limits were chosen (no holding
  scene flagged, with a margin of 1.5 to the nearest);
- scenes 80-119, drawn from the same ranges and looked at while choosing;
- scenes 120-159, never looked at before this benchmark ran: the held-out check.

A scene holds where its relative phase error inside the sample stays below 0.25 (as in
``random_scenes``). Reported per set: how many hold and fail, how many of each the warning
flags, and the flagged and unflagged failures' gains.

    python -m benchmarks.sensitivity_check [--scenes 160] [--out benchmarks/results]

Writes ``sensitivity_check.md``, ``.csv`` and ``.png`` (about 20 min for 160 scenes on 2 cores).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.random_scenes import run_and_report
from benchmarks.stability import PHASE_ERROR_THRESHOLD
from pwf_dask.calibration import SensitivityLimits

#: (first scene, end, name) of the sets the report keeps apart
SETS = (
    (0, 80, "0-79 (limits chosen here)"),
    (80, 120, "80-119 (seen while choosing)"),
    (120, 160, "120-159 (held out)"),
)


def _set_name(scene: int) -> str:
    for lo, hi, name in SETS:
        if lo <= scene < hi:
            return name
    return f"{SETS[-1][1]}+ (held out)"


def _median(values) -> str:
    values = [v for v in values if np.isfinite(v)]
    return f"{np.median(values):.2f}" if values else "-"


def summary_rows(rows: list[dict]) -> list[dict]:
    """Per set: scenes retrieved, holding, failing, and what the warning flagged of each."""
    out = []
    for name in dict.fromkeys(_set_name(r["scene"]) for r in rows):
        rs = [r for r in rows if _set_name(r["scene"]) == name and not r["refused"]]
        holds = [r for r in rs if r["holds"]]
        fails = [r for r in rs if not r["holds"]]
        flagged_fails = [r for r in fails if r["flagged"]]
        out.append(
            {
                "set": name,
                "retrieved": len(rs),
                "refused": sum(1 for r in rows if _set_name(r["scene"]) == name and r["refused"]),
                "holds": len(holds),
                "flagged_holds": sum(r["flagged"] for r in holds),
                "fails": len(fails),
                "flagged_fails": len(flagged_fails),
                "gain_flagged": _median(r["phase_gain"] for r in flagged_fails),
                "gain_unflagged_fails": _median(r["phase_gain"] for r in fails if not r["flagged"]),
                "nearest_hold": min((r["speckle_shift_over_grain"] for r in holds), default=np.nan),
            }
        )
    return out


def write_report(rows: list[dict], out_dir: str | Path, device: str) -> None:
    limits = SensitivityLimits()
    lines = [
        f"# PWF's sensitivity warning on {len(rows)} random geometries ({device})",
        "",
        "`python -m benchmarks.sensitivity_check`: PWF with every default (coherence lengths calibrated) on the",
        "random geometries of `benchmarks.random_scenes` (one projection each; module docstring: the ranges).",
        "The warning (`RetrievalResult.parameters['sensitivity_warning']`, a run's one-line summary) fires where",
        f"the retrieved phase moves the speckle by under {limits.min_shift_over_grain:g} of its grain (99th",
        f"percentile) or the reference's visibility, photon noise removed, is under {limits.min_visibility:g}.",
        f"A scene holds below a relative phase error of {PHASE_ERROR_THRESHOLD:g} inside the sample.",
        "",
        "| scenes | retrieved | holds | flagged of them | fails | flagged of them | gain, flagged fails "
        "| gain, unflagged fails | smallest shift / grain that holds | calibration refused |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary_rows(rows):
        lines.append(
            f"| {s['set']} | {s['retrieved']} | {s['holds']} | {s['flagged_holds']} | {s['fails']} "
            f"| {s['flagged_fails']} | {s['gain_flagged']} | {s['gain_unflagged_fails']} | {s['nearest_hold']:.3f} "
            f"| {s['refused']} |"
        )
    lines += [
        "",
        "Every scene (phase error / gain; shift / grain and visibility as the retrieval measured them):",
        "",
        "| scene | phase error | gain | shift / grain | visibility | flagged | holds |",
        "|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        if r["refused"]:
            lines.append(f"| {r['scene']} | refused | | | | | |")
            continue
        lines.append(
            f"| {r['scene']} | {r['phase_error']:.3f} | {r['phase_gain']:.2f} | {r['speckle_shift_over_grain']:.4f} "
            f"| {r['speckle_visibility_measured']:.3f} | {'yes' if r['flagged'] else ''} "
            f"| {'yes' if r['holds'] else ''} |"
        )
    Path(out_dir, "sensitivity_check.md").write_text("\n".join(lines) + "\n")


def plot(rows: list[dict], path: str | Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    limits = SensitivityLimits()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (lo, hi, name), marker in zip(SETS, "o^s"):
        pts = [r for r in rows if lo <= r["scene"] < hi and not r["refused"]]
        ax.scatter(
            [max(r["speckle_shift_over_grain"], 1e-4) for r in pts],
            [min(r["phase_error"], 3.0) for r in pts],
            marker=marker,
            c=["C3" if r["flagged"] else "C0" for r in pts],
            label=name,
            alpha=0.8,
        )
    ax.axhline(PHASE_ERROR_THRESHOLD, color="grey", lw=0.8, ls="--")
    ax.axvline(limits.min_shift_over_grain, color="C3", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("retrieved phase's speckle shift / speckle grain (99th percentile)")
    ax.set_ylabel("relative phase error in the sample (capped at 3)")
    ax.set_title("PWF's warning (red: flagged) against the truth")
    legend = ax.legend()
    for handle in legend.legend_handles:  # the marker names the set, the colour the flag
        handle.set_color("grey")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=SETS[-1][1])
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)
    return run_and_report(args.scenes, ("pwf",), args.out, "sensitivity_check", write_report, plot)


if __name__ == "__main__":
    main()
