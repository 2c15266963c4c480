"""Histogram search for the colourful shirt (Wang et al. 2011, §4).

The chrominance of an RGB pixel is ``(r, g, b) / (r + g + b)``. Each pixel falls in one of
``N_BINS = 100`` chrominance bins: a **10 x 10 grid over the (r, g) chromaticity square**,
``bin = 10 * floor(10 r / S) + floor(10 g / S)`` with ``S = r + g + b`` and each index clipped to
9 (so ``r / S = 1`` falls in the last row). The index is computed in exact integer arithmetic,
``(10 r) // S``, so it does not depend on the float dtype. A black pixel (``S = 0``) is grey: bin
``(3, 3)``. Since ``r + g <= 1`` only 64 of the 100 bins can be reached; the other bins are
always empty and add nothing to the uniformity.

For a window of ``s x s`` pixels centred at (x, y) the normalised histogram is ``h(x, y, s)``
and its uniformity ``u(h) = sum_i min(h_i, tau)`` with ``tau = 0.1``: a single colour gives
``u = tau``, ten or more colours in equal parts ``u = 1``. The shirt's location is the weighted
mean of the window centres and scales,

    (x', y', s') = sum w (x, y, s) / sum w,   w = exp(-(u - u_max)^2 / u_sigma^2),
    u_sigma = u_max / 10.

Windows are sampled every ``STRIDE = 6`` pixels at six scales. We build the integral histogram
[Porikli 2005] on the grid of 6 x 6 pixel *cells* (80 x 106 cells for 640 x 480): a scale ``s``
is a whole, even number of cells, ``m = s / 6``, so every window is a block of cells and its
histogram four corner look-ups; window centres lie on cell corners. The prefix sums are two
small GEMMs with triangular ones-matrices (exact for integer counts below 2^24), which is far
cheaper on CPU than ``cumsum`` over a full-resolution ``(480, 640, 100)`` array.

Coordinates: pixel centres at integer coordinates (OpenCV's convention), so the corner between
cells at cell-corner index ``(a, b)`` is the pixel position ``(x, y) = (6 b - 0.5, 6 a - 0.5)``.
Pixels beyond the last whole cell (the right 4 columns at 640 wide) are not searched.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

N_BINS = 100  # Wang §4: "we sample histograms with 100 bins"
BINS_PER_AXIS = 10  # 10 x 10 over (r, g) chromaticity
TAU = 0.1  # Wang §4: u(h) = sum_i min(h_i, tau), tau = 0.1
STRIDE = 6  # Wang §4: "sample histograms at every sixth pixel"
U_SIGMA_FRACTION = 0.1  # Wang §4: u_sigma = u_max / 10
# Wang §4: "search over six discrete scales". Window sides in pixels for 640 x 480 frames, each a
# multiple of 2 * STRIDE, roughly geometric (x1.33) from a distant torso to one filling the frame.
DEFAULT_SCALES = (48, 72, 96, 120, 144, 192)
# Not in the paper: with a foreground mask, a window needs this fraction of foreground pixels.
MIN_FOREGROUND_FRACTION = 0.25
# Not in the paper: pixels with r + g + b below this (0..765) are left out of the histograms, as
# the chrominance of near-black pixels is mostly sensor noise (it looks falsely "colourful").
MIN_INTENSITY = 45.0


class SearchResult(eqx.Module):
    """Output of :func:`histogram_search`.

    ``x, y, s`` are in pixels; ``heat[k, a, b]`` is ``u`` of the window of side ``scales[k]``
    centred at pixel ``(6 b - 0.5, 6 a - 0.5)`` (0 where the window does not fit or has too
    little foreground). ``found`` is False when no window was valid; then ``(x, y, s)`` is the
    image centre and the largest scale.
    """

    x: Float[Array, ""]
    y: Float[Array, ""]
    s: Float[Array, ""]
    u_max: Float[Array, ""]
    found: Bool[Array, ""]
    heat: Float[Array, "n_scales hc1 wc1"]


def _bin_rg(
    image: UInt8[Array, "h w 3"],
) -> tuple[Int[Array, "h w"], Int[Array, "h w"], Float[Array, "h w"]]:
    """Row and column ``(floor(10 r / S), floor(10 g / S))`` of the 10 x 10 chromaticity grid.

    The floor is taken of a float32 division of exact integers: when ``10 r / S`` is an integer
    the quotient is exact, otherwise it is at least ``1 / S >= 1 / 765`` away from one, far beyond
    the rounding error, so the result equals the integer quotient ``(10 r) // S``.
    """
    # Channels as planes: XLA on CPU vectorises a size-3 minor-axis reduction poorly.
    r, g, b = (image[..., c].astype(jnp.float32) for c in range(3))
    total = r + g + b
    safe = jnp.where(total > 0, total, 1.0)
    top = BINS_PER_AXIS - 1
    ir = jnp.minimum(jnp.floor(BINS_PER_AXIS * r / safe), top).astype(jnp.int32)
    ig = jnp.minimum(jnp.floor(BINS_PER_AXIS * g / safe), top).astype(jnp.int32)
    grey = BINS_PER_AXIS // 3
    return jnp.where(total > 0, ir, grey), jnp.where(total > 0, ig, grey), total


def chroma_bins(image: UInt8[Array, "h w 3"]) -> Int[Array, "h w"]:
    """Chrominance bin index ``10 floor(10 r / S) + floor(10 g / S)`` in ``[0, 100)``; exact."""
    ir, ig, _ = _bin_rg(image)
    return ir * BINS_PER_AXIS + ig


def _reachable_bins() -> tuple[int, ...]:
    """The 100-bin indices that a pixel can reach: ``ir + ig <= 10`` (64 of them)."""
    n = BINS_PER_AXIS
    return tuple(i * n + j for i in range(n) for j in range(n) if i + j <= n)


# ``hist100[..., REACHABLE_BINS] == hist_compact``: the compact histograms used internally.
REACHABLE_BINS = _reachable_bins()


def _compact_bins(ir: Int[Array, "*shape"], ig: Int[Array, "*shape"]) -> Int[Array, "*shape"]:
    """Position of the reachable bin ``(ir, ig)`` in ``REACHABLE_BINS`` (closed form, no gather).

    Rows ``ir = 0, 1, 2, ..., 9`` of the 10 x 10 grid hold ``10, 10, 9, 8, ..., 2`` reachable
    bins, so row ``ir >= 2`` starts at ``20 + 11 (ir - 2) - ir (ir - 1) / 2 + 1``.
    """
    start = jnp.where(ir <= 1, 10 * ir, 20 + 11 * (ir - 2) - (ir * (ir - 1)) // 2 + 1)
    return start + ig


def chrominance(image: UInt8[Array, "h w 3"] | Float[Array, "h w 3"]) -> Float[Array, "h w 3"]:
    """``(r, g, b) / (r + g + b)``; a black pixel maps to ``(1/3, 1/3, 1/3)``."""
    rgb = image.astype(jnp.float32) if jnp.issubdtype(image.dtype, jnp.integer) else image
    total = rgb.sum(axis=-1, keepdims=True)
    return jnp.where(total > 0, rgb / jnp.where(total > 0, total, 1), 1.0 / 3.0)


def _prefix_sum_2d(x: Float[Array, "h w c"]) -> Float[Array, "h1 w1 c"]:
    """Zero-bordered 2-D prefix sums ``out[a, b] = sum x[:a, :b]`` as two ``lax.scan``s.

    On CPU ``jnp.cumsum`` lowers to a quadratic ``reduce_window``; a scan over the 80 rows and
    then the 106 columns of the cell grid is a few hundred small, cache-resident adds.
    """

    def step(carry, row):
        carry = carry + row
        return carry, carry

    _, rows = jax.lax.scan(step, jnp.zeros_like(x[0]), x)  # (h, w, c)
    _, cols = jax.lax.scan(step, jnp.zeros_like(rows[:, 0]), jnp.swapaxes(rows, 0, 1))
    out = jnp.swapaxes(cols, 0, 1)  # (h, w, c)
    return jnp.pad(out, ((1, 0), (1, 0), (0, 0)))


def integral_histogram(
    image: UInt8[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    stride: int = STRIDE,
    min_intensity: float | Float[Array, ""] = MIN_INTENSITY,
) -> Float[Array, "hc1 wc1 65"]:
    """Integral histogram on the ``stride x stride`` cell grid, compact bins + a count channel.

    ``out[a, b, j]`` (``j < 64``) counts the (foreground) pixels of bin ``REACHABLE_BINS[j]`` in
    cells ``[0, a) x [0, b)``, i.e. pixels ``[0, stride a) x [0, stride b)``; ``out[a, b, 64]``
    counts all of them. Pixels outside ``mask`` or with ``r + g + b < min_intensity`` are not
    counted. Shape ``(H // stride + 1, W // stride + 1, 65)``, float32 (exact
    integers).
    """
    h, w = image.shape[0] // stride, image.shape[1] // stride
    n_compact = len(REACHABLE_BINS)
    ir, ig, total = _bin_rg(image[: h * stride, : w * stride])
    bins = _compact_bins(ir, ig)
    # Cell index of every pixel: a compile-time constant (static shapes), no integer division.
    cell = np.arange(h * w, dtype=np.int32).reshape(h, w).repeat(stride, 0).repeat(stride, 1)
    counted = total >= min_intensity
    if mask is not None:
        counted = counted & mask[: h * stride, : w * stride]
    weight = counted.astype(jnp.float32)
    flat = (jnp.asarray(cell * n_compact) + bins).reshape(-1)
    counts = jax.ops.segment_sum(weight.reshape(-1), flat, h * w * n_compact)
    counts = counts.reshape(h, w, n_compact)
    total = counts.sum(axis=-1)
    return _prefix_sum_2d(jnp.concatenate([counts, total[..., None]], axis=-1))


def expand_bins(hist: Float[Array, "*batch 64"]) -> Float[Array, "*batch 100"]:
    """Compact 64-bin histograms to the full 100-bin layout (unreachable bins are 0)."""
    full = jnp.zeros((*hist.shape[:-1], N_BINS), hist.dtype)
    return full.at[..., jnp.asarray(REACHABLE_BINS)].set(hist)


def window_histograms(integral: Float[Array, "hc1 wc1 c"], cells: int) -> Float[Array, "na nb c"]:
    """Sums of all ``cells x cells`` blocks; ``[i, j]`` is the block starting at cell (i, j)."""
    m = cells
    return integral[m:, m:] - integral[:-m, m:] - integral[m:, :-m] + integral[:-m, :-m]


def uniformity(
    hist: Float[Array, "*batch n"], tau: float | Float[Array, ""] = TAU
) -> Float[Array, "*batch"]:
    """``u(h) = sum_i min(h_i, tau)`` of histograms normalised here to sum 1 (0 if empty)."""
    total = hist.sum(axis=-1)
    safe = jnp.where(total > 0, total, 1)
    return jnp.minimum(hist, tau * safe[..., None]).sum(axis=-1) / safe


def _check_scales(scales: Sequence[int], stride: int, shape: tuple[int, ...]) -> None:
    if len(scales) == 0:
        raise ValueError("histogram_search: scales must be a non-empty sequence of ints")
    for s in scales:
        if int(s) != s or s <= 0 or s % (2 * stride) != 0:
            raise ValueError(
                f"histogram_search: scale {s!r} must be a positive multiple of 2 * stride "
                f"= {2 * stride} (windows are whole, even numbers of cells)"
            )
        if s > min(shape[0] // stride, shape[1] // stride) * stride:
            raise ValueError(
                f"histogram_search: scale {s} does not fit in an image of shape {shape[:2]}"
            )


def histogram_search(
    image: UInt8[Array, "h w 3"],
    mask: Bool[Array, "h w"] | None = None,
    *,
    scales: Sequence[int] = DEFAULT_SCALES,
    stride: int = STRIDE,
    tau: float | Float[Array, ""] = TAU,
    min_foreground: float | Float[Array, ""] = MIN_FOREGROUND_FRACTION,
    min_intensity: float | Float[Array, ""] = MIN_INTENSITY,
) -> SearchResult:
    """Locate the shirt: the ``u``-weighted mean window ``(x', y', s')`` (Wang §4).

    ``image`` is RGB uint8. Only counted pixels enter the histograms: inside the foreground
    ``mask`` (if given) and with ``r + g + b >= min_intensity``; windows whose counted fraction
    is below ``min_foreground`` are excluded.
    ``scales`` and ``stride`` are static (they set shapes); ``tau`` may be traced. Jit with
    ``jax.jit(histogram_search, static_argnames=("scales", "stride"))``.
    """
    _check_scales(scales, stride, image.shape)
    scales = tuple(int(s) for s in scales)
    integral = integral_histogram(image, mask, stride, min_intensity)
    hc1, wc1 = integral.shape[:2]
    heats, valids = [], []
    for s in scales:
        m = s // stride
        block = window_histograms(integral, m)
        total = block[..., -1]
        safe = jnp.where(total > 0, total, 1.0)
        u = jnp.minimum(block[..., :-1], tau * safe[..., None]).sum(axis=-1) / safe
        valid = total >= min_foreground * (s * s)
        u = jnp.where(valid, u, 0.0)
        pad = ((m // 2, m // 2), (m // 2, m // 2))
        heats.append(jnp.pad(u, pad))
        valids.append(jnp.pad(valid, pad))
    heat = jnp.stack(heats)
    valid = jnp.stack(valids)
    u_max = jnp.max(heat)
    found = jnp.any(valid) & (u_max > 0)
    u_sigma = jnp.where(found, U_SIGMA_FRACTION * u_max, 1.0)
    weight = jnp.where(valid, jnp.exp(-(((heat - u_max) / u_sigma) ** 2)), 0.0)
    wsum = weight.sum()
    safe = jnp.where(wsum > 0, wsum, 1.0)
    ys = stride * jnp.arange(hc1, dtype=jnp.float32) - 0.5
    xs = stride * jnp.arange(wc1, dtype=jnp.float32) - 0.5
    ss = jnp.asarray(scales, jnp.float32)
    x = jnp.einsum("kab,b->", weight, xs) / safe
    y = jnp.einsum("kab,a->", weight, ys) / safe
    s = jnp.einsum("kab,k->", weight, ss) / safe
    x = jnp.where(found, x, (image.shape[1] - 1) / 2)
    y = jnp.where(found, y, (image.shape[0] - 1) / 2)
    s = jnp.where(found, s, float(max(scales)))
    return SearchResult(x=x, y=y, s=s, u_max=u_max, found=found, heat=heat)
