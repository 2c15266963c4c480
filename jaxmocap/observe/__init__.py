"""The learned observation layer (issue 49; beyond both papers): a small network trained by
gradient on the project's own renders under randomised light gives every pixel of a crop a
probability over the garment's colours, the skin of the head and of each hand, and the
background. Both trackers read it; Wang's white balance + Mahalanobis path stays as the paper's
set-up.

* :mod:`.classes` — the class table of a body + garment, ground truth from a render (by roles);
* :mod:`.scenes` — training scenes: geometry by the JAX ray caster, light drawn from a key;
* :mod:`.model` — the network (equinox) and its light-normalised input;
* :mod:`.train` — the optax training step and loop;
* :mod:`.io` — the model file (JSON header with digests and training record + weights);
* :mod:`.fit` — one call: render, train, cache by digest, resume (``jaxmocap learn``).

This package imports the body, garment and renderer; the trackers import it, never the reverse.
"""

from .classes import Classes, PartMaps, classes_of, labels_of, part_maps, skin_label_map
from .fit import BUNDLED, FINE_TUNE, Settings, cache_key, fit, learn
from .io import ObserverFileError, load, read_header, save
from .model import Observer, features, log_probs
from .scenes import Geometry, blackbody_rgb, render_geometry, shade
from .train import TrainConfig, class_weights, loss_fn, make_step, train

__all__ = [
    "BUNDLED", "FINE_TUNE", "Classes", "Geometry", "Observer", "ObserverFileError", "PartMaps",
    "Settings", "TrainConfig", "blackbody_rgb", "cache_key", "class_weights", "classes_of",
    "features", "fit", "labels_of", "learn", "load", "log_probs", "loss_fn", "make_step",
    "part_maps", "read_header", "render_geometry", "save", "shade", "skin_label_map", "train",
]  # fmt: skip
