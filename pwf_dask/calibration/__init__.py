"""Calibration from the reference speckle, once per diffuser position (Methods: IOTF; Diffuser transmission function).

* :mod:`~pwf_dask.calibration.coherence` - the coherence lengths x_coh, y_coh of the IOTF,
  Eq. (IOTF), and the photon noise of a frame;
* :mod:`~pwf_dask.calibration.diffuser` - the diffuser's transmission function t_r;
* :mod:`~pwf_dask.calibration.drift` - the diffuser's drift between reference and sample
  frames (not in the paper);
* :mod:`~pwf_dask.calibration.sensitivity` - what the speckle can carry: its visibility and
  grain, and a retrieved phase's speckle shift against them (not in the paper).
"""

from pwf_dask.calibration.coherence import (
    COHERENCE_METHODS,
    CoherenceFit,
    coherence_lengths,
    fit_coherence_lengths,
    noise_to_signal,
    photon_noise_pct,
    relative_noise_variance,
    speckle_spectrum,
    spectrum_tile,
    white_noise_floor,
)
from pwf_dask.calibration.diffuser import (
    AUTO_MIN_ATTENUATION_PER_M,
    DIFFUSER_MODEL_CHOICES,
    DIFFUSER_MODELS,
    DiffuserEstimate,
    choose_diffuser_model,
    ctf_phase_delay,
    diffuser_transmission,
    refine_phase_screen,
    single_material_diffuser,
)
from pwf_dask.calibration.drift import shift_transmission, speckle_drift_px, unseen_by_reference
from pwf_dask.calibration.sensitivity import (
    Sensitivity,
    SensitivityLimits,
    attenuation_contrast,
    phase_sensitivity,
    phase_sensitivity_noise_bound,
    position_disagreement,
    sample_misfit,
    speckle_grain_px,
    speckle_shift_px,
    speckle_visibility,
)

__all__ = [
    "AUTO_MIN_ATTENUATION_PER_M",
    "COHERENCE_METHODS",
    "DIFFUSER_MODEL_CHOICES",
    "DIFFUSER_MODELS",
    "CoherenceFit",
    "DiffuserEstimate",
    "Sensitivity",
    "SensitivityLimits",
    "attenuation_contrast",
    "choose_diffuser_model",
    "coherence_lengths",
    "ctf_phase_delay",
    "diffuser_transmission",
    "fit_coherence_lengths",
    "noise_to_signal",
    "phase_sensitivity",
    "phase_sensitivity_noise_bound",
    "photon_noise_pct",
    "refine_phase_screen",
    "relative_noise_variance",
    "position_disagreement",
    "sample_misfit",
    "shift_transmission",
    "single_material_diffuser",
    "speckle_drift_px",
    "speckle_grain_px",
    "speckle_shift_px",
    "speckle_spectrum",
    "spectrum_tile",
    "speckle_visibility",
    "unseen_by_reference",
    "white_noise_floor",
]
