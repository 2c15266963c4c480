"""Particle filtering for the stereo tracker (Azad et al. §II): a generic, jit-compiled filter.

The filter is generic in the likelihood: ``PFParams.loglik(s, z) -> scalar`` is vmapped over
particles. The stereo cues of Azad et al. §III live beside it (``cues`` / ``stereo*`` modules).
"""

from jaxmocap.pf.filter import (
    ANNEAL_ALPHA,
    DAMPING,
    ERROR_SCALE,
    RESAMPLE_THRESHOLD,
    PFEstimate,
    PFParams,
    PFState,
    anneal_step,
    anneal_step_lineage,
    init,
    init_uniform,
    run,
    run_lineage,
    step,
    step_lineage,
)
from jaxmocap.pf.guided import GuidedProposal, min_norm_steps
from jaxmocap.pf.resample import (
    effective_sample_size,
    multinomial,
    normalize_log_weights,
    systematic,
)
from jaxmocap.pf.smooth import Lineage, fixed_lag_smooth

__all__ = [
    "ANNEAL_ALPHA",
    "DAMPING",
    "ERROR_SCALE",
    "GuidedProposal",
    "Lineage",
    "RESAMPLE_THRESHOLD",
    "PFEstimate",
    "PFParams",
    "PFState",
    "anneal_step",
    "anneal_step_lineage",
    "effective_sample_size",
    "fixed_lag_smooth",
    "init",
    "init_uniform",
    "min_norm_steps",
    "multinomial",
    "normalize_log_weights",
    "run",
    "run_lineage",
    "step",
    "step_lineage",
    "systematic",
]
