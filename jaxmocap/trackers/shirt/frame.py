"""The colour-shirt frame step (Wang et al. 2011 §5.2), one function per paper step; ``_step``
chains them under one jit (the frame walk: :mod:`jaxmocap.trackers.shirt`).

Why one file: the steps share the per-frame structures defined here (``Views``,
``DatabasePose``, ``RoundContext``) and are read in order as the paper's frame; the starts
(``starts_of``, ``orientation_starts``) and the rounds that run them are one mechanism."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxmocap import appearance
from jaxmocap.camera import Camera, camera_center, pixel_rays, to_camera
from jaxmocap.color import (
    classify_views_with_references,
    histogram_search,
    maybe_add_reference,
    white_balance_from_ids,
)
from jaxmocap.color.classify import THRESHOLD
from jaxmocap.color.illumination import MIN_CLASSIFIED_FRACTION, ReferenceClassification
from jaxmocap.color.pose_assisted import (
    POSE_THRESHOLD,
    PRIOR_SCALE,
    PatchCentroids,
    patch_centroids,
    patch_distance_maps,
    pose_assisted_classify,
)
from jaxmocap.garment import Garment
from jaxmocap.ik import (
    IKCovariances,
    append_anchors,
    append_centroid_covariances,
    initial_root,
    solve_global,
    solve_ik,
)
from jaxmocap.ik import view_anchors as _view_anchors
from jaxmocap.posedb._sample import pose_in_camera
from jaxmocap.posedb._search import estimate_hypotheses, estimate_pose
from jaxmocap.render import (
    TINY_SIZE,
    Hits,
    render_rays,
    render_uv,
    resample_ids,
    tiny_hits,
    window_from_mask,
)
from jaxmocap.sampling import (
    crop_to_image,
    crop_uv,
    crop_window,
    erode_ids,
    sample_bilinear_clamped,
    sample_nearest,
)
from jaxmocap.trackers.shirt.colours import (
    classify_by_patch,
    colour_update,
    in_look_space,
    patch_model,
)
from jaxmocap.trackers.shirt.params import (
    MAX_ROOT_OFFSET,
    MIN_VALID_PATCHES,
    REFERENCE_PIXELS,
    TIE_BREAK_WEIGHT,
    FrameSignals,
    ShirtOutput,
    ShirtParams,
    ShirtState,
)
from jaxmocap.trackers.shirt.skin import observe_skin, skin_maps


def _root_guess(
    params: ShirtParams, cam: Camera, q_db: Array, win_db: Array, win_q: Array
) -> Array:
    """Root (6) of the database pose placed in camera ``cam`` so that its canonical window
    ``win_db`` lands on the query window ``win_q``: the root's pixel keeps its normalised
    position in the window and its depth scales with the window side and focal length."""
    canon = params.canon
    dt = q_db.dtype
    root_c = canon.t.astype(dt)  # root at the origin: its canonical camera-frame position
    p_c = canon.K.astype(dt) @ root_c
    p_c = p_c[:2] / p_c[2]
    p_i = win_q[:2] + (p_c - win_db[:2]) * win_q[2] / win_db[2]
    depth = root_c[2] * (cam.K[0, 0] / canon.K[0, 0]) * (win_db[2] / win_q[2])
    o, d = pixel_rays(cam, p_i)
    X = o + d * depth / to_camera(cam, o + d)[2]
    q = pose_in_camera(q_db, cam, to_camera(cam, X))
    return q[:6]


def _widened(prior: Array, blend: Array, fresh: Array) -> Array:
    """``Sigma_p + Sigma_b`` where ``fresh``, else ``Sigma_p`` (each a matrix or a vector of
    variances; a matrix if either is)."""
    if prior.ndim != blend.ndim:
        prior = jnp.diag(prior) if prior.ndim == 1 else prior
        blend = jnp.diag(blend) if blend.ndim == 1 else blend
    return jnp.where(fresh, prior + blend.astype(prior.dtype), prior)


class Views(NamedTuple):
    """Steps 0–1, stacked over cameras: resampled crops, their foregrounds (or None), crop
    windows, scales ``s'``, whether the search found the shirt, step-1 classification."""

    crops: UInt8[Array, "n_cams n n 3"]
    fgs: Bool[Array, "n_cams n n"] | None
    windows: Float[Array, "n_cams 4"]
    s_found: Float[Array, " n_cams"]
    found: Bool[Array, " n_cams"]
    cls: ReferenceClassification
    learned: LearnedCosts | None = None  # the learned model's step-3 costs (colours.observer)


class DatabasePose(NamedTuple):
    """Step 2, stacked over cameras: blended database pose, query window (image px),
    ``q_db``'s tiny patch map and canonical window; ``okq`` cameras that found the shirt; the
    joint angles averaged over them."""

    q_dbs: Float[Array, "n_cams n_dof"]
    win_qs: Float[Array, "n_cams 4"]
    tiny_patch: Int[Array, "n_cams t t"]
    win_dbs: Float[Array, "n_cams 4"]
    okq: Bool[Array, " n_cams"]
    joints: Array


class RoundContext(NamedTuple):
    """What every round of steps 3–4 shares: the views, ``okq``, the placed blend ``q_g``,
    the temporal prior ``q_h``, the IK covariances, the crops' pixel grids and their rays
    (``(origins, dirs)`` stacked over cameras: every render of the frame casts the same rays,
    so the grid is undistorted once per frame, not once per render)."""

    views: Views
    okq: Array
    q_g: Array
    q_h: Array
    cov: IKCovariances
    uvs: Float[Array, "n_cams n n 2"]
    rays: tuple[Float[Array, "n_cams 3"], Float[Array, "n_cams n n 3"]]
    look: appearance.PartColours | None = None  # the patch colour states (``patch_colours``)
    look_W: Array | None = None
    # with ``orientation_hypotheses``: the placed hypotheses (orientation_starts), how many
    # of them are real, and whether the previous frame was lost (they start only then)
    hyps: Array | None = None
    n_hyps: Array | None = None
    lost: Array | None = None
    skin: Array | None = None  # with ``rounds.skin_terms``: the crops' skin pixels (skin_maps)


def locate_and_classify(params: ShirtParams, state: ShirtState, frames, masks) -> Views:
    """§4 + §5.2 step 1: histogram search and crop resampling per camera (unrolled: the
    search under vmap ran 9.3 -> 10.8 ms), then the classification of every crop with its
    reference illuminations in one ``vmap`` (:func:`classify_views_with_references`)."""
    n, dt = params.search.work_size, state.q.dtype
    crops, fgs, windows, s_found, found = [], [], [], [], []
    for i in range(params.n_cams):
        mask_i = None if masks is None else masks[i]
        res = histogram_search(frames[i], mask_i, scales=params.search.scales)
        win = crop_window(res.x.astype(dt), res.y.astype(dt), res.s.astype(dt),
                          params.search.crop_factor)
        uv = crop_uv(win, n)
        crops.append(sample_bilinear_clamped(frames[i], uv))
        fgs.append(None if masks is None else sample_nearest(masks[i], uv))
        windows.append(win), s_found.append(res.s.astype(dt)), found.append(res.found)
    crops = jnp.stack(crops)
    fgs = None if masks is None else jnp.stack(fgs)
    if params.colours.observer is not None:
        learned, cls = learned_classification(params, state, crops, fgs)
        return Views(crops, fgs, jnp.stack(windows), jnp.stack(s_found), jnp.stack(found), cls,
                     learned)
    if params.colours.patch_colours:
        cls = classify_by_patch(params, state, crops, fgs)
        return Views(crops, fgs, jnp.stack(windows), jnp.stack(s_found), jnp.stack(found), cls)
    cls = classify_views_with_references(
        params.color, state.refs, state.W, crops, fgs, THRESHOLD,
        min_fraction=MIN_CLASSIFIED_FRACTION if params.ablations.adaptive_white_balance else 0.0,
        gain=params.colours.shading, background=params.colours.scene_colors,
    )  # fmt: skip
    return Views(crops, fgs, jnp.stack(windows), jnp.stack(s_found), jnp.stack(found), cls)


def learned_classification(params: ShirtParams, state: ShirtState, crops, fgs):
    """Step 1 on the learned model (``colours.observer``, issue 49): per camera the
    log-probabilities of every crop pixel and the colour ids of the most probable class (skin
    and background: 0; outside the foreground mask: 0). ``fraction`` is the share of the
    crop's (foreground) pixels given a shirt colour; the white balance stays ``state.W``."""
    from jaxmocap.observe import log_probs

    K, dt = params.garment.n_colours, state.W.dtype

    def one(crop, fg, W):
        logp = log_probs(params.colours.observer, crop)
        best = jnp.argmax(logp, -1)
        ids = jnp.where(best <= K, best, 0).astype(jnp.int32)
        n_px = jnp.asarray(ids.size, dt)
        if fg is not None:
            ids = jnp.where(fg, ids, 0)
            n_px = jnp.maximum(jnp.sum(fg), 1).astype(dt)
        fraction = (jnp.sum(ids > 0) / n_px).astype(dt)
        costs = learned_costs(params.garment, logp)
        return costs, ReferenceClassification(ids=ids, distance=-jnp.max(logp, -1).astype(dt),
                                             W=W, fraction=fraction,
                                             used_reference=jnp.array(False))

    return jax.vmap(one, in_axes=(0, None if fgs is None else 0, 0))(crops, fgs, state.W)


class LearnedCosts(NamedTuple):
    """Step 3's data terms from the learned model, once per frame (every IK round reuses them):
    ``patch[p - 1] = -log p(colour(p))`` per pixel, ``rest = -log p(not shirt)``."""

    patch: Float[Array, "*cams p h w"]
    rest: Float[Array, "*cams h w"]


def learned_costs(garment: Garment, logp: Float[Array, "h w c"]) -> LearnedCosts:
    """:class:`LearnedCosts` of one crop's log-probabilities."""
    K = garment.n_colours
    pc = jnp.asarray(garment.patch_colour, jnp.int32)
    p_shirt = jnp.sum(jnp.exp(logp[..., 1:K + 1]), -1)
    return LearnedCosts(jnp.moveaxis(-logp[..., pc], -1, 0),
                        -jnp.log(jnp.maximum(1 - p_shirt, 1e-12)))


def learned_pose_assisted(costs: LearnedCosts, dist: Float[Array, "p h w"], weight,
                          fg) -> Int[Array, "h w"]:
    """Step 3 on the learned model: the patch minimising ``-log p(colour(p)) + weight d_p``
    (``dist``: :func:`patch_distance_maps` of the prior) unless ``-log p(not shirt)``
    (background or skin) is lower; patch ids (0 none). A running minimum over the patch planes,
    as :func:`jaxmocap.color.pose_assisted_classify` (one fused loop, ties to the first)."""
    dt = costs.patch.dtype
    score = best = None
    for p in range(costs.patch.shape[0]):
        cost = costs.patch[p] + weight * dist[p].astype(dt)
        if score is None:
            score, best = cost, jnp.zeros(cost.shape, jnp.int32)
        else:
            better = cost < score
            score, best = jnp.where(better, cost, score), jnp.where(better, p, best)
    keep = score < costs.rest
    if fg is not None:
        keep = keep & fg
    return jnp.where(keep, best + 1, 0)


def database_pose(params: ShirtParams, views: Views, dt) -> DatabasePose:
    """§5.2 step 2: the database pose of every camera (one ``vmap``), joint angles averaged
    over the cameras that found the shirt."""
    n = params.search.work_size

    def one(ids, window, found):
        win_c = window_from_mask(ids > 0)
        tiny = resample_ids(ids, win_c, TINY_SIZE)
        q_db = estimate_pose(params.db, tiny)[0].astype(dt)
        hits, win_db = tiny_hits(params.body, params.garment, q_db, params.canon)
        ok = found & (jnp.sum(ids > 0) > 0)
        return q_db, crop_to_image(win_c, window, n), hits.patch, win_db, ok

    q_dbs, win_qs, tiny_patch, win_dbs, okq = jax.vmap(one)(
        views.cls.ids, views.windows, views.found
    )
    wq = okq.astype(dt) / jnp.maximum(jnp.sum(okq), 1)
    joints = jnp.sum(wq[:, None] * q_dbs[:, 6:], axis=0)
    return DatabasePose(q_dbs, win_qs, tiny_patch, win_dbs, okq, joints)


def global_placement(params: ShirtParams, db: DatabasePose, dt) -> Array:
    """§5.2 step 2 (global): the centroids of ``r^b``'s patches in each query window are 2D
    constraints of a 6-DOF IK from a closed-form root guess; returns the placed blend ``q_g``."""
    P, cams = params.garment.n_patches, params.cams
    cons = jax.vmap(lambda t, w: patch_centroids(t, P, w, min_pixels=2, dtype=dt))(
        db.tiny_patch, db.win_qs
    )
    c_xy, c_vis = cons.xy, cons.valid & db.okq[:, None]
    best = jnp.argmax(db.okq)  # first camera that found the shirt
    guesses = jax.vmap(lambda *a: _root_guess(params, *a))(cams, db.q_dbs, db.win_dbs, db.win_qs)
    q_b = jnp.concatenate([jnp.zeros(6, dt), db.joints])
    root0, _ = initial_root(
        cams, params.body.chain, params.anchors, c_xy, c_vis, q_b, guesses[best]
    )
    glob = solve_global(
        params.body.chain, cams, params.anchors, c_xy, c_vis, q_b, root0, params.cov.centroid
    )
    return glob.q


def orientation_starts(params: ShirtParams, views: Views, db: DatabasePose, dt):
    """Issue 38 item 2: every camera's orientation hypotheses
    (:func:`jaxmocap.posedb.estimate_hypotheses`, ``rounds.orientation_hypotheses`` of them:
    the nearest maps split into orientation clusters, each blended on its own), each placed
    in the world by step 2's global placement from that camera alone (its closed-form root
    guess, then the 6-DOF IK on the centroids of the hypothesis's own patch map in the query
    window). Returns ``(starts, n)``: the placed poses (n_cams * H, n_dof), the real ones
    first (a camera that did not find the shirt, or a query with fewer clusters, has none),
    and their count. A pose placed from one camera is not averaged with another camera's
    view of a different orientation (what :func:`global_placement` does with the joint angles
    of every camera's blend)."""
    H, P, n = params.rounds.orientation_hypotheses, params.garment.n_patches, params.n_cams
    cams = params.cams

    def one(c, ids, win_q, ok_cam):
        tiny = resample_ids(ids, window_from_mask(ids > 0), TINY_SIZE)
        hyp = estimate_hypotheses(params.db, tiny, H)
        cam = jax.tree.map(lambda a: a[c], cams)

        def place(q_h, d_h):
            q_h = q_h.astype(dt)
            hits, win_db = tiny_hits(params.body, params.garment, q_h, params.canon)
            guess = _root_guess(params, cam, q_h, win_db, win_q)
            cons = patch_centroids(hits.patch, P, win_q, min_pixels=2, dtype=dt)
            mine = (jnp.arange(n) == c)[:, None]
            c_xy = jnp.where(mine[..., None], cons.xy[None], 0.0)
            c_vis = mine & cons.valid[None]
            q_b = jnp.concatenate([jnp.zeros(6, dt), q_h[6:]])
            root0, _ = initial_root(cams, params.body.chain, params.anchors, c_xy, c_vis, q_b,
                                    guess)
            glob = solve_global(params.body.chain, cams, params.anchors, c_xy, c_vis, q_b,
                                root0, params.cov.centroid)
            ok = ok_cam & jnp.isfinite(d_h) & jnp.all(jnp.isfinite(glob.q))
            return glob.q, ok

        return jax.vmap(place)(hyp.poses, hyp.distance)

    qs, ok = jax.vmap(one)(jnp.arange(n), views.cls.ids, db.win_qs, db.okq)
    qs, ok = qs.reshape(n * H, -1), ok.reshape(n * H)
    order = jnp.argsort(~ok, stable=True)
    return qs[order], jnp.sum(ok).astype(jnp.int32)


def round_context(params: ShirtParams, state: ShirtState, views: Views, okq, q_g,
                  hyps=None) -> RoundContext:
    """The shared inputs of steps 3–4; the temporal prior widened by Sigma_b for
    ``reacquire_frames`` frames after a loss (its ``q_h`` comes from a cold start)."""
    uvs = jax.vmap(lambda w: crop_uv(w, params.search.work_size))(views.windows)
    q_h = jnp.where(state.valid, state.q, q_g)
    cov = params.cov
    if params.rounds.reacquire_frames:
        fresh = state.tracked < params.rounds.reacquire_frames
        cov = eqx.tree_at(lambda c: c.prior, cov, _widened(cov.prior, cov.blend, fresh))
    rays = jax.vmap(lambda cam, uv: (camera_center(cam), pixel_rays(cam, uv)[1]))(params.cams, uvs)
    extra = {}
    if hyps is not None:
        extra = dict(hyps=hyps[0], n_hyps=hyps[1], lost=~state.valid)
    if params.rounds.skin_terms:
        # only after a valid frame: after a loss the starts are tens of cm off and the windows
        # around their prediction catch the wrong skin (docs/results/shirt_skin.md)
        extra["skin"] = skin_maps(params.color, params.skin, views.cls.W, views.crops, views.fgs,
                                  params.colours.shading) & state.valid
    if params.colours.patch_colours:
        return RoundContext(views, okq, q_g, q_h, cov, uvs, rays, state.look, state.look_W,
                            **extra)
    return RoundContext(views, okq, q_g, q_h, cov, uvs, rays, **extra)


def render_views(params: ShirtParams, ctx: RoundContext, q) -> Hits:
    """The model at ``q`` rendered on every camera's crop grid (patch, colour, 3D point), one
    ``vmap`` over the cameras; Hits stacked over cameras."""
    body, garment = params.render_body, params.garment
    return jax.vmap(lambda o, d, z: render_rays(body, garment, q, o, d, z))(
        *ctx.rays, params.cams.R[:, 2]
    )


def pose_assisted_centroids(
    params: ShirtParams, ctx: RoundContext, patch_maps, plain
) -> PatchCentroids:
    """§5.2 step 3 in every camera (one ``vmap``): one exact EDT per patch of the rendered
    ``patch_maps`` (n_cams, n, n), the pose-assisted classification (``C = 6/s'``, ``T = 5``;
    with ``plain`` the ablation's measurement: step-1 threshold, distance only a tie-break)
    and its patch centroids, stacked over cameras."""
    n, P, dt = params.search.work_size, params.garment.n_patches, ctx.q_g.dtype
    v = ctx.views
    patch_colour = params.garment.patch_colour

    def one(patch_map, W, crop, fg, s_found, window, look, W_look, learned):
        dist = patch_distance_maps(patch_map, P, dt)
        if learned is not None:  # the learned model (colours.observer)
            w = PRIOR_SCALE / s_found * (window[2] / n) * params.colours.observer_prior
            if params.ablations.pose_prior:
                w = jnp.where(plain, jnp.asarray(TIE_BREAK_WEIGHT, dt), w)
            else:
                w = jnp.asarray(TIE_BREAK_WEIGHT, dt)
            patch = learned_pose_assisted(learned, dist, w.astype(learned.patch.dtype), fg)
            return patch_centroids(patch, P, window, dtype=dt)
        if params.ablations.pose_prior:
            weight = PRIOR_SCALE / s_found * (window[2] / n)  # C = 6/s', d in image px
            weight = jnp.where(plain, jnp.asarray(TIE_BREAK_WEIGHT, dt), weight)
            thr = jnp.where(plain, jnp.asarray(THRESHOLD, dt), jnp.asarray(POSE_THRESHOLD, dt))
        else:
            weight, thr = TIE_BREAK_WEIGHT, THRESHOLD
        if look is None:
            pa = pose_assisted_classify(
                params.color, W, crop, dist, patch_colour, weight, fg, thr, params.colours.shading,
                params.colours.scene_colors,
            )  # fmt: skip
        else:  # every patch its own colour state: the "colours" are the patches
            pa = pose_assisted_classify(
                patch_model(params, look), jnp.eye(3, dtype=W_look.dtype),
                in_look_space(crop, W_look), dist, jnp.arange(1, P + 1), weight, fg, thr,
                params.colours.shading, params.colours.scene_colors,
            )  # fmt: skip
        return patch_centroids(pa.patch, P, window, dtype=dt)

    fg_ax = None if v.fgs is None else 0
    look, look_W = ctx.look, ctx.look_W
    l_ax = None if look is None else 0
    p_ax = None if v.learned is None else 0
    c = jax.vmap(one, in_axes=(0, 0, 0, fg_ax, 0, 0, l_ax, l_ax, p_ax))(
        patch_maps, v.cls.W, v.crops, v.fgs, v.s_found, v.windows, look, look_W, v.learned
    )
    return PatchCentroids(c.xy, c.count, c.valid & ctx.okq[:, None])


def ik_round(params: ShirtParams, ctx: RoundContext, q, hits: Hits, plain=False, prior=None):
    """One round of steps 3 + 4 with the model rendered at ``q`` (``hits``, stacked over
    cameras): measured centroids in every camera, then the full IK (per-view anchors from
    ``hits``). ``prior``: the blend the IK's database term pulls to (default the placed blend
    ``q_g``; an orientation hypothesis's own pose for its start), also the temporal prior
    after a loss (where that is the blend)."""
    if prior is not None:
        ctx = ctx._replace(q_g=prior, q_h=jnp.where(ctx.lost, prior, ctx.q_h))
    meas = pose_assisted_centroids(params, ctx, hits.patch, plain)
    c_obs, v_obs = meas.xy, meas.valid
    chain = params.body.chain
    if params.rounds.view_anchors:
        anchors = _view_anchors(chain, params.anchors, params.cams, q, hits.patch, hits.point,
                                ctx.uvs)  # fmt: skip
    else:
        anchors = params.anchors
    c_ik, v_ik, cov = c_obs, v_obs, ctx.cov
    if ctx.skin is not None:  # head and hands observed as skin (issue 38 item 1)
        sk = observe_skin(params.skin, chain, params.cams, q, hits.geom, hits.point, ctx.uvs,
                          ctx.views.windows, ctx.skin, ctx.okq)  # fmt: skip
        anchors = append_anchors(anchors, sk.anchors, params.n_cams)
        c_ik = jnp.concatenate([c_obs, sk.xy.astype(c_obs.dtype)], axis=1)
        v_ik = jnp.concatenate([v_obs, sk.valid], axis=1)
        cov = append_centroid_covariances(cov, params.garment.n_patches, params.skin.cov)
    sol = solve_ik(chain, params.cams, anchors, c_ik, v_ik, ctx.q_g, ctx.q_h, cov, q,
                   robust=params.rounds.robust)  # fmt: skip
    return sol.q, c_obs, v_obs


def agreement(params: ShirtParams, ctx: RoundContext, hits: Hits) -> Array:
    """Agreement of a render ``hits`` (stacked over cameras) with the step-1 classification:
    agreeing minus disagreeing pixels over the rendered shirt pixels of the cameras that found
    the shirt (shared by all starts, so comparable between them)."""
    dt = ctx.q_g.dtype
    c1, r = ctx.views.cls.ids, hits.colour
    ok = ctx.okq[:, None, None]
    both = (r > 0) & (c1 > 0) & ok
    score = jnp.sum(both & (r == c1)) - jnp.sum(both & (r != c1))
    shown = jnp.sum((r > 0) & ok)
    return score.astype(dt) / jnp.maximum(shown, 1).astype(dt)


def starts_of(params: ShirtParams, state: ShirtState, ctx: RoundContext):
    """The starts of the first round, ``(starts, plain, n)``: the placed blend and the previous
    pose (after a loss: the blend measured without the pose prior); on (re)acquisition frames
    and ``reacquire_frames`` after, a third: the last valid pose measured without the pose
    prior. ``n`` (2 or 3) is traced; without ``temporal_start`` the blend alone. With
    ``orientation_hypotheses``, after a loss the placed orientation hypotheses follow
    (:func:`orientation_starts`; ``n`` counts the real ones)."""
    q_g = ctx.q_g
    if not params.rounds.temporal_start:
        return q_g[None], jnp.zeros((1,), bool), jnp.asarray(1)
    reacquire = ~state.valid
    starts = [q_g, jnp.where(state.valid, state.q, q_g)]
    plain = [jnp.array(False), reacquire & params.rounds.reacquire_start]
    n = jnp.asarray(2)
    if params.rounds.held_start:
        starts.append(state.q)
        plain.append(jnp.array(True))
        fresh = reacquire | (state.tracked < params.rounds.reacquire_frames)
        n = n + fresh.astype(n.dtype)
    if state.q_own is not None:
        starts.append(state.q_own)
        plain.append(jnp.array(False))
        n = n + reacquire.astype(n.dtype)
    if ctx.hyps is not None:
        starts += list(ctx.hyps)
        plain += [jnp.array(False)] * ctx.hyps.shape[0]
        n = n + jnp.where(reacquire, ctx.n_hyps, 0).astype(n.dtype)
    return jnp.stack(starts), jnp.stack(plain), n


def rounds(params: ShirtParams, state: ShirtState, ctx: RoundContext, n_more):
    """Steps 3–4 of the frame: the first round from every start (:func:`starts_of`), the
    best-agreeing result kept (the first of equals), then ``n_more`` (traced) more rounds from
    it, each with the model re-rendered at the last pose. Returns ``(q, c_obs, v_obs, hits,
    agreement)``: the last round's pose and centroids, the render of the pose, and the
    agreement of the kept start's first round.

    One loop of ``2 n + n_more`` iterations, each one render and at most one IK round (under
    ``lax.cond``, which runs one branch on CPU): iteration ``2s`` renders start ``s`` and runs
    its round, ``2s + 1`` renders the result and scores it; after the last start's score and
    after each extra render the next round runs from the kept result. XLA compiles one render
    and one round for the whole frame where a loop per phase compiled three renders and two
    rounds (its cold and steady times: docs/results/realtime_profile_history.json)."""
    starts, plain, n = starts_of(params, state, ctx)
    hyp = ctx.hyps is not None  # each start's IK pulls to its own hypothesis
    if hyp:  # the IK prior of each start: its own pose for a hypothesis, else the blend
        is_hyp = jnp.arange(starts.shape[0]) >= starts.shape[0] - ctx.hyps.shape[0]
        priors = jnp.where(is_hyp[:, None], starts, ctx.q_g[None])
    total = 2 * n + n_more
    dt = ctx.q_g.dtype
    P = params.garment.n_patches
    hits0 = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                         jax.eval_shape(lambda: render_views(params, ctx, ctx.q_g)))  # fmt: skip
    c0 = jnp.zeros((params.n_cams, P, 2), dt)
    v0 = jnp.zeros((params.n_cams, P), bool)
    pick = lambda b, x, y: jax.tree.map(lambda u, w: jnp.where(b, u, w), x, y)  # noqa: E731

    def body(k, carry):
        pose, ik_out, best, prior_best = carry
        hits = render_views(params, ctx, pose)
        s = jnp.minimum(k // 2, starts.shape[0] - 1)
        in_starts = k < 2 * n
        is_start = in_starts & (k % 2 == 0)
        is_check = in_starts & (k % 2 == 1)
        score = agreement(params, ctx, hits)
        # a start's first round scored: kept if it agrees better than every earlier start
        kept = is_check & (score > best[-1])
        best = pick(kept, (*ik_out, hits, score), best)
        if hyp:  # the kept start's prior follows it into the extra rounds
            prior_best = jnp.where(kept, priors[s], prior_best)
        # an extra round's render: that round's result is the frame's (agreement kept)
        best = pick(~in_starts, (*ik_out, hits, best[-1]), best)
        last_check = is_check & (s == n - 1)
        more = k + 1 < total
        do_ik = is_start | ((last_check | ~in_starts) & more)
        q_src = jnp.where(is_start, pose, best[0])
        hits_src = pick(is_start, hits, best[3])
        plain_k = is_start & plain[s]
        prior_k = jnp.where(is_start, priors[s], prior_best) if hyp else None
        ik_out = jax.lax.cond(
            do_ik,
            lambda: ik_round(params, ctx, q_src, hits_src, plain_k, prior_k),
            lambda: ik_out,
        )
        nxt = starts[jnp.minimum(s + 1, starts.shape[0] - 1)]
        pose = jnp.where(is_check & ~last_check, nxt, ik_out[0])
        return pose, ik_out, best, prior_best

    init = (starts[0], (ctx.q_g, c0, v0), (ctx.q_g, c0, v0, hits0, jnp.asarray(-jnp.inf, dt)),
            ctx.q_g if hyp else None)
    _, _, best, _ = jax.lax.fori_loop(0, total, body, init)
    return best


def frame_validity(params: ShirtParams, ctx: RoundContext, v_obs, agreement) -> Array:
    """Found in some camera, ``min_patches`` centroids measured, and (when step 1
    classified ``gate_min_fraction`` of some crop: after a sudden lighting change it
    classifies almost nothing until W is re-fitted; with ``patch_colours`` always) the
    agreement gate passed."""
    rule = params.validity
    valid = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= rule.min_patches)
    frac = jnp.max(ctx.views.cls.fraction * ctx.okq)
    seen = frac >= rule.gate_min_fraction
    if params.colours.patch_colours:  # the light is followed by the colour states, not by a W refit
        seen = jnp.array(True)  # that needs the frame valid: the gate always applies
    return valid & ((agreement >= rule.min_agreement) | ~seen)


def reported_validity(
    params: ShirtParams, ctx: RoundContext, v_obs, signals: FrameSignals, valid, own
) -> Array:
    """The ``valid`` flag reported for the frame: ``valid`` (the tracker's own, which also
    decides what the state keeps) unless ``make_params`` set a reporting rule: then
    ``report_patches`` centroids measured and, in every camera that found the shirt, the
    final pose's centroid residual at most ``max_residual`` and its recall at least
    ``min_recall`` (:class:`FrameSignals`; calibrated on ground truth, issue 17), and the
    output pose is this frame's own solution (``own``: the signals describe it; a held pose,
    ``hold_invalid``, is never reported valid by them)."""
    rule = params.validity
    if not rule.report:
        return valid
    ok = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= rule.report_patches)
    if rule.check_residual:
        ok = ok & jnp.all((signals.residual <= rule.max_residual) | ~ctx.okq)
    if rule.check_recall:
        ok = ok & jnp.all((signals.recall >= rule.min_recall) | ~ctx.okq)
    return ok & own


def frame_signals(
    params: ShirtParams, state: ShirtState, ctx: RoundContext, db: DatabasePose, q, c_obs,
    v_obs, hits,
) -> FrameSignals:
    """:class:`FrameSignals` of the final pose ``q`` (``hits`` its render on the crops,
    ``c_obs`` / ``v_obs`` the last round's measured centroids)."""
    P, dt = params.garment.n_patches, q.dtype

    def one(patch_map, window, c_obs_i, v_obs_i, c1, r):
        model = patch_centroids(patch_map, P, window, dtype=dt)
        use = v_obs_i & model.valid
        d = jnp.linalg.norm(c_obs_i - model.xy, axis=-1)
        mean_d = jnp.sum(jnp.where(use, d, 0.0)) / jnp.maximum(jnp.sum(use), 1)
        same = jnp.sum((c1 > 0) & (r == c1)).astype(dt)
        return (mean_d / window[2], same / jnp.maximum(jnp.sum(c1 > 0), 1),
                same / jnp.maximum(jnp.sum(r > 0), 1))  # fmt: skip

    res, cov, rec = jax.vmap(one)(hits.patch, ctx.views.windows, c_obs, v_obs,
                                  ctx.views.cls.ids, hits.colour)  # fmt: skip
    rms = lambda a: jnp.sqrt(jnp.mean(jnp.square(a)))  # noqa: E731
    spread = rms(db.q_dbs[0][6:] - db.q_dbs[1][6:]) if params.n_cams > 1 else jnp.zeros((), dt)
    jump = jnp.where(state.valid, jnp.linalg.norm(q[:3] - state.q[:3]), 0.0)
    return FrameSignals(res, cov, rec,
                        rms(q[6:] - ctx.q_g[6:]), spread.astype(dt), jump.astype(dt))


def near_placement(ctx: RoundContext, q) -> Array:
    """Whether ``q`` is finite and its root within ``MAX_ROOT_OFFSET`` of the placed blend's
    (step 2's root, from where and how large the shirt appears in the crops): an IK that ran
    off (too few or wrong centroids) lands metres away."""
    off = jnp.linalg.norm(q[:3] - ctx.q_g[:3])
    return jnp.all(jnp.isfinite(q)) & (off < MAX_ROOT_OFFSET)


def white_balance_refit(params: ShirtParams, state: ShirtState, ctx: RoundContext, hits, valid):
    """§5.2 step 5: ``W*`` per camera refitted on ``r*`` (the final pose's render, eroded by
    one pixel), joining the reference illuminations when new. Returns ``(W, refs, added)``
    stacked over cameras."""
    v = ctx.views
    if not params.ablations.adaptive_white_balance or params.colours.observer is not None:
        return state.W, state.refs, jnp.zeros(params.n_cams, bool)

    def one(refs_i, colour, crop, W_i, fg, ok_cam):
        r_star = erode_ids(colour)  # q* rendered in the crop (unused if not valid)
        W_star = white_balance_from_ids(
            params.color, crop, r_star, W_i, fg, min_pixels=REFERENCE_PIXELS
        )
        # a camera's gain on each channel is positive: a W* with a non-positive diagonal (the
        # linear fit after a lamp goes off gave e.g. -1.93, issue 49) explains the crop by
        # inverting a channel, and is not adopted
        ok = valid & ok_cam & jnp.all(jnp.isfinite(W_star)) & jnp.all(jnp.diagonal(W_star) > 0)
        W_star = jnp.where(ok, W_star, W_i)
        refs_i2, add = maybe_add_reference(refs_i, W_star)
        refs_i = jax.tree.map(lambda a, b: jnp.where(ok, a, b), refs_i2, refs_i)
        return W_star, refs_i, add & ok

    fg_ax = None if v.fgs is None else 0
    return jax.vmap(one, in_axes=(0, 0, 0, 0, fg_ax, 0))(
        state.refs, hits.colour, v.crops, v.cls.W, v.fgs, ctx.okq
    )


def _step(params: ShirtParams, state: ShirtState, frames, masks) -> tuple[ShirtState, ShirtOutput]:
    dt = state.q.dtype
    views = locate_and_classify(params, state, frames, masks)
    db = database_pose(params, views, dt)
    q_g = global_placement(params, db, dt)
    hyps = None
    if params.rounds.orientation_hypotheses:  # computed only after a loss (they start then)
        H = params.rounds.orientation_hypotheses * params.n_cams
        hyps = jax.lax.cond(
            state.valid,
            lambda: (jnp.broadcast_to(q_g, (H, q_g.shape[0])), jnp.asarray(0, jnp.int32)),
            lambda: orientation_starts(params, views, db, dt))
    ctx = round_context(params, state, views, db.okq, q_g, hyps)
    # ik_passes - 1 more rounds, and reacquire_passes more after a loss
    n_more = params.rounds.ik_passes - 1 + jnp.where(state.valid, 0, params.rounds.reacquire_passes)
    q_sol, c_obs, v_obs, hits, agree = rounds(params, state, ctx, n_more)
    valid = frame_validity(params, ctx, v_obs, agree)
    q_star = jnp.where(valid, q_sol, state.q)
    tracked = jnp.where(valid, state.tracked + 1, 0).astype(jnp.int32)
    signals = frame_signals(params, state, ctx, db, q_sol, c_obs, v_obs, hits)
    colour_out = {}
    if params.colours.patch_colours:
        learn = valid & (signals.residual <= params.colours.learn_max_residual) & (
            signals.recall >= params.colours.learn_min_recall)
        held = hits.patch
        if params.colours.follow_light:  # the held pose rendered only on an invalid frame
            held = jax.lax.cond(valid, lambda: hits.patch,
                                lambda: render_views(params, ctx, state.q).patch)  # fmt: skip
        look, n_upd, r_ok, r_rms = colour_update(params, state, views, db.okq, hits.patch,
                                                 held, valid, learn)
        W_new, refs, added = state.W, state.refs, jnp.zeros(params.n_cams, bool)
        colour_out = dict(colour_updated=n_upd, relight_ok=r_ok, relight_rms=r_rms)
        new_state = ShirtState(W=W_new, refs=refs, q=q_star, valid=valid, tracked=tracked,
                               look=look, look_W=state.look_W)  # fmt: skip
    else:
        W_new, refs, added = white_balance_refit(params, state, ctx, hits, valid)
        new_state = ShirtState(W=W_new, refs=refs, q=q_star, valid=valid, tracked=tracked)
    # this frame's estimate where there was something to fit (else it is unconstrained)
    measured = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= MIN_VALID_PATCHES)
    q_frame = jnp.where((measured | valid) & jnp.all(jnp.isfinite(q_sol)), q_sol, jnp.nan)
    has_own = measured & near_placement(ctx, q_sol)
    if params.validity.hold_invalid:
        q_out, own = q_star, valid
    else:
        own = has_own
        q_out = jnp.where(own, q_sol, state.q)
    if state.q_own is not None:  # the frame's own estimate where it had one, valid or not
        new_state = dataclasses.replace(new_state, q_own=jnp.where(has_own, q_sol, state.q_own))
    out = ShirtOutput(
        q=q_out,
        q_frame=q_frame.astype(dt),
        q_blend=q_g,
        valid=reported_validity(params, ctx, v_obs, signals, valid, own),
        window=views.windows,
        fraction=views.cls.fraction,
        used_reference=views.cls.used_reference,
        added_reference=added,
        centroids=c_obs,
        visible=v_obs,
        agreement=agree,
        signals=signals,
        **colour_out,
    )
    return new_state, out


@eqx.filter_jit
def model_centroids(
    params: ShirtParams, q: Float[Array, " n_dof"], windows: Float[Array, "n_cams 4"]
) -> PatchCentroids:
    """The model's patch centroids at pose ``q`` as the tracker sees them: ``q`` rendered on
    each camera's ``params.search.work_size`` crop grid of ``windows`` (e.g.
    ``ShirtOutput.window``), centroids in image pixels, batched over cameras. With ``q`` the
    ground truth these are what per-view anchors predict there, the model term of covariance
    training
    (:func:`jaxmocap.ik.estimate_covariances` ``predicted=``)."""
    n, P = params.search.work_size, params.garment.n_patches

    def one(cam, win):
        ids = render_uv(params.render_body, params.garment, q, cam, crop_uv(win, n)).patch
        return patch_centroids(ids, P, win, dtype=q.dtype)

    return jax.vmap(one)(params.cams, windows.astype(q.dtype))
