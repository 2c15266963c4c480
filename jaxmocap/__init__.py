"""jaxmocap: differentiable markerless motion capture in JAX.

Modules follow the papers' concepts: ``camera``, ``body``, ``garment``, ``render``, ``color``,
``distance``, ``posedb``, ``ik``, ``pf``, ``blobs``, ``trackers``, ``synth``, ``io``.
"""

__version__ = "0.1.0"
