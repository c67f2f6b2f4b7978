"""An extended Gaussian source: partial coherence as an incoherent sum over source points.

The paper's model, Eq. (IPSF), blurs the whole detector intensity by one Gaussian, whose
width it calibrates from the reference. A real source of finite size does something else:
each of its points lights the set-up by a plane wave tilted by an angle theta, and a tilt
moves the pattern of each object by theta times that object's distance to the detector. With
two objects (sample and diffuser) at different distances, a tilt also moves one against the
other, which no blur of the detector intensity reproduces. By the shift theorem (paraxial),

    I_theta = S[theta z_ref] | P2{ t . S[theta h] x } |^2,

with S[s] f(r) = f(r - s), t the diffuser's field where the sample is, x the sample's field
there, z_ref the diffuser's distance to the detector (the reference's speckle is blurred over
theta z_ref alone, so the calibrated lengths are the source's at z_ref) and h the sample's
shift against the speckle per unit angle: +L1 with the diffuser L1 downstream of the sample
(x is then P1{exp psi}), -d with the diffuser d upstream (derivation: docs/methods.md,
"An extended source").

The detector intensity is the mean of I_theta over theta ~ N(0, sigma_theta^2) per axis.
:func:`source_nodes` puts nodes at the conditional means of equal-probability bins of each
axis; the sample's shift theta h is computed at the nodes and interpolated linearly between
them, while the detector shift theta z_ref is integrated exactly against the interpolation's
hat functions (on a 1 / :data:`SUBSTEPS_PER_SIGMA` sigma sub-grid, :func:`node_transfer`), so
that the nodes' transfer functions sum to the paper's IOTF: with h = 0 the sum is the IPSF
model.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

#: sub-steps per standard deviation and the half-width (in standard deviations) of the grid on
#: which each bin's detector shift is integrated (the Gaussian's tail beyond it: 1e-12)
SUBSTEPS_PER_SIGMA = 200
HALF_WIDTH_SIGMA = 7.0
#: nodes per axis of :func:`nodes_per_axis`: this many per detector pixel of the sample's rms
#: shift, at least :data:`MIN_NODES` and at most :data:`MAX_NODES`. Against 32 nodes per axis,
#: the intensity of a 128^2 bead scene moved by 0.16 % rms of its mean (the paper's geometry,
#: 5 x 4 nodes), 0.15 % (the diffuser 50 mm upstream, 22 x 18) and 0.20 % (L1 10 mm, L2 100 mm,
#: 3 x 3): below 1e4 photons' 1 % (docs/methods.md, "An extended source").
NODES_PER_PIXEL_OF_SHIFT = 16
MIN_NODES = 3
MAX_NODES = 32


def ipsf_sigma_m(coherence_length_m: float) -> float:
    """The standard deviation of the IPSF, Eq. (IPSF): exp(-2 pi x^2 / x_coh^2) has
    sigma = x_coh / (2 sqrt(pi))."""
    return coherence_length_m / (2.0 * math.sqrt(math.pi))


def source_nodes(n_nodes: int) -> np.ndarray:
    """The source's nodes along one axis, in standard deviations: the conditional means of a
    standard normal split into ``n_nodes`` bins of equal probability, (phi(a0) - phi(a1)) * n_nodes."""
    edges = special.ndtri(np.linspace(0.0, 1.0, n_nodes + 1))
    pdf = np.exp(-0.5 * edges**2) / math.sqrt(2 * math.pi)  # 0 at the infinite edges
    return (pdf[:-1] - pdf[1:]) * n_nodes


def node_transfer(freq: np.ndarray, sigma_m: float, n_nodes: int) -> np.ndarray:
    """Per node a_k of :func:`source_nodes`, the transfer function of the detector shift
    a sigma_m weighted by the node's hat function: sum over a of w(a) hat_k(a)
    exp(-2 pi i f a sigma_m), shape (n_nodes, len(freq)).

    The sample's shift is known at the nodes only; the hat functions interpolate it linearly
    between them (constant beyond the outer ones), which keeps its correlation with the
    detector shift inside a bin: the sum then converges as the square of the nodes' spacing,
    where one value per bin converged only as the spacing. The hats sum to 1, so the
    transfers sum to exp(-2 pi^2 sigma_m^2 f^2), one axis of the IOTF."""
    n_sub = int(2 * HALF_WIDTH_SIGMA * SUBSTEPS_PER_SIGMA)
    a = (np.arange(n_sub) + 0.5) / SUBSTEPS_PER_SIGMA - HALF_WIDTH_SIGMA
    w = np.exp(-0.5 * a**2)
    w /= w.sum()
    nodes = source_nodes(n_nodes)
    hats = np.eye(n_nodes)
    freq = np.asarray(freq, float)
    out = np.zeros((n_nodes, len(freq)), complex)
    for k in range(n_nodes):
        weight = w * np.interp(a, nodes, hats[k])
        sel = weight > 0
        out[k] = weight[sel] @ np.exp(-2j * np.pi * np.outer(a[sel] * sigma_m, freq))
    return out


def nodes_per_axis(shift_sigma_m: float, pixel_size_m: float) -> int:
    """Nodes per axis for a sample shifted by ``shift_sigma_m`` rms against the speckle
    (:data:`NODES_PER_PIXEL_OF_SHIFT`); 1 where it does not move."""
    if shift_sigma_m == 0:
        return 1
    n = math.ceil(NODES_PER_PIXEL_OF_SHIFT * abs(shift_sigma_m) / pixel_size_m)
    return int(min(MAX_NODES, max(MIN_NODES, n)))


def shift_ramp(freq: np.ndarray, shift_m: float) -> np.ndarray:
    """exp(-2 pi i f s): the Fourier factor of S[s] f(r) = f(r - s) along one axis."""
    return np.exp(-2j * np.pi * np.asarray(freq, float) * shift_m)
