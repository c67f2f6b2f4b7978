"""The extended source of the simulator (:mod:`pwf_dask.physics.source`): partial coherence as
an incoherent sum over the source's tilted waves, against an explicit tilt and the paper's IPSF."""

from dataclasses import replace

import numpy as np
import pytest

from pwf_dask.physics import optics, source
from pwf_dask.simulation import SpeckleSetup
from pwf_dask.simulation.phantoms import default_phantom
from pwf_dask.simulation.speckle import SpeckleSimulator, source_geometry

UPSTREAM = {"sample_diffuser_distance_m": 0.0, "diffuser_upstream_m": 0.05}


def _scene(shape=(48, 64), margin_px=16, **fields):
    setup = SpeckleSetup(shape=shape, margin_px=margin_px, **fields)
    sim = SpeckleSimulator(setup, seed=1)
    p = setup.pixel_size_m
    phantom = default_phantom(shape[1] * p, np.random.default_rng(2), height_m=shape[0] * p)
    return setup, sim, sim.sample_field(phantom)[0], sim.diffuser()


def test_node_transfers_sum_to_the_iotf():
    freq = np.fft.rfftfreq(200, 0.325e-6)
    sigma = source.ipsf_sigma_m(3.47e-6)
    total = source.node_transfer(freq, sigma, 7).sum(axis=0)
    iotf = optics.iotf((1, 200), 0.325e-6, 3.47e-6, 0.0)[0]
    np.testing.assert_allclose(total.real, iotf, atol=1e-9)
    np.testing.assert_allclose(total.imag, 0.0, atol=1e-9)
    # the nodes are the conditional means of equal-probability bins: symmetric, mean 0
    nodes = source.source_nodes(6)
    np.testing.assert_allclose(nodes, -nodes[::-1], atol=1e-12)
    assert nodes.mean() == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("fields", [{}, UPSTREAM], ids=["L1 3 mm", "50 mm upstream"])
def test_one_tilted_wave_gives_the_shift_formula(fields):
    """A plane wave tilted by theta through diffuser and sample, propagated by the angular
    spectrum, equals S[theta z_ref] |P2{t S[theta h] x}|^2 (fields band-limited so that |v|^2
    does not alias on the grid); h of the other sign, or no shift, is far off."""
    setup, sim, xs, diffuser = _scene(**fields)
    ny, nx = sim.fine_shape
    low = (np.abs(np.fft.fftfreq(ny))[:, None] > 0.12) | (np.abs(np.fft.fftfreq(nx))[None, :] > 0.12)

    def band_limited(f):
        spec = np.fft.fft2(f)
        spec[low] = 0
        return np.fft.ifft2(spec)

    def propagate(f, kernel):
        return np.fft.ifft2(np.fft.fft2(f) * kernel)

    xs, diffuser = band_limited(xs), band_limited(diffuser)
    m = 12  # cycles over the grid: the tilted wave is periodic on it
    theta = sim.wavelength * m / (nx * sim.spacing)
    tilt = np.exp(2j * np.pi * m * np.arange(nx) / nx)[None, :]
    if fields:
        explicit = np.abs(propagate(propagate(tilt * diffuser, sim.kernel_upstream) * xs, sim.kernel2)) ** 2
    else:
        explicit = np.abs(propagate(propagate(tilt * xs, sim.kernel1) * diffuser, sim.kernel2)) ** 2
    carrier, lit = sim._carrier_and_sample(xs, diffuser)
    z_ref, h = source_geometry(setup)
    fx = np.fft.fftfreq(nx, sim.spacing)

    def formula(sign):
        a = np.fft.ifft2(np.fft.fft2(lit) * source.shift_ramp(fx, sign * theta * h)[None, :]) * carrier
        i0 = np.abs(propagate(a, sim.kernel2)) ** 2
        return np.fft.ifft2(np.fft.fft2(i0) * source.shift_ramp(fx, theta * z_ref)[None, :]).real

    scale = explicit.mean()
    assert np.abs(formula(1) - explicit).max() / scale < 1e-6
    assert np.abs(formula(-1) - explicit).max() / scale > 0.1
    assert np.abs(np.abs(propagate(carrier * lit, sim.kernel2)) ** 2 - explicit).max() / scale > 1.0


@pytest.mark.parametrize(
    "fields, moves",
    [({"sample_diffuser_distance_m": 0.0}, False), ({}, True), (UPSTREAM, True)],
    ids=["L1 0", "L1 3 mm", "50 mm upstream"],
)
def test_the_source_is_the_paper_blur_where_the_sample_does_not_move_against_the_speckle(fields, moves):
    """The reference (one plane of objects), and a sample in the diffuser's plane, get the
    paper's IPSF bit for bit; elsewhere the sample image differs."""
    setup, sim, xs, diffuser = _scene(**fields)
    src = SpeckleSimulator(replace(setup, coherence_model="source"), seed=1)
    assert np.array_equal(src.intensity(None, diffuser), sim.intensity(None, diffuser))
    paper, extended = sim.intensity(xs, diffuser), src.intensity(xs, diffuser)
    if moves:
        assert np.abs(extended - paper).mean() / paper.mean() > 2e-3
    else:
        assert np.array_equal(extended, paper)


def test_the_nodes_converge():
    """The automatic node count is within 0.3 % rms of 32 nodes per axis (noise-free), where
    two nodes per axis are not."""
    setup, _, xs, diffuser = _scene(shape=(64, 64), **UPSTREAM)

    def image(nodes):
        return SpeckleSimulator(replace(setup, coherence_model="source", source_nodes=nodes), seed=1).intensity(
            xs, diffuser
        )

    fine = image(32)

    def rms(a):
        return float(np.sqrt(np.mean((a - fine) ** 2)) / fine.mean())

    assert rms(image(None)) < 3e-3
    assert rms(image(2)) > 3 * rms(image(None))


def test_a_bad_coherence_model_is_refused_in_one_line():
    with pytest.raises(ValueError, match="unknown coherence_model 'gaussian'"):
        SpeckleSetup(coherence_model="gaussian")
    with pytest.raises(ValueError, match="source_nodes must be a whole number >= 1"):
        SpeckleSetup(coherence_model="source", source_nodes=0)
