"""Colours that follow the light: a colour state per part, relit and updated on-line from the
pixels that the tracked pose's render gives each part (issue 37; both trackers).

Wang et al. (§5.2 step 5) follow the light with one 3 x 3 white balance per camera, re-fitted
on the final pose's render, and fall back to *reference illuminations* when it is lost. One
matrix per camera cannot represent two lamps of different colour on one shirt, nor a surface
turning from one lamp to the other: on the test world's dev split even the best single W per
camera (fitted to ground truth) gives 54-63% of the visible shirt pixels their colour with
Wang's pose prior, where a Gaussian per *patch* learned on-line from the pixels the true pose
assigns to it gives 70-85% (``benchmarks/experiments/appearance_ladder.py``,
docs/results/appearance.md). This
module is that state, shared by the colour-shirt tracker (a part = a patch, per camera) and
the stereo filter (a part = head, each hand, the shirt):

* :class:`PartColours`: per part a Gaussian (``mean``, ``cov``) in the tracker's colour space,
  the calibrated Gaussian it started from (``ref_mean``, ``ref_cov``: scribbles of the first
  frames, the default start), the part's share of the first of two illuminants (``mix``) and
  the frames since it was last updated (``age``).
* :func:`part_statistics`: per part the mean and covariance of the pixels a render assigns to
  it (the caller erodes the render: no pixel on a border), **trimmed** by a Mahalanobis gate
  around the part's relit state, with the shading-invariant distance of
  :mod:`jaxmocap.color.classify` when ``shading`` is given (pixels brought to the part's
  brightness first, as :func:`jaxmocap.color.fit_color_model` does).
* :func:`part_distances`: every pixel's (shading-invariant) squared distance to every part's
  state, to classify pixels by the parts' current colours.
* :func:`fit_relight`: **a mixture of two illuminants per camera** with the parts' own states
  as the reference materials (Hsu et al., "Light mixture estimation for spatially varying
  white balance", SIGGRAPH 2008: each pixel's light is ``w L_0 + (1 - w) L_1``; here each
  part's). One Levenberg-Marquardt solve (optimistix) of the change of the two illuminants
  ``r_0, r_1`` (per channel gains), each part's mixture weight ``w_p`` and brightness ``s_p``,
  in logs, with priors toward no change and the last mixture weights:

      log m_p^obs = log s_p + log(w_p r_0 + (1 - w_p) r_1) + log m_p       (seen parts)

  so a lamp dimmed or switched off relights **every** part, also those not seen this frame,
  by its own mixture. Differentiable (jit / vmap / grad through the solve).
* :func:`follow_light`: on a frame the tracker could not use shortly after a valid one, the
  light alone, from the pixels of the held pose's render: each part seen there takes its own
  observed gain (per-part gain model), the others the mixture fit's (a lamp switched off
  within a frame makes that frame invalid: it is followed without a reset). The own gain:
  in the tracker test of a warm and a cool lamp switched on over the two halves of the image,
  the mixture alone (rms 0.18-0.20 in log) left every later frame invalid, the own gains had
  it tracked again from the next frame.
* :func:`update_parts`: the relit state moved toward the trimmed statistics with weight
  ``rate`` (moment-matched, exponential forgetting), its spread kept within
  ``[min_spread, max_spread]`` times the calibrated one's in every direction; an **invalid
  frame leaves the state untouched**, and after ``lost_frames`` invalid frames in a row it
  relaxes toward the calibrated model (:func:`relax`).

Everything stays physical: a relight whose gains leave :data:`GAIN_RANGE`, whose illuminant
change is more chromatic than :data:`MAX_CHROMA` (ratio of its largest to smallest channel
gain) or whose log residual exceeds :data:`MAX_RELIGHT_RMS` is rejected for that frame (the
state is then only updated by the statistics, and the rejection is reported); a part's mean
stays inside the colour cube, its covariance positive definite with a bounded condition number
(the spread bounds).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

RATE = 0.3  # one frame's statistics weigh this much (dev split: 0.3 follows a 30-frame dimming)
MIN_PIXELS = 20.0  # a part needs this many trimmed pixels to be updated (and to enter the relight)
# trim: a pixel farther than this squared distance (5 standard deviations) from its part's
# relit state is not the part's (a hand across a patch, a neighbour's colour bleeding in)
GATE = 25.0
# spread of an updated covariance along any direction, relative to the calibrated one's. With
# the true pose (benchmarks/experiments/appearance_ladder.py, dev split) a looser state (gate
# 100, spread 3) classified more pixels right (77-84% vs 70-75%), but in the tracker's loop
# it learned the wrong patches from wrong poses: mean all-frames error over the dev split 14.0
# cm with these values, 26.4 with gate 100, spread 3 and a 4x stronger pose prior, 28.2 with
# gate 100, spread 3 and follow_light (docs/results/appearance.md)
MAX_SPREAD = 1.0
MIN_SPREAD = 0.5
GAIN_RANGE = (0.1, 10.0)  # a relight's per-part, per-channel gain must lie inside
MAX_CHROMA = 4.0  # an illuminant change: largest over smallest channel gain at most this
MAX_RELIGHT_RMS = 0.35  # RMS log residual over the seen parts' channels (~ 40% colour error)
MIX_PRIOR = 0.3  # weight of the prior on the mixture logits (per unit logit)
CHANGE_PRIOR = 0.2  # weight of the prior toward no illuminant change (per unit log gain)
SCALE_PRIOR = 0.02  # weight of the prior toward a part's brightness unchanged (per unit log)
LOST_FRAMES = 10  # invalid frames in a row after which the state relaxes toward the calibration
RELAX_RATE = 0.1  # per invalid frame after that
MAX_DRIFT = 4.0  # a relit mean stays within this factor of its calibrated mean per channel
COLOUR_MAX = 255.0 * 1.5  # a mean stays inside [1, COLOUR_MAX] per channel (W-mapped colours
# can leave 0..255 a little)
_EPS = 1.0


class PartColours(eqx.Module):
    """Per part ``i`` a Gaussian ``N(mean[i], cov[i])`` and what it started from; batch it
    (e.g. over cameras) with ``jax.vmap``."""

    mean: Float[Array, "n 3"]
    cov: Float[Array, "n 3 3"]
    ref_mean: Float[Array, "n 3"]
    ref_cov: Float[Array, "n 3 3"]
    mix: Float[Array, " n"]  # share of illuminant 0 in each part's light
    age: Int[Array, " n"]  # frames since the part was last updated (0: this frame)
    lost: Int[Array, ""]  # invalid frames in a row


def init_parts(
    mean: Float[Array, "n 3"], cov: Float[Array, "n 3 3"], mix: Float[Array, " n"] | None = None
) -> PartColours:
    """The calibrated start (e.g. the scribbled colour of every patch): state = reference;
    ``mix`` each part's share of illuminant 0 (default 0.5: not known)."""
    mean, cov = jnp.asarray(mean), jnp.asarray(cov)
    n = mean.shape[0]
    mix = jnp.full((n,), 0.5, mean.dtype) if mix is None else jnp.asarray(mix, mean.dtype)
    return PartColours(mean, cov, mean, cov, mix,
                       jnp.zeros((n,), jnp.int32), jnp.zeros((), jnp.int32))  # fmt: skip


class PartStats(NamedTuple):
    """Per part: trimmed pixel count, raw mean (what the light does) and the mean and
    covariance of the shading-normalised pixels (what the classifier compares)."""

    count: Float[Array, " n"]
    raw_mean: Float[Array, "n 3"]
    mean: Float[Array, "n 3"]
    cov: Float[Array, "n 3 3"]


def _precision(cov):
    chol = jnp.linalg.cholesky(cov)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=cov.dtype), cov.shape)
    inv = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
    return jnp.swapaxes(inv, -1, -2) @ inv


def part_statistics(
    state: PartColours,
    image: Float[Array, "h w 3"],
    parts: Int[Array, "h w"],
    gate: float | Float[Array, ""] = GATE,
    shading: tuple[float, float] | None = None,
    mask: Bool[Array, "h w"] | None = None,
) -> PartStats:
    """Statistics of the pixels of ``image`` (the tracker's colour space) that ``parts``
    (0 = none, ``1..n``) gives each part, trimmed at squared distance ``gate`` from the
    part's state (shading-invariant with ``shading = (lo, hi)``); ``mask``: pixels to use."""
    n = state.mean.shape[0]
    dt = state.mean.dtype
    x = image.reshape(-1, 3).astype(dt)
    seg = parts.reshape(-1).astype(jnp.int32)
    if mask is not None:
        seg = jnp.where(mask.reshape(-1), seg, 0)
    idx = jnp.clip(seg - 1, 0, n - 1)
    mu, prec = state.mean[idx], _precision(state.cov)[idx]  # (N, 3), (N, 3, 3)
    if shading is None:
        y = x
    else:
        xpx = jnp.einsum("ni,nij,nj->n", x, prec, x)
        a = jnp.einsum("ni,nij,nj->n", x, prec, mu) / jnp.maximum(xpx, 1e-12)
        y = jnp.clip(a, shading[0], shading[1])[:, None] * x
    d = y - mu
    d2 = jnp.einsum("ni,nij,nj->n", d, prec, d)
    seg = jnp.where(d2 <= gate, seg, 0)
    ones = jnp.ones(seg.shape, dt)
    count = jax.ops.segment_sum(ones, seg, n + 1)[1:]
    c = jnp.maximum(count, 1)
    raw = jax.ops.segment_sum(x, seg, n + 1)[1:] / c[:, None]
    m = jax.ops.segment_sum(y, seg, n + 1)[1:] / c[:, None]
    yy = jax.ops.segment_sum(y[:, :, None] * y[:, None, :], seg, n + 1)[1:] / c[:, None, None]
    cov = yy - m[:, :, None] * m[:, None, :]
    return PartStats(count, raw, m, cov)


def part_distances(
    state: PartColours,
    pixels: Float[Array, "*s 3"],
    shading: tuple[float, float] | None = None,
) -> Float[Array, "*s n"]:
    """Squared Mahalanobis distance of every pixel to every part's Gaussian; with ``shading =
    (lo, hi)`` the shading-invariant ``min_a (a x - mean)^T cov^-1 (a x - mean)`` over ``a`` in
    ``[lo, hi]`` (a surface in its own shadow or highlight: the distance
    :func:`part_statistics` trims with). For classifying pixels by the parts' states, e.g. a
    search for one part's pixels near where it is predicted."""
    dt = state.mean.dtype
    n = state.mean.shape[0]
    x = jnp.broadcast_to(pixels.reshape(-1, 1, 3).astype(dt), (pixels.size // 3, n, 3))
    prec = _precision(state.cov)[None]  # (1, n, 3, 3)
    mu = state.mean[None]  # (1, n, 3)
    if shading is not None:
        xpx = jnp.einsum("kni,knij,knj->kn", x, jnp.broadcast_to(prec, x.shape + (3,)), x)
        a = jnp.einsum("kni,knij,knj->kn", x, jnp.broadcast_to(prec, x.shape + (3,)),
                       jnp.broadcast_to(mu, x.shape)) / jnp.maximum(xpx, 1e-12)
        x = jnp.clip(a, shading[0], shading[1])[..., None] * x
    d = x - jnp.broadcast_to(mu, x.shape)
    d2 = jnp.einsum("kni,knij,knj->kn", d, jnp.broadcast_to(prec, x.shape + (3,)), d)
    return d2.reshape(pixels.shape[:-1] + (n,))


class Relight(NamedTuple):
    """A fitted change of two illuminants: per part the gain of its light (3 channels, the
    part's brightness change included where it was seen) and mixture weight, whether the fit
    is physical (else it must not be applied), its RMS log residual and the illuminant
    changes ``r`` (2, 3)."""

    gains: Float[Array, "n 3"]
    mix: Float[Array, " n"]
    ok: Bool[Array, ""]
    rms: Float[Array, ""]
    change: Float[Array, "2 3"]


def fit_relight(
    state: PartColours,
    stats: PartStats,
    min_pixels: float | Float[Array, ""] = MIN_PIXELS,
    max_steps: int = 24,
) -> Relight:
    """The change of a two-illuminant mixture that explains the parts' raw means this frame
    from their states (module docstring): one optimistix Levenberg-Marquardt solve. Parts with
    fewer than ``min_pixels`` trimmed pixels do not enter the data term; their gain is their
    mixture of the two illuminant changes at unchanged brightness."""
    n, dt = state.mean.shape[0], state.mean.dtype
    seen = (stats.count >= min_pixels).astype(dt)
    sw = jnp.sqrt(seen * jnp.minimum(stats.count, 400.0) / 400.0)[:, None]
    log_obs = jnp.log(jnp.maximum(stats.raw_mean, _EPS))
    log_state = jnp.log(jnp.maximum(state.mean, _EPS))
    logit0 = jnp.log(jnp.clip(state.mix, 1e-3, 1 - 1e-3)) - jnp.log1p(
        -jnp.clip(state.mix, 1e-3, 1 - 1e-3)
    )

    def model(x):
        log_r, logit, log_s = x
        w = jax.nn.sigmoid(logit)[:, None]
        r = jnp.exp(log_r)
        mixed = w * r[0][None, :] + (1 - w) * r[1][None, :]
        return log_s[:, None] + jnp.log(mixed) + log_state, w[:, 0], r

    def residual(x, _):
        log_r, logit, log_s = x
        pred, _, _ = model(x)
        data = (sw * (pred - log_obs)).reshape(-1)
        return jnp.concatenate([
            data,
            CHANGE_PRIOR * log_r.reshape(-1),
            MIX_PRIOR * (logit - logit0),
            SCALE_PRIOR * log_s,
        ])  # fmt: skip

    x0 = (*_split_start(log_obs - log_state, seen, state.mix), jnp.zeros((n,), dt))
    tol = 1e-8 if dt == jnp.float64 else 1e-5
    sol = optx.least_squares(residual, optx.LevenbergMarquardt(rtol=tol, atol=tol), x0,
                             max_steps=max_steps, throw=False)  # fmt: skip
    log_s = sol.value[2]
    pred, w, r = model(sol.value)
    scale = jnp.exp(log_s * seen)  # unseen parts keep their brightness
    gains = scale[:, None] * (w[:, None] * r[0][None, :] + (1 - w[:, None]) * r[1][None, :])
    n_seen = jnp.maximum(jnp.sum(seen), 1)
    rms = jnp.sqrt(jnp.sum(seen[:, None] * jnp.square(pred - log_obs)) / (3 * n_seen))
    chroma = jnp.max(r, axis=1) / jnp.min(r, axis=1)
    ok = (
        jnp.all(jnp.isfinite(gains))
        & jnp.all((gains >= GAIN_RANGE[0]) & (gains <= GAIN_RANGE[1]))
        & jnp.all(chroma <= MAX_CHROMA)
        & (rms <= MAX_RELIGHT_RMS)
        & (jnp.sum(seen) >= 2)
    )
    return Relight(gains, w, ok, rms, r)


def _split_start(d, seen, mix, rounds: int = 6):
    """Start of the relight solve from the seen parts' log changes ``d`` (n, 3): two-means of
    the seen parts' chromatic changes (split first along their main direction, weighted by
    ``seen``), the two illuminant changes the clusters' mean log changes, each part's logit
    +-2 toward its cluster, the pair ordered to agree with the last mixture weights ``mix``.
    (From equal illuminants and equal weights the problem is symmetric: a Gauss-Newton step
    never splits the lamps; from the two most distant parts one outlier part sets a lamp.)"""
    dc = d - jnp.mean(d, axis=-1, keepdims=True)
    mean = jnp.sum(seen[:, None] * dc, 0) / jnp.maximum(jnp.sum(seen), 1e-9)
    cov = jnp.einsum("n,ni,nj->ij", seen, dc - mean[None, :], dc - mean[None, :])
    v = jnp.linalg.eigh(cov + 1e-12 * jnp.eye(3, dtype=d.dtype))[1][:, -1]
    in0 = (dc - mean[None, :]) @ v >= 0
    for _ in range(rounds):
        w0, w1 = seen * in0, seen * ~in0
        c0 = jnp.sum(w0[:, None] * dc, 0) / jnp.maximum(jnp.sum(w0), 1e-9)
        c1 = jnp.sum(w1[:, None] * dc, 0) / jnp.maximum(jnp.sum(w1), 1e-9)
        in0 = (jnp.linalg.norm(dc - c0[None, :], axis=-1)
               <= jnp.linalg.norm(dc - c1[None, :], axis=-1))
    w0, w1 = seen * in0, seen * ~in0
    r0 = jnp.sum(w0[:, None] * d, 0) / jnp.maximum(jnp.sum(w0), 1e-9)
    r1 = jnp.sum(w1[:, None] * d, 0) / jnp.maximum(jnp.sum(w1), 1e-9)
    r1 = jnp.where(jnp.sum(w1) > 0, r1, r0)
    r0 = jnp.where(jnp.sum(w0) > 0, r0, r1)
    sign = jnp.where(in0, 1.0, -1.0).astype(d.dtype)
    swap = jnp.sum(seen * (mix - 0.5) * sign) < 0
    log_r = jnp.where(swap, jnp.stack([r1, r0]), jnp.stack([r0, r1]))
    return log_r, 2.0 * jnp.where(swap, -sign, sign)


def _bounded_cov(cov, ref_cov, min_spread, max_spread):
    """``cov`` with its eigenvalues in ``ref_cov``'s whitened space clipped to
    ``[min_spread^2, max_spread^2]`` (spread and condition number bounded by the reference's)."""
    lr = jnp.linalg.cholesky(ref_cov)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=cov.dtype), cov.shape)
    li = jax.scipy.linalg.solve_triangular(lr, eye, lower=True)
    a = li @ cov @ jnp.swapaxes(li, -1, -2)
    w, v = jnp.linalg.eigh(0.5 * (a + jnp.swapaxes(a, -1, -2)))
    w = jnp.clip(w, min_spread**2, max_spread**2)
    a = (v * w[..., None, :]) @ jnp.swapaxes(v, -1, -2)
    return lr @ a @ jnp.swapaxes(lr, -1, -2)


def relit(state: PartColours, relight: Relight) -> PartColours:
    """``state`` with every part's Gaussian under the fitted light change (``relight.ok``
    false: unchanged): ``mean -> g * mean``, ``cov -> diag(g) cov diag(g)``."""
    g = jnp.where(relight.ok, relight.gains, 1.0)
    # a part unseen for long is relit by every frame's fit: bounded within MAX_DRIFT of its
    # calibration per channel, its colour cannot random-walk off (the stereo filter's hands,
    # seen on few frames, reached the colour range's bound within 20 frames without it)
    mean = jnp.clip(g * state.mean, state.ref_mean / MAX_DRIFT, state.ref_mean * MAX_DRIFT)
    mean = jnp.clip(mean, 1.0, COLOUR_MAX)
    cov = g[:, :, None] * state.cov * g[:, None, :]
    mix = jnp.where(relight.ok, relight.mix, state.mix)
    return eqx.tree_at(lambda s: (s.mean, s.cov, s.mix), state, (mean, cov, mix))


def update_parts(
    state: PartColours,
    stats: PartStats,
    valid: Bool[Array, ""],
    rate: float | Float[Array, ""] | Float[Array, " n"] = RATE,
    min_pixels: float | Float[Array, ""] = MIN_PIXELS,
    min_spread: float = MIN_SPREAD,
    max_spread: float = MAX_SPREAD,
    relight: bool = True,
) -> tuple[PartColours, Bool[Array, " n"], Relight]:
    """One frame's update (module docstring): relight (when ``relight`` and the fit is
    physical), then each part with ``min_pixels`` trimmed pixels moved toward its
    statistics by ``rate`` (one for all parts, or one per part); an invalid frame (``valid``
    false) returns ``state`` unchanged
    but for the lost-frame count and, after :data:`LOST_FRAMES`, the relaxation toward the
    calibration. Returns ``(state, updated parts, relight fit)``."""
    dt = state.mean.dtype
    if relight:
        fit = fit_relight(state, stats, min_pixels)
        s = relit(state, fit)
    else:
        n = state.mean.shape[0]
        fit = Relight(jnp.ones((n, 3), dt), state.mix, jnp.array(False), jnp.zeros((), dt),
                      jnp.ones((2, 3), dt))  # fmt: skip
        s = state
    use = stats.count >= min_pixels
    a = jnp.where(use, jnp.asarray(rate, dt), 0.0)[:, None]
    m = (1 - a) * s.mean + a * stats.mean
    d0, d1 = s.mean - m, stats.mean - m
    outer = lambda u: u[:, :, None] * u[:, None, :]  # noqa: E731
    cov = (1 - a[:, :, None]) * (s.cov + outer(d0)) + a[:, :, None] * (stats.cov + outer(d1))
    cov = _bounded_cov(cov, s.ref_cov, min_spread, max_spread)
    m = jnp.clip(m, 1.0, COLOUR_MAX)
    good = jnp.all(jnp.isfinite(m), axis=-1) & jnp.all(jnp.isfinite(cov), axis=(-2, -1))
    use = use & good
    m = jnp.where(good[:, None], m, s.mean)
    cov = jnp.where(good[:, None, None], cov, s.cov)
    new = PartColours(m, cov, state.ref_mean, state.ref_cov, s.mix,
                      jnp.where(use, 0, state.age + 1).astype(jnp.int32),
                      jnp.zeros((), jnp.int32))  # fmt: skip
    lost = eqx.tree_at(lambda t: (t.age, t.lost), state,
                       ((state.age + 1).astype(jnp.int32), (state.lost + 1).astype(jnp.int32)))
    lost = jax.lax.cond(lost.lost > LOST_FRAMES, lambda t: relax(t, RELAX_RATE), lambda t: t,
                        lost)  # fmt: skip
    out = jax.tree.map(lambda u, v: jnp.where(valid, u, v), new, lost)
    return out, use & valid, fit._replace(ok=fit.ok & valid)


def follow_light(
    state: PartColours, stats: PartStats, on: Bool[Array, ""],
    min_pixels: float | Float[Array, ""] = MIN_PIXELS,
) -> tuple[PartColours, Relight]:
    """The light followed through a frame the tracker could not use (``on``: invalid, but
    the last valid pose is recent): only the two-illuminant relight (no statistics enter the
    Gaussians), fitted on the pixels that the **held** pose's render gives each part
    (``stats``, untrimmed: after a lamp switch every pixel is far from the old state, and a
    trimmed fit sees nothing). A lamp switched off makes every classification fail at once,
    so the frame is invalid and :func:`update_parts` leaves the state as it was; without
    this the tracker would stay lost under the new light. A part seen there takes its own
    observed gain (within :data:`GAIN_RANGE`), the others the mixture fit's; applied only
    where the fit is physical."""
    fit = fit_relight(state, stats, min_pixels)
    seen = stats.count >= min_pixels
    own = jnp.maximum(stats.raw_mean, _EPS) / jnp.maximum(state.mean, _EPS)
    own_ok = jnp.all((own >= GAIN_RANGE[0]) & (own <= GAIN_RANGE[1]), axis=-1)
    gains = jnp.where((seen & own_ok)[:, None], own, fit.gains)
    fit = fit._replace(gains=gains, ok=fit.ok & on)
    return relit(state, fit), fit


def relax(state: PartColours, rate: float | Float[Array, ""]) -> PartColours:
    """``state`` moved toward its calibrated Gaussians by ``rate`` (moment-matched)."""
    a = jnp.asarray(rate, state.mean.dtype)
    m = (1 - a) * state.mean + a * state.ref_mean
    d0, d1 = state.mean - m, state.ref_mean - m
    outer = lambda u: u[:, :, None] * u[:, None, :]  # noqa: E731
    cov = (1 - a) * (state.cov + outer(d0)) + a * (state.ref_cov + outer(d1))
    cov = _bounded_cov(cov, state.ref_cov, MIN_SPREAD, MAX_SPREAD)
    mix = (1 - a) * state.mix + a * 0.5
    return eqx.tree_at(lambda s: (s.mean, s.cov, s.mix), state, (m, cov, mix))
