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
