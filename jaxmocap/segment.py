"""The stereo tracker's image processing line (Azad et al. 2007, §III-A and §IV, Fig. 3).

Per camera image ``I`` (uint8 RGB, ``h x w``):

1. smooth with the 3x3 Gaussian kernel ``[1 2 1]^T [1 2 1] / 16``;
2. convert to HSV (OpenCV's 8-bit convention, see below);
3. skin map ``s = [hsv in skin interval]`` (hands and head, §IV "fixed interval colour model");
4. foreground ``F = [hsv in shirt interval]`` (§III-A: the subject wears a solid coloured shirt)
   -- or an externally given mask, e.g. background subtraction;
5. gradient of the binary foreground with a 2x1 and a 1x2 operator (§IV),
   ``G(x, y) = max(|F(x+1, y) - F(x, y)|, |F(x, y+1) - F(x, y)|)`` (0 on the last column/row);
6. spread the gradients with a Gaussian (§II-A, as Deutscher et al. [4]) and remap to [0, 1]
   by dividing by the image maximum: the edge map ``g`` of the edge cue ``p_g``.

Two implementations with identical outputs:

- :func:`segment` -- pure JAX (jit / vmap over the cameras / scan over frames). The 3x3 blur and
  the HSV conversion reproduce OpenCV's 8-bit fixed-point arithmetic bit-exactly, so the masks
  equal OpenCV's; the edge map agrees to float32 rounding.
- :func:`segment_cv` -- OpenCV + NumPy (``cv2.GaussianBlur``, ``cv2.cvtColor``, ``cv2.inRange``):
  the fast path at the I/O edge and the oracle of the tests.

HSV convention (OpenCV, 8-bit): ``V = max(R, G, B)`` in [0, 255]; ``S = 255 (V - min) / V`` in
[0, 255]; ``H`` = hue in degrees / 2, in [0, 180). An :class:`HSVInterval` is the closed box
``low <= (H, S, V) <= high``; when ``low[0] > high[0]`` the hue range wraps through red:
``H >= low[0] or H <= high[0]``.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, UInt8

# --- defaults ---------------------------------------------------------------------------------
# Azad et al. (§IV) segment skin with a "fixed interval colour model in HSV space" and the shirt
# with another (§III-A) but publish no numbers (they live in IVT's configuration). Ours:
# skin: hue 0..25 (0..50 deg: red-orange-yellowish, covering light to dark skin renderings
# such as RGB (255,219,172), (224,172,105), (141,85,36) -> H 14..17), saturation 40..230
# (excludes greys/white and fully saturated orange paint), value >= 60 (excludes dark shadows).
SKIN_HSV_LOW = (0, 40, 60)
SKIN_HSV_HIGH = (25, 230, 255)
# shirt: a saturated blue (hue 100..130 = 200..260 deg), the solid shirt of our synthetic
# scenes; change it to the colour of the subject's shirt.
SHIRT_HSV_LOW = (100, 80, 40)
SHIRT_HSV_HIGH = (130, 255, 255)
# spreading of the binary gradient image (§II-A / §IV "blurring the gradient image"); the paper
# gives no width: sigma = 1.5 px at 320x240, kernel 9 px (+-4 px = 2.7 sigma).
EDGE_SIGMA = 1.5
EDGE_KSIZE = 9

_HSV_SHIFT = 12  # OpenCV's fixed-point precision for the 8-bit RGB -> HSV conversion


class HSVInterval(eqx.Module):
    """A closed box in OpenCV 8-bit HSV space (H in [0, 180), S and V in [0, 255]).

    ``low[0] > high[0]`` denotes a hue range wrapping through 0 (reds): H >= low[0] or
    H <= high[0]. Bounds are arrays, so changing them does not recompile a jitted pipeline.
    """

    low: Int[Array, " 3"]
    high: Int[Array, " 3"]

    def __init__(
        self, low: Sequence[int | float] | ArrayLike, high: Sequence[int | float] | ArrayLike
    ):
        lo, hi = np.asarray(low), np.asarray(high)
        for name, v in (("low", lo), ("high", hi)):
            if v.shape != (3,) or not np.issubdtype(v.dtype, np.integer):
                raise ValueError(f"HSVInterval.{name}: expected 3 integers (H, S, V), got {v!r}")
            if not (0 <= v[0] < 180 and 0 <= v[1] <= 255 and 0 <= v[2] <= 255):
                raise ValueError(
                    f"HSVInterval.{name}={v.tolist()}: expected H in [0, 180) (OpenCV's degrees/2),"
                    " S and V in [0, 255]"
                )
        if lo[1] > hi[1] or lo[2] > hi[2]:
            raise ValueError(
                f"HSVInterval: expected low <= high for S and V, got low={lo.tolist()} "
                f"high={hi.tolist()} (only the hue range may wrap)"
            )
        self.low = jnp.asarray(lo, dtype=jnp.int32)
        self.high = jnp.asarray(hi, dtype=jnp.int32)


class SegmentParams(eqx.Module):
    """Parameters of the image processing line; defaults: the module constants above."""

    skin: HSVInterval
    shirt: HSVInterval
    edge_sigma: Float[Array, ""]  # px, Gaussian spreading of the gradient image
    edge_ksize: int = eqx.field(static=True)  # odd kernel size in px

    def __init__(
        self,
        skin: HSVInterval | None = None,
        shirt: HSVInterval | None = None,
        edge_sigma: float = EDGE_SIGMA,
        edge_ksize: int = EDGE_KSIZE,
    ):
        if not (isinstance(edge_ksize, int) and edge_ksize >= 1 and edge_ksize % 2 == 1):
            raise ValueError(
                f"SegmentParams.edge_ksize: expected an odd int >= 1, got {edge_ksize!r}"
            )
        if not float(edge_sigma) > 0:
            raise ValueError(f"SegmentParams.edge_sigma: expected > 0 px, got {edge_sigma!r}")
        self.skin = HSVInterval(SKIN_HSV_LOW, SKIN_HSV_HIGH) if skin is None else skin
        self.shirt = HSVInterval(SHIRT_HSV_LOW, SHIRT_HSV_HIGH) if shirt is None else shirt
        self.edge_sigma = jnp.asarray(edge_sigma, dtype=jnp.float32)
        self.edge_ksize = edge_ksize


class Segmentation(eqx.Module):
    """Output of the image processing line for one image (or a leading batch of cameras)."""

    skin: Bool[Array | np.ndarray, "*batch h w"]  # skin-colour map (hands, head)
    foreground: Bool[Array | np.ndarray, "*batch h w"]  # shirt / given foreground F
    edges: Float[Array | np.ndarray, "*batch h w"]  # spread gradient map g in [0, 1], float32


# --- JAX implementation -----------------------------------------------------------------------


def _reflect101(x: Array, r: int, axis: int) -> Array:
    pad = [(0, 0)] * x.ndim
    pad[axis] = (r, r)
    return jnp.pad(x, pad, mode="reflect")  # numpy's "reflect" == OpenCV's BORDER_REFLECT_101


def _correlate1d(x: Array, kernel: Array, axis: int) -> Array:
    """Separable 1D correlation along ``axis`` with BORDER_REFLECT_101, as sums of shifts."""
    r = (kernel.shape[0] - 1) // 2
    xp = _reflect101(x, r, axis)
    n = x.shape[axis]
    out = kernel[0] * jax.lax.slice_in_dim(xp, 0, n, axis=axis)
    for i in range(1, kernel.shape[0]):
        out = out + kernel[i] * jax.lax.slice_in_dim(xp, i, i + n, axis=axis)
    return out


def _blur3_planes(planes: Array) -> Array:
    """3x3 binomial blur of (c, h, w) uint8 planes, OpenCV rounding ``(sum + 8) >> 4``.

    Planes keep the image width as the minor axis, so every step vectorises."""
    k = jnp.array([1, 2, 1], dtype=jnp.int16)  # sums <= 16 * 255: int16 (wider SIMD lanes)
    s = _correlate1d(_correlate1d(planes.astype(jnp.int16), k, 1), k, 2)
    return ((s + 8) >> 4).astype(jnp.int32)


def gaussian_blur_3x3(image: UInt8[Array, "h w c"]) -> UInt8[Array, "h w c"]:
    """3x3 Gaussian ``[1 2 1]^T [1 2 1] / 16`` with OpenCV's rounding: ``(sum + 8) >> 4``.

    Bit-exact with ``cv2.GaussianBlur(image, (3, 3), 0)`` (BORDER_REFLECT_101).
    """
    planes = _blur3_planes(jnp.moveaxis(image, -1, 0))
    return jnp.moveaxis(planes, 0, -1).astype(jnp.uint8)


def _round_div(num: int, den: Array) -> Array:
    """``round(num / den)`` for integer den in [1, 255] as int32; float32 division reproduces
    OpenCV's double-precision division tables exactly for these numerators (checked in tests)."""
    q = jnp.float32(num) / den.astype(jnp.float32)
    return jnp.floor(q + jnp.float32(0.5)).astype(jnp.int32)


def _hsv_planes(r: Array, g: Array, b: Array) -> tuple[Array, Array, Array]:
    """OpenCV's 8-bit RGB -> HSV on int32 planes: ``V = max``,
    ``S = (diff * round(255 * 2^12 / V) + 2^11) >> 12``,
    ``H = (h' * round(180 * 2^12 / (6 diff)) + 2^11) >> 12`` (+180 if negative), with ``h'``
    the hexcone sector offset (``g - b``, ``b - r + 2 diff`` or ``r - g + 4 diff``)."""
    v = jnp.maximum(jnp.maximum(r, g), b)
    diff = v - jnp.minimum(jnp.minimum(r, g), b)
    half = 1 << (_HSV_SHIFT - 1)
    sdiv = jnp.where(v > 0, _round_div(255 << _HSV_SHIFT, jnp.maximum(v, 1)), 0)
    hdiv = jnp.where(diff > 0, _round_div((180 << _HSV_SHIFT) // 6, jnp.maximum(diff, 1)), 0)
    s = (diff * sdiv + half) >> _HSV_SHIFT
    h = jnp.where(v == r, g - b, jnp.where(v == g, b - r + 2 * diff, r - g + 4 * diff))
    h = (h * hdiv + half) >> _HSV_SHIFT
    h = jnp.where(h < 0, h + 180, h)
    return h, s, v


def rgb_to_hsv(image: UInt8[Array, "*batch 3"]) -> UInt8[Array, "*batch 3"]:
    """RGB -> HSV in OpenCV's 8-bit fixed-point arithmetic (== ``cv2.COLOR_RGB2HSV``).

    ``V = max``, ``S = round(diff * 255 / V)``, ``H = round(h' * 180 / (6 diff))`` with
    ``h'`` the hexcone sector offset; H in [0, 180) (degrees / 2).
    """
    x = image.astype(jnp.int32)
    hsv = _hsv_planes(x[..., 0], x[..., 1], x[..., 2])
    return jnp.stack(hsv, axis=-1).astype(jnp.uint8)


def _in_range_planes(h: Array, s: Array, v: Array, interval: HSVInterval) -> Array:
    lo, hi = interval.low, interval.high
    hue = jnp.where(lo[0] <= hi[0], (h >= lo[0]) & (h <= hi[0]), (h >= lo[0]) | (h <= hi[0]))
    return hue & (s >= lo[1]) & (s <= hi[1]) & (v >= lo[2]) & (v <= hi[2])


def in_range(hsv: UInt8[Array, "*batch 3"], interval: HSVInterval) -> Bool[Array, "*batch"]:
    """``low <= hsv <= high`` per channel (hue wrapping when ``low[0] > high[0]``)."""
    x = hsv.astype(jnp.int32)
    return _in_range_planes(x[..., 0], x[..., 1], x[..., 2], interval)


def binary_gradient(mask: Bool[Array, "h w"], dtype=jnp.float32) -> Float[Array, "h w"]:
    """2x1 + 1x2 gradient of a binary image (Azad §IV), combined by max (the logical OR).

    ``G(x, y) = max(|F(x+1, y) - F(x, y)|, |F(x, y+1) - F(x, y)|)``, 0 where ``x+1`` or ``y+1``
    leaves the image: 1 on the foreground/background boundary, 0 elsewhere.
    """
    gx = jnp.pad(mask[:, 1:] != mask[:, :-1], ((0, 0), (0, 1)))
    gy = jnp.pad(mask[1:, :] != mask[:-1, :], ((0, 1), (0, 0)))
    return (gx | gy).astype(dtype)


def gaussian_kernel(ksize: int, sigma: Float[ArrayLike, ""]) -> Float[Array, " k"]:
    """Normalised 1D Gaussian ``exp(-(i - (k-1)/2)^2 / (2 sigma^2))`` (== cv2.getGaussianKernel)."""
    sigma = jnp.asarray(sigma, dtype=jnp.float32)
    x = jnp.arange(ksize, dtype=jnp.float32) - (ksize - 1) / 2
    k = jnp.exp(-(x * x) / (2 * sigma * sigma))
    return k / jnp.sum(k)


def edge_map(
    foreground: Bool[Array, "h w"],
    sigma: Float[ArrayLike, ""] = EDGE_SIGMA,
    ksize: int = EDGE_KSIZE,
) -> Float[Array, "h w"]:
    """Edge map ``g`` of the edge cue (Azad §II-A, §III-A): the binary gradient of the
    foreground, spread with a ``ksize`` Gaussian of width ``sigma`` px (BORDER_REFLECT_101),
    remapped to [0, 1] by its maximum (all zeros when there is no edge). float32."""
    k = gaussian_kernel(ksize, sigma)
    spread = _correlate1d(_correlate1d(binary_gradient(foreground), k, 1), k, 0)
    peak = jnp.max(spread)
    return jnp.where(peak > 0, spread / jnp.where(peak > 0, peak, 1), 0).astype(jnp.float32)


def segment(
    params: SegmentParams,
    image: UInt8[Array, "h w 3"],
    foreground: Bool[Array, "h w"] | None = None,
) -> Segmentation:
    """The image processing line for one RGB image (Azad §IV, Fig. 3); pure, jit/vmap-able.

    ``foreground``: an external foreground mask (e.g. background subtraction) used instead of
    the shirt-colour segmentation. Returns skin map, foreground and the edge map ``g``.
    """
    r, g, b = _blur3_planes(jnp.moveaxis(image, -1, 0))
    hsv = _hsv_planes(r, g, b)
    skin = _in_range_planes(*hsv, params.skin)
    fg = _in_range_planes(*hsv, params.shirt) if foreground is None else foreground.astype(bool)
    return Segmentation(skin, fg, edge_map(fg, params.edge_sigma, params.edge_ksize))


@jax.jit
def segment_views(
    params: SegmentParams,
    images: UInt8[Array, "n h w 3"],
    foregrounds: Bool[Array, "n h w"] | None = None,
) -> Segmentation:
    """:func:`segment` vmapped over the cameras (e.g. a stereo pair), jitted."""
    return jax.vmap(segment, in_axes=(None, 0, 0))(params, images, foregrounds)


# --- OpenCV implementation (edge fast path, test oracle) --------------------------------------


def _in_range_cv(hsv: np.ndarray, interval: HSVInterval) -> np.ndarray:
    lo, hi = np.asarray(interval.low), np.asarray(interval.high)
    if lo[0] <= hi[0]:
        return cv2.inRange(hsv, lo.astype(np.uint8), hi.astype(np.uint8)) > 0
    upper = cv2.inRange(hsv, lo.astype(np.uint8), np.array([179, hi[1], hi[2]], np.uint8))
    lower = cv2.inRange(hsv, np.array([0, lo[1], lo[2]], np.uint8), hi.astype(np.uint8))
    return (upper | lower) > 0


def segment_cv(
    params: SegmentParams,
    image: np.ndarray,
    foreground: np.ndarray | None = None,
) -> Segmentation:
    """:func:`segment` with OpenCV + NumPy on the host; same outputs, as NumPy arrays.

    ``image``: (h, w, 3) uint8 RGB; ``foreground``: optional (h, w) mask (nonzero = foreground).
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(
            f"segment_cv: image: expected an (h, w, 3) uint8 RGB array, got "
            f"{image.dtype} {image.shape}"
        )
    if foreground is not None and foreground.shape != image.shape[:2]:
        raise ValueError(
            f"segment_cv: foreground: expected shape {image.shape[:2]}, got {foreground.shape}"
        )
    hsv = cv2.cvtColor(cv2.GaussianBlur(image, (3, 3), 0), cv2.COLOR_RGB2HSV)
    skin = _in_range_cv(hsv, params.skin)
    fg = _in_range_cv(hsv, params.shirt) if foreground is None else foreground.astype(bool)
    grad = np.zeros(fg.shape, np.uint8)
    grad[:, :-1] = fg[:, 1:] != fg[:, :-1]
    grad[:-1, :] |= fg[1:, :] != fg[:-1, :]
    sigma = float(params.edge_sigma)
    k = params.edge_ksize
    spread = cv2.GaussianBlur(
        grad.astype(np.float32), (k, k), sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT_101
    )
    peak = spread.max()
    edges = spread / peak if peak > 0 else np.zeros_like(spread)
    return Segmentation(skin, fg, edges.astype(np.float32))
