"""Trackers: the papers' full per-frame pipelines built from the library's stages.

* :mod:`jaxmocap.trackers.stereo_pf` -- Azad et al. 2007, the stereo particle filter.
"""

from jaxmocap.trackers import stereo_pf

__all__ = ["stereo_pf"]
