"""The retrieval's options (issue #30): one dataclass, each default defined once, read by
retrieve_projection, the scan workflow and the CLI alike (docs/scan-format.md §4)."""

import dataclasses

import numpy as np
import pytest

from pwf_dask import RetrievalOptions, cli, retrieve_projection
from pwf_dask.options import DEFAULTS, OPTION_NAMES
from pwf_dask.retrieval import parse_alpha
from pwf_dask.simulation import SpeckleSetup, simulate_projection

#: the keyword options the outside contract names for retrieve_projection
CONTRACT_OPTIONS = {"method", "max_iter", "tol", "gamma", "alpha", "coherence_length_x_m", "coherence_length_y_m"}


@pytest.fixture(scope="module")
def sim():
    return simulate_projection(SpeckleSetup(shape=(64, 64)), seed=2)


def test_the_contracts_keywords_are_options():
    assert CONTRACT_OPTIONS <= set(OPTION_NAMES)


def test_an_options_object_gives_what_its_keywords_give(sim):
    """Bit for bit, and keywords beside the object replace its fields."""
    coherence = dict(coherence_length_x_m=sim.coherence_length_x_m, coherence_length_y_m=sim.coherence_length_y_m)
    by_keywords = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), max_iter=25, gamma=2.0, **coherence)
    opts = RetrievalOptions(max_iter=25, gamma=3.0, **coherence)
    by_object = retrieve_projection(sim.sample, sim.reference, **sim.geometry(), options=opts, gamma=2.0)
    assert np.array_equal(by_keywords.phase, by_object.phase)
    assert np.array_equal(by_keywords.attenuation, by_object.attenuation)
    assert by_object.parameters["gamma"] == 2.0 and by_object.iterations == by_keywords.iterations == 25
    assert opts.gamma == 3.0  # the caller's object is not changed


def test_a_misspelt_option_is_refused_in_one_line_naming_the_nearest(sim):
    with pytest.raises(TypeError, match=r"unknown retrieval option 'max_iters' \(did you mean 'max_iter'\?\)"):
        retrieve_projection(sim.sample, sim.reference, **sim.geometry(), max_iters=10)
    with pytest.raises(TypeError, match="unknown retrieval option 'xyzzy'$"):
        RetrievalOptions.from_keywords(xyzzy=1)


def test_a_scan_with_a_misspelt_option_is_refused_before_anything_is_written(tmp_path):
    from pwf_dask.pipeline.workflow import retrieve_scan

    recon = tmp_path / "r.zarr"
    with pytest.raises(TypeError, match="did you mean 'diffuser_model'"):
        retrieve_scan(tmp_path / "no-scan-needed.zarr", recon, diffuser_modle="zero-phase")
    assert not recon.exists()


def test_the_clis_defaults_are_the_options_defaults():
    """Every retrieval option the CLI offers defaults to DEFAULTS' value (nothing restated)."""
    args = cli.build_parser().parse_args(["retrieve", "scan.zarr", "recon.zarr"])
    given = cli.retrieval_kwargs(args)
    shared = {k: v for k, v in given.items() if k in OPTION_NAMES}
    assert len(shared) >= 13
    for name, value in shared.items():
        default = getattr(DEFAULTS, name)
        if name == "alpha":
            value, default = parse_alpha(value), parse_alpha(default)
        assert value == default, name


def test_every_option_has_a_default_and_the_defaults_are_frozen():
    assert all(f.default is not dataclasses.MISSING for f in dataclasses.fields(RetrievalOptions))
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULTS.max_iter = 1


def test_an_unknown_stationary_terms_is_refused_before_anything_is_written(tmp_path):
    """``stationary_terms`` (the stop's J test on J, or on J or its data term) takes two
    values; anything else is one line naming the option, in a scan before its store exists."""
    from pwf_dask.pipeline.workflow import retrieve_scan

    args = cli.build_parser().parse_args(["retrieve", "s.zarr", "r.zarr", "--stationary-terms", "j-or-data"])
    assert cli.retrieval_kwargs(args)["stationary_terms"] == "j-or-data"
    recon = tmp_path / "r.zarr"
    with pytest.raises(ValueError, match="^stationary_terms must be one of j, j-or-data, got 'data'$"):
        retrieve_scan(tmp_path / "no-scan-needed.zarr", recon, stationary_terms="data")
    assert not recon.exists()
