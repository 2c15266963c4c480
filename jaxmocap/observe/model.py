"""The learned observation model: a small fully-convolutional network over a crop that gives
every pixel a probability over the classes of :mod:`jaxmocap.observe.classes`.

Input normalised against the light (issue 49: a per-pixel model learns the light it saw): with
``l = log((I + 2) / 257)`` per channel, the network reads

    [l - mean_crop(l)  (3: the crop's grey world, removing exposure and white-balance gains),
     l_R - l_G, l_B - l_G  (2: log-chroma, removing shading)]

Architecture (equinox, ``../shared/STYLE.md``'s pattern): a 3x3 stem at full resolution, a
stride-2 3x3 convolution, residual 3x3 convolutions dilated 1, 2, 4, 8 at half resolution (a
receptive field of 65 px, half of the tracker's 128 px crop: neighbouring patches and
the skin beside them), bilinear upsampling, and a 1x1 head over the stem's and the context's
features. ~25k parameters; at 128 x 128 about 8 M multiply-adds per 1,000 pixels.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

N_INPUTS = 5
DTYPE = jnp.float32  # the weights' dtype whatever jax_enable_x64 says (files stay float32)
DILATIONS = (1, 2, 4, 8)


def features(image: Float[Array, "h w 3"]) -> Float[Array, "5 h w"]:
    """The light-normalised input planes (module docstring) of an RGB crop (0..255)."""
    lg = jnp.log((image.astype(jnp.float32) + 2.0) / 257.0)
    centred = lg - jnp.mean(lg, axis=(0, 1), keepdims=True)
    chroma = jnp.stack([lg[..., 0] - lg[..., 1], lg[..., 2] - lg[..., 1]], -1)
    return jnp.moveaxis(jnp.concatenate([centred, chroma], -1), -1, 0)


class Observer(eqx.Module):
    """Per-pixel class logits of a crop (module docstring). ``n_classes`` and the widths are
    hyper-parameters (static); :func:`jaxmocap.observe.io.load` rebuilds the skeleton from
    them before reading the weights."""

    stem: eqx.nn.Conv2d
    down: eqx.nn.Conv2d
    blocks: tuple[eqx.nn.Conv2d, ...]
    head: eqx.nn.Conv2d
    n_classes: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    context: int = eqx.field(static=True)

    def __init__(self, n_classes: int, key: PRNGKeyArray, width: int = 16, context: int = 24):
        ks = jax.random.split(key, 3 + len(DILATIONS))
        self.stem = eqx.nn.Conv2d(N_INPUTS, width, 3, padding=1, key=ks[0], dtype=DTYPE)
        self.down = eqx.nn.Conv2d(width, context, 3, stride=2, padding=1, key=ks[1],
                                  dtype=DTYPE)
        self.blocks = tuple(
            eqx.nn.Conv2d(context, context, 3, padding=d, dilation=d, key=k, dtype=DTYPE)
            for d, k in zip(DILATIONS, ks[3:], strict=True)
        )
        self.head = eqx.nn.Conv2d(width + context, n_classes, 1, key=ks[2], dtype=DTYPE)
        self.n_classes, self.width, self.context = int(n_classes), int(width), int(context)

    def __call__(self, image: Float[Array, "h w 3"]) -> Float[Array, "h w c"]:
        """Logits (h, w, n_classes) of an RGB crop (0..255, h and w even)."""
        x = features(image)
        h0 = jax.nn.relu(self.stem(x))
        h = jax.nn.relu(self.down(h0))
        for conv in self.blocks:
            h = h + jax.nn.relu(conv(h))
        up = jax.image.resize(h, (h.shape[0],) + h0.shape[1:], "bilinear")
        logits = self.head(jnp.concatenate([h0, up], 0))
        return jnp.moveaxis(logits, 0, -1)


def log_probs(model: Observer, image: Float[Array, "h w 3"]) -> Float[Array, "h w c"]:
    """Per-pixel log-probabilities over the classes."""
    return jax.nn.log_softmax(model(image), -1)


def hyper(model: Observer) -> dict:
    """The hyper-parameters that rebuild ``model``'s skeleton."""
    return dict(n_classes=model.n_classes, width=model.width, context=model.context)
