"""The command line's own behaviour: version, and never writing over what exists (issue #28)."""

import pytest

from pwf_dask import cli


def test_version_is_printed(capsys):
    from pwf_dask import __version__

    with pytest.raises(SystemExit) as exit_:
        cli.main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"pwf-dask {__version__}"


def test_simulate_never_writes_over_an_existing_path(tmp_path, capsys):
    """Issue #28: a folder of the user's files survives; so does an existing store."""
    folder = tmp_path / "notastore"
    folder.mkdir()
    (folder / "thesis.tex").write_text("years of work")
    assert cli.main(["simulate", str(folder), "--preset", "demo", "--shape", "32", "64", "--angles", "3"]) != 0
    err = capsys.readouterr().err.strip()
    assert "already exists" in err and len(err.splitlines()) == 1
    assert (folder / "thesis.tex").read_text() == "years of work"


@pytest.mark.parametrize(
    "option, named",
    [
        (["--photons", "0"], "photons"),  # a given 0 was replaced by the preset's 1e4
        (["--photons", "nan"], "photons"),
        (["--positions", "0"], "position"),
        (["--grain-radius-um", "0"], "diffuser_radius_median_m"),
        (["--axis-offset-px", "1e6"], "rotation_axis_offset_px"),  # the sample never in the frame
        (["--detector-blur-um", "-1"], "detector blur"),
        (["--detector-halo", "1", "5"], "halo fraction"),
        (["--pixel-size-m", "0"], "pixel_size_m"),
        (["--energy-eV", "inf"], "energy_eV"),
        (["--sample-diffuser-distance-m", "2e-3", "--diffuser-upstream-m", "0.05"], "L1 = 0"),
    ],
)
def test_bad_simulate_option_is_refused_in_one_line_and_writes_nothing(tmp_path, capsys, option, named):
    scan = tmp_path / "scan.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--angles", "3", *option]) != 0
    err = capsys.readouterr().err.strip()
    assert named in err and len(err.splitlines()) == 1
    assert not scan.exists()


@pytest.mark.parametrize(
    "option",
    [
        ["--max-iter", "-5"],
        ["--max-iter", "0"],
        ["--tol", "-1"],
        ["--gamma", "-1"],
        ["--phase-scale", "0"],
        ["--alpha", "foo"],
        ["--detector-halo", "2", "3"],
        ["--diffuser-nsr-floor", "-1"],
        ["--diffuser-nsr-floor", "much"],
    ],
)
def test_bad_solver_option_is_refused_before_any_store_is_written(tmp_path, capsys, option):
    """Issue #28: each refused in one line naming the option; no reconstruction store is left
    behind to block the valid re-run."""
    scan = tmp_path / "scan.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "32", "--angles", "2"]) == 0
    capsys.readouterr()
    recon = tmp_path / "recon.zarr"
    assert cli.main(["retrieve", str(scan), str(recon), *option]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    name = option[0].lstrip("-").replace("-", "_")
    assert len(err) == 1 and name in err[0], err
    assert not recon.exists()


def test_a_one_angle_scan_retrieves_and_tomography_refuses_in_one_line(tmp_path, capsys):
    """Issue #28: a single radiograph (the paper's Fig. 2) goes through `retrieve` and `run`;
    `tomo` and `fsc` refuse it in one line, and the retrieved projection stays."""
    import numpy as np
    import xarray as xr

    from pwf_dask.simulation import simulate_scan
    from pwf_dask.stores import scan_io

    two = tmp_path / "two.zarr"
    simulate_scan(two, preset="demo", shape=(48, 64), angles=2, photons=1e4, progress=False)
    ds, _ = scan_io.open_scan(two)
    one = tmp_path / "one.zarr"
    g = scan_io.create_scan(
        one,
        n_positions=1,
        angles_deg=[0.0],
        shape=(48, 64),
        pixel_size_m=float(ds.attrs["pixel_size_m"]),
        dtype=ds.projections.dtype,
        attrs=dict(ds.attrs),
        flat_dark="flat" in ds,
    )
    g["projections"][...] = ds.projections.values[:1, :1]
    g["reference"][...] = ds.reference.values[:1]
    for name in ("flat", "dark"):
        if name in ds:
            g[name][...] = ds[name].values
    scan_io.consolidate(one)
    recon = tmp_path / "one_recon.zarr"
    assert cli.main(["run", str(one), str(recon), "--max-iter", "30"]) == 0
    assert "one angle" in capsys.readouterr().out
    phase = xr.open_zarr(recon).phase.values
    assert phase.shape == (1, 1, 48, 64) and np.isfinite(phase).all() and np.abs(phase).max() > 0.1
    for stage in ("tomo", "fsc"):
        assert cli.main([stage, str(recon)]) == 2
        err = capsys.readouterr().err.strip()
        assert "one angle" in err and len(err.splitlines()) == 1, err
    assert np.array_equal(xr.open_zarr(recon).phase.values, phase)


@pytest.mark.slow
def _default_sigint() -> None:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def test_ctrl_c_during_run_says_what_is_saved_and_the_rerun_completes(tmp_path):
    """Issue #28: SIGINT exits 130 within seconds with the resume message; the same command
    then completes the store."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import numpy as np
    import zarr

    from pwf_dask.simulation import simulate_scan

    scan, recon = tmp_path / "scan.zarr", tmp_path / "recon.zarr"
    # enough projections that the run is still going when the first one is saved: six chains
    # of eight angles, the first saved after a sixth of the work
    simulate_scan(scan, preset="demo", shape=(48, 64), angles=24, photons=1e4, progress=False)
    cmd = [sys.executable, "-m", "pwf_dask.cli", "retrieve", str(scan), str(recon), "--max-iter", "100"]
    # as from a shell: Ctrl-C at its default and not blocked, whatever this process's state
    # after earlier tests (an ignored or blocked SIGINT is inherited by the child)
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=os.environ.copy(),
        preexec_fn=_default_sigint,
    )
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if (zarr.open_group(str(recon), mode="r", use_consolidated=False)["iterations"][...] >= 0).any():
                break
        except Exception:  # noqa: BLE001 - the store is not there yet
            pass
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be interrupted"
    proc.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and time.monotonic() - t0 < 10, (proc.returncode, err[-500:])
    message = err.strip().splitlines()[-1]
    assert "interrupted" in message and "projections saved" in message and "run the same command" in message
    assert cli.main(["retrieve", str(scan), str(recon), "--max-iter", "100"]) == 0
    assert (zarr.open_group(str(recon), mode="r")["iterations"][...] >= 0).all()
    assert np.isfinite(zarr.open_group(str(recon), mode="r")["phase"][...]).all()


def test_every_option_has_help_and_defaults_are_shown(capsys):
    """Issue #28: no option or positional without a text; --help shows the defaults."""
    import argparse

    parser = cli.build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name, sub in commands.items():
        for action in sub._actions:
            if not isinstance(action, argparse._HelpAction):
                assert action.help, (name, action.dest)
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 2000)" in text and "threads (default)" in text and "(default: auto)" in text


def test_a_nan_frame_is_refused_naming_its_position_and_angle(tmp_path, capsys):
    """Issue #28: the refusal names the frame, in one line with exit status 2."""
    import numpy as np
    import zarr

    scan = tmp_path / "scan.zarr"
    args = ["simulate", str(scan), "--preset", "demo", "--shape", "32", "32", "--angles", "4", "--corrected"]
    assert cli.main(args) == 0
    g = zarr.open_group(str(scan), mode="r+")
    frame = g["projections"][1, 2]
    frame[5, 6] = np.nan
    g["projections"][1, 2] = frame
    capsys.readouterr()
    assert cli.main(["retrieve", str(scan), str(tmp_path / "recon.zarr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "projections at position 1, angle 2 (120 deg) has non-finite values" in err[0], err
    assert not (tmp_path / "recon.zarr").exists()


@pytest.fixture(scope="module")
def small_recon(tmp_path_factory):
    """A 32 x 48, 4-angle, K = 2 demo scan through `run` (20 iterations: values do not matter)."""
    d = tmp_path_factory.mktemp("small")
    scan, recon = d / "scan.zarr", d / "recon.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "48", "--angles", "4"]) == 0
    assert cli.main(["run", str(scan), str(recon), "--max-iter", "20", "--figures", str(d / "figs")]) == 0
    return recon


def test_run_writes_the_preview_figures_with_the_real_residual(small_recon):
    """Issue #28: `run` ends with `preview`; the residual panel shows the stored residual."""
    import numpy as np
    import xarray as xr

    figs = small_recon.parent / "figs"
    assert {p.name for p in figs.iterdir()} == {"projection.png", "tomograms.png", "fsc.png"}
    ds = xr.open_zarr(small_recon)
    residual = ds["preview_residual"][0].values
    rmse = float(ds["residual_rmse"][0, 0])
    assert np.isfinite(residual).all() and np.sqrt(np.mean(residual**2)) == pytest.approx(rmse, rel=1e-3)
    assert ds["preview_residual"].attrs["units"] == "percent"


def test_preview_into_a_chosen_folder(small_recon, tmp_path, capsys):
    assert cli.main(["preview", str(small_recon), str(tmp_path / "p")]) == 0
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["fsc.png", "projection.png", "tomograms.png"]


@pytest.mark.parametrize("layout", ["stack", "slices"])
def test_export_tiff_values_and_voxel_size_match_the_store(small_recon, tmp_path, capsys, layout):
    """Issue #28: float32 TIFF, values equal to the store's, the voxel size in um in the
    resolution tags (what Fiji reads), and existing files are never written over."""
    import numpy as np
    import tifffile
    import xarray as xr

    ds = xr.open_zarr(small_recon)
    out = tmp_path / "tif"
    assert cli.main(["export", str(small_recon), str(out), "--format", "tiff", "--layout", layout]) == 0
    voxel_um = ds.attrs["pixel_size_m"] * 1e6
    for name in ("delta", "beta"):
        for p in range(2):
            if layout == "stack":
                f = out / f"{name}_position{p}.tif"
                got = tifffile.imread(f)
            else:
                f = out / f"{name}_position{p}" / "y0010.tif"
                got = tifffile.imread(f)[None]
            want = ds[name][p].values if layout == "stack" else ds[name][p, 10:11].values
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, want.astype(np.float32))
            with tifffile.TiffFile(f) as tif:
                num, den = tif.pages[0].tags["XResolution"].value
                assert num / den == pytest.approx(1 / voxel_um, rel=1e-5)
                assert tif.imagej_metadata["unit"] == "um"
    before = sorted(out.rglob("*"))
    stamp = before[0].stat().st_mtime_ns
    assert cli.main(["export", str(small_recon), str(out), "--layout", layout]) == 2
    assert "already exists" in capsys.readouterr().err and sorted(out.rglob("*")) == before
    assert before[0].stat().st_mtime_ns == stamp


def test_a_run_failing_before_its_first_projection_leaves_no_store(tmp_path, capsys, monkeypatch):
    """Issue #28: a store with nothing in it would refuse the corrected re-run; a store with
    saved projections is kept for the resume."""
    from pwf_dask.pipeline import workflow

    scan, recon = tmp_path / "scan.zarr", tmp_path / "recon.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "32", "--angles", "2"]) == 0

    def lost(*args, **kwargs):
        raise RuntimeError("device lost")

    monkeypatch.setattr(workflow, "_retrieve_chain", lost)
    capsys.readouterr()
    assert cli.main(["retrieve", str(scan), str(recon), "--max-iter", "10"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == "pwf-dask retrieve: error: device lost"
    assert not recon.exists()
    monkeypatch.undo()
    assert cli.main(["retrieve", str(scan), str(recon), "--max-iter", "10"]) == 0


@pytest.mark.parametrize("center_um", ["nan", "1e9"])
def test_tomo_refuses_a_centre_off_the_frame_and_keeps_the_tomograms(tmp_path, capsys, center_um):
    """A given centre that is NaN or off the detector made NaN or empty tomograms (exit 0)."""
    import numpy as np
    import xarray as xr

    scan, recon = tmp_path / "scan.zarr", tmp_path / "recon.zarr"
    small = ["--preset", "demo", "--shape", "32", "64", "--angles", "3", "--positions", "1"]
    assert cli.main(["simulate", str(scan), *small]) == 0
    assert cli.main(["-q", "run", str(scan), str(recon), "--max-iter", "5", "--center-um", "1.6"]) == 0
    before = xr.open_zarr(recon).delta.values
    capsys.readouterr()
    assert cli.main(["tomo", str(recon), "--center-um", center_um]) != 0
    err = capsys.readouterr().err.strip()
    assert "inside the frame" in err and len(err.splitlines()) == 1
    np.testing.assert_array_equal(xr.open_zarr(recon).delta.values, before)


def test_a_reconstruction_inside_the_scan_store_is_refused_and_fsc_names_a_scan_store(tmp_path, capsys):
    """The reconstruction (and its figures) went inside the scan store, changing the input."""
    scan = tmp_path / "scan.zarr"
    assert cli.main(["simulate", str(scan), "--preset", "demo", "--shape", "32", "64", "--angles", "3"]) == 0
    before = sorted(p.name for p in scan.iterdir())
    capsys.readouterr()
    for recon in (scan, scan / "recon.zarr"):
        assert cli.main(["run", str(scan), str(recon), "--max-iter", "5"]) != 0
        err = capsys.readouterr().err.strip()
        assert "must lie outside the scan store" in err and len(err.splitlines()) == 1
    assert sorted(p.name for p in scan.iterdir()) == before
    assert cli.main(["fsc", str(scan)]) != 0
    assert "not a reconstruction store" in capsys.readouterr().err


def test_a_librarys_warning_of_several_lines_is_printed_as_its_first_line():
    import io

    out = io.StringIO()
    cli._one_line_warning(UserWarning("Failed to open the store.\nTo silence it:\n1. ..."), UserWarning, "f", 1, out)
    assert out.getvalue() == "pwf-dask: warning: Failed to open the store.\n"


def test_slice_background_choices_are_the_tomography_modes():
    """The CLI names its choices without importing the numerics; they are the modes
    ``tomography.SLICE_BACKGROUNDS`` defines, its default the stage's."""
    import argparse

    from pwf_dask.tomo import tomography

    parser = cli.build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    for command in ("tomo", "run"):
        action = next(a for a in commands[command]._actions if "--slice-background" in a.option_strings)
        assert sorted(action.choices) == sorted(tomography.SLICE_BACKGROUNDS), command
        assert action.default == tomography.DEFAULT_SLICE_BACKGROUND, command
