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
