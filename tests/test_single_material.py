"""The single-material prior (pwf_dask.physics.single_material) against analytic results."""

import math

import numpy as np
import pytest

from pwf_dask.physics.single_material import paganin_filter, paganin_length_m, single_material_phase

PIXEL = 6.5e-6
GEOMETRY = dict(pixel_size_m=PIXEL, wavelength_m=4.96e-11, distance_m=0.7)
RATIO = 5987.0  # PMMA at 25 keV (xraydb)


def rod(shape, centre_px, radius_px):
    """A rod's phase along y (chord profile, -177 rad deep for 254 px at PMMA's 25 keV delta)."""
    x = np.arange(shape[1]) - centre_px
    chord = 2.0 * np.sqrt(np.clip(radius_px**2 - x**2, 0, None))
    return np.broadcast_to(-chord * 177.0 / (2 * 254), shape).copy()


def test_paganin_length_and_filter_follow_the_formula():
    ell = paganin_length_m(4.96e-11, 0.7, RATIO)
    assert ell == pytest.approx(math.sqrt(4.96e-11 * 0.7 * RATIO / (4 * math.pi)))
    assert 19 < ell / PIXEL < 21  # the regime of issue #27: ~20 px
    w = paganin_filter((64, 4096), PIXEL, ell)
    assert w[0, 0] == 1.0
    # at |q| = 1/ell (q = 2 pi u) the filter is 1/2: along x, the bin nearest u = 1/(2 pi ell)
    u = np.fft.rfftfreq(4096, d=PIXEL)
    k = int(np.argmin(abs(u - 1 / (2 * math.pi * ell))))
    assert w[0, k] == pytest.approx(1 / (1 + (2 * math.pi * u[k] * ell) ** 2))
    assert w[0, k] == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="delta_over_beta must be positive"):
        paganin_length_m(4.96e-11, 0.7, -1.0)


def test_a_phase_that_already_follows_the_attenuation_is_kept():
    phase = rod((64, 700), 300, 254)
    out = single_material_phase(phase, -phase / RATIO, RATIO, **GEOMETRY)
    np.testing.assert_allclose(out, phase, atol=1e-9 * abs(phase).max())


def test_an_edge_step_lost_by_the_phase_is_restored_from_the_attenuation():
    """The failure of docs/methods.md (Wide frames): the phase between two edges off by a
    constant (here -30 rad left of the rod's right edge), the attenuation right. The prior puts
    the step back: far from the edge (beyond 5 ell) within 1 % of it, rms error 5x smaller."""
    truth = rod((64, 1024), 500, 254)
    edge = 500 + 254
    wrong = truth.copy()
    wrong[:, :edge] -= 30.0
    out = single_material_phase(wrong, -truth / RATIO, RATIO, **GEOMETRY)
    err_before = np.sqrt(np.mean((wrong - truth) ** 2))
    err_after = np.sqrt(np.mean((out - truth) ** 2))
    assert err_after < err_before / 5
    far = np.abs(np.arange(1024) - edge) > 5 * 20
    assert np.abs(out - truth)[:, far].max() < 0.01 * 30.0


def test_attenuation_noise_reaches_the_phase_as_paganins_filter_predicts():
    """White attenuation noise sigma becomes phase noise (delta/beta) sigma p / (2 sqrt(pi) ell)
    (the filter's integral of W^2 over the plane, p the pixel)."""
    rng = np.random.default_rng(0)
    sigma = 1e-3
    attenuation = sigma * rng.standard_normal((2048, 2048))  # ~800 modes under 1/ell: 2 % scatter
    out = single_material_phase(np.zeros_like(attenuation), attenuation, RATIO, **GEOMETRY)
    ell = paganin_length_m(GEOMETRY["wavelength_m"], GEOMETRY["distance_m"], RATIO)
    expected = RATIO * sigma * PIXEL / (2 * math.sqrt(math.pi) * ell)
    assert float(np.sqrt(np.mean(out**2))) == pytest.approx(expected, rel=0.05)


@pytest.mark.gpu
def test_cupy_matches_numpy(cupy):
    truth = rod((32, 300), 120, 100)
    wrong = truth.copy()
    wrong[:, :220] -= 30.0
    cpu = single_material_phase(wrong, -truth / RATIO, RATIO, **GEOMETRY)
    gpu = single_material_phase(cupy.asarray(wrong), cupy.asarray(-truth / RATIO), RATIO, **GEOMETRY)
    assert isinstance(gpu, cupy.ndarray)
    np.testing.assert_allclose(cupy.asnumpy(gpu), cpu, atol=1e-9 * abs(truth).max())
