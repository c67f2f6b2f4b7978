"""Simulated speckle scans with known ground truth, as realistic as the checks demand.

* :mod:`~pwf_dask.simulation.phantoms` - analytic phantoms (beads in a cylinder, rods) and their
  exact refractive-index volumes;
* :mod:`~pwf_dask.simulation.speckle` - one projection: sample, propagation, sandpaper diffuser,
  partial coherence, pixel integration, Poisson noise;
* :mod:`~pwf_dask.simulation.scan` - whole scans written as scan stores, from named presets.
"""

from pwf_dask.simulation.phantoms import (
    PAPER_BEAD_RADIUS_M,
    SCAN_CYLINDER_WIDTH_FRACTION,
    Phantom,
    Rods,
    Sphere,
    default_phantom,
    phantom_from_json,
    phantom_to_json,
    refractive_index_volume,
    scan_phantom,
)
from pwf_dask.simulation.scan import DEFAULT_PRESET, PRESETS, simulate_scan
from pwf_dask.simulation.speckle import (
    FINE_DIFFUSER,
    GEOMETRY_KEYS,
    SimulatedProjection,
    SpeckleSetup,
    SpeckleSimulator,
    dark_field_blur,
    simulate_projection,
)

__all__ = [
    "DEFAULT_PRESET",
    "FINE_DIFFUSER",
    "GEOMETRY_KEYS",
    "PAPER_BEAD_RADIUS_M",
    "PRESETS",
    "SCAN_CYLINDER_WIDTH_FRACTION",
    "Phantom",
    "Rods",
    "SimulatedProjection",
    "SpeckleSetup",
    "SpeckleSimulator",
    "Sphere",
    "dark_field_blur",
    "default_phantom",
    "phantom_from_json",
    "phantom_to_json",
    "refractive_index_volume",
    "scan_phantom",
    "simulate_projection",
    "simulate_scan",
]
