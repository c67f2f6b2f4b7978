"""The speckle set-up's geometry (the paper's Fig. 1a), in SI units, validated once.

One :class:`Geometry` is what retrieval, the scan store and ingest all check a measurement's
distances against: the same rules and the same one-line messages everywhere.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from pwf_dask.physics.optics import check_diffuser_upstream, check_plausible_geometry, wavelength_m

#: What :func:`pwf_dask.retrieve_projection` must be told about a measurement (every
#: :class:`Geometry` field but the optional upstream diffuser).
GEOMETRY_KEYS = ("energy_eV", "pixel_size_m", "sample_diffuser_distance_m", "diffuser_detector_distance_m")


@dataclass(frozen=True)
class Geometry:
    """Source energy, detector pixel and the two distances of a speckle measurement.

    Parameters
    ----------
    energy_eV
        Photon energy (eV).
    pixel_size_m
        Effective detector pixel (m).
    sample_diffuser_distance_m
        L1, sample to diffuser (m); 0 when the diffuser sits against the sample or upstream.
    diffuser_detector_distance_m
        L2, diffuser to detector (m).
    diffuser_upstream_m
        > 0: the diffuser this far upstream of the sample (needs L1 = 0); its speckle then
        develops over ``diffuser_upstream_m + L2``.

    Raises
    ------
    ValueError
        One line naming the first value that is not a number, not positive where it must be,
        or outside :data:`pwf_dask.physics.optics.PLAUSIBLE_GEOMETRY` (a unit slip).
    """

    energy_eV: float
    pixel_size_m: float
    sample_diffuser_distance_m: float
    diffuser_detector_distance_m: float
    diffuser_upstream_m: float = 0.0

    def __post_init__(self) -> None:
        for name, positive in (
            ("energy_eV", True),
            ("pixel_size_m", True),
            ("sample_diffuser_distance_m", False),
            ("diffuser_detector_distance_m", True),
        ):
            value = getattr(self, name)
            try:
                v = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {value!r}") from None
            if not math.isfinite(v) or (v <= 0 if positive else v < 0):
                raise ValueError(f"{name} must be {'positive' if positive else '>= 0'}, got {value}")
            object.__setattr__(self, name, v)
        upstream = check_diffuser_upstream(self.diffuser_upstream_m, self.sample_diffuser_distance_m)
        object.__setattr__(self, "diffuser_upstream_m", upstream)
        check_plausible_geometry(**asdict(self))

    @property
    def wavelength_m(self) -> float:
        """lambda = h c / E (m)."""
        return wavelength_m(self.energy_eV)

    @property
    def speckle_distance_m(self) -> float:
        """The distance over which the diffuser's speckle develops before the detector (m)."""
        return self.diffuser_detector_distance_m + self.diffuser_upstream_m

    @property
    def sample_detector_distance_m(self) -> float:
        """L1 + L2: the sample's own propagation distance to the detector (m)."""
        return self.sample_diffuser_distance_m + self.diffuser_detector_distance_m

    @classmethod
    def from_attrs(cls, attrs, diffuser_upstream_m: float | None = None) -> Geometry:
        """The geometry a scan store records (docs/scan-format.md §1); ``diffuser_upstream_m``
        overrides the optional attribute of that name."""
        if diffuser_upstream_m is None:
            diffuser_upstream_m = attrs.get("diffuser_upstream_m", 0.0)
        return cls(*(attrs[name] for name in GEOMETRY_KEYS), diffuser_upstream_m)

    def keywords(self, with_upstream: bool = True) -> dict[str, float]:
        """The geometry as :func:`pwf_dask.retrieve_projection` takes it (the upstream
        distance only where set and asked for)."""
        out = {name: getattr(self, name) for name in GEOMETRY_KEYS}
        if with_upstream and self.diffuser_upstream_m:
            out["diffuser_upstream_m"] = self.diffuser_upstream_m
        return out
