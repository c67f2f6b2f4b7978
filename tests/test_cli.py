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
    "option",
    [
        ["--max-iter", "-5"],
        ["--max-iter", "0"],
        ["--tol", "-1"],
        ["--gamma", "-1"],
        ["--phase-scale", "0"],
        ["--alpha", "foo"],
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

    from pwf_dask import scan_io
    from pwf_dask.simulation import simulate_scan

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
    simulate_scan(scan, preset="demo", shape=(48, 64), angles=12, photons=1e4, progress=False)
    cmd = [sys.executable, "-m", "pwf_dask.cli", "retrieve", str(scan), str(recon), "--max-iter", "100"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ.copy())
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
