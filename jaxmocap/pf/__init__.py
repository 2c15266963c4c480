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
    init,
    init_uniform,
    run,
    step,
)
from jaxmocap.pf.guided import GuidedProposal, min_norm_steps
from jaxmocap.pf.resample import (
    effective_sample_size,
    multinomial,
    normalize_log_weights,
    systematic,
)

__all__ = [
    "ANNEAL_ALPHA",
    "DAMPING",
    "ERROR_SCALE",
    "GuidedProposal",
    "RESAMPLE_THRESHOLD",
    "PFEstimate",
    "PFParams",
    "PFState",
    "anneal_step",
    "effective_sample_size",
    "init",
    "init_uniform",
    "min_norm_steps",
    "multinomial",
    "normalize_log_weights",
    "run",
    "step",
    "systematic",
]
