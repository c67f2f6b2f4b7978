"""The options of one retrieval, each with its default defined here once.

:func:`pwf_dask.retrieve_projection` takes them as keywords (the contract's ``method``,
``max_iter``, ``tol``, ``gamma``, ``alpha``, ``coherence_length_x_m``,
``coherence_length_y_m``, and ours) or as one :class:`RetrievalOptions`; the scan workflow
and the CLI read their defaults from :data:`DEFAULTS`. The stop rule's defaults come from
:class:`~pwf_dask.pwf.stopping.StopRule`, the solver's from :mod:`pwf_dask.pwf.solver`.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field, fields, replace
from typing import Any

from pwf_dask.calibration.coherence import DEFAULT_COHERENCE_METHOD
from pwf_dask.calibration.diffuser import REFINE_ITER, SAMPLE_FLOOR
from pwf_dask.physics.detector import DEFAULT_OUTLIER_SIGMA
from pwf_dask.physics.diffusers import DEFAULT_MATERIAL
from pwf_dask.pwf.solver import DEFAULT_GAMMA, DEFAULT_STEP, STOP_RULE

#: The sample's one material (MIST, the single-material prior) when none is named.
DEFAULT_SAMPLE_MATERIAL = "cellulose"


@dataclass(frozen=True)
class RetrievalOptions:
    """Every option of :func:`pwf_dask.retrieve_projection` (its docstring says what each does).

    Grouped as the retrieval uses them: the method and Algorithm S1's stop rule and step; the
    regularizer and preconditioner of Algorithm S2; the IOTF's coherence lengths; the
    computational grids; the diffuser estimate; the images; the sample; the baselines.
    """

    method: str = "pwf"
    # Algorithm S1: stop rule (pwf_dask.pwf.stopping.StopRule), step and momentum restart
    max_iter: int = STOP_RULE.max_iter
    tol: float = STOP_RULE.tol
    min_iter: int = STOP_RULE.min_iter
    patience: int = STOP_RULE.patience
    rtol: float = STOP_RULE.rtol
    jtol: float = STOP_RULE.jtol
    low_band_atol_rad: float = STOP_RULE.low_band_atol_rad
    stationary_terms: str = STOP_RULE.stationary_terms
    step: float = DEFAULT_STEP
    step_search: bool = True
    restart: str = "gradient"
    initial: Any = "zero"
    # Algorithm S2: regularizer, preconditioner, objective scale
    gamma: float = DEFAULT_GAMMA
    #: "sensitivity": DEFAULT_ALPHA where the data see the phase as the paper's scene does, its
    #: Im lowered where they see it more weakly (pwf_dask.pwf.solver.sensitivity_alpha)
    alpha: complex | str = "sensitivity"
    preconditioner: bool = True
    normalization: str = "paper"
    phase_scale: float | str = 1.0
    precision: str = "single"
    # the IOTF, Eq. (IOTF): calibrated from the reference when not given
    coherence_length_x_m: float | None = None
    coherence_length_y_m: float | None = None
    coherence_method: str = DEFAULT_COHERENCE_METHOD
    coherence_includes_pixel_blur: bool = False
    #: the detector's halo beside the IOTF: this fraction of the light over an exponential of
    #: this 1/e radius (its Gaussian core is in the calibrated lengths); 0: none, the paper's model
    detector_halo_fraction: float = 0.0
    detector_halo_radius_m: float = 0.0
    # computational grids
    upsample: int | str = "auto"
    pad: int | str = "auto"
    field_upsample: int | float | str = "auto"
    #: exp(psi) on the field grid ("field") or on the detector grid, folded into P1 ("detector":
    #: 6 instead of 10 field-grid FFTs per iteration; phase error 0-20 % higher on P3000 scenes,
    #: 2x at coarse pixels: docs/methods.md). Under field_upsample="auto" "detector" holds on
    #: the aliasing diffuser's grid only: where the pixel asks for a grid, exp(psi) is formed on it
    #: (retrieval.sample_field_grid_on)
    sample_field_grid: str = "field"
    # the diffuser estimate t_r
    diffuser_model: str = "auto"
    diffuser_material: str = DEFAULT_MATERIAL
    diffuser_beta_over_delta: float | None = None
    diffuser_refine_iter: int = REFINE_ITER
    #: the Wiener filters' least NSR: "sample" (half the sample image's photon noise over the
    #: reference's speckle), or a number (0: the reference's own ratio, as read)
    diffuser_nsr_floor: float | str = SAMPLE_FLOOR
    phase_screen_iter: int = 0
    diffuser_upstream_m: float = 0.0
    diffuser_drift: str | tuple[float, float] = "auto"
    # the images
    outlier_sigma: float | None = DEFAULT_OUTLIER_SIGMA
    zero_background: bool = True
    # the sample: MIST's material and the single-material prior
    single_material: bool = False
    sample_material: str = DEFAULT_SAMPLE_MATERIAL
    sample_delta_over_beta: float | None = None
    # the speckle-tracking baselines' own options, and the FFT threads of this call
    tracking_options: dict | None = field(default=None, compare=False)
    fft_workers: int | None = None

    @classmethod
    def from_keywords(cls, options: RetrievalOptions | None = None, /, **keywords) -> RetrievalOptions:
        """``options`` (default: :data:`DEFAULTS`) with the given keywords replacing fields.

        Raises
        ------
        TypeError
            A keyword that is no option, in one line, with the nearest option's name.
        """
        check_option_names(keywords)
        return replace(options or DEFAULTS, **keywords)


#: The defaults, as one object.
DEFAULTS = RetrievalOptions()
#: The options' names.
OPTION_NAMES = tuple(f.name for f in fields(RetrievalOptions))


def check_option_names(keywords) -> None:
    """A one-line TypeError for the first name that is not a retrieval option."""
    for name in keywords:
        if name not in OPTION_NAMES:
            near = difflib.get_close_matches(name, OPTION_NAMES, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise TypeError(f"unknown retrieval option {name!r}{hint}")
