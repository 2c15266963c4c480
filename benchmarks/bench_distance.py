"""Exact EDT: jaxmocap.distance vs cv2.distanceTransform (DIST_L2, DIST_MASK_PRECISE) and SciPy.

20 masks of 40x40 (the pose database's tiny id maps) and of 160x160 (blobs plus scattered
pixels: every mask spans the image), float32 (the user default); and the masks the colour-shirt
tracker transforms: the 20 patch masks of the bundled body's shirt rendered in each camera's
128x128 working crop (two 640x480 cameras, several poses), one call per camera as in
``color.pose_assisted.patch_distance_maps``. Also session 8's transform (the row pass in
float32; cv2, the library and it interleaved in rounds), the library's previous formulation
(row pass over all w candidate columns, column pass by associative scans) and a naive JAX
formulation (one broadcast min over all candidates per 1D pass).
Run: python -m benchmarks.bench_distance
"""

import functools
import os

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap.distance import _column_distance_sq, _edt_sq_float, edt, id_map_distances


def _previous_edt_sq(masks):
    """The library before issue 21's session 8: column pass by associative scans on the
    transposed stack, row pass brute force over all w columns (blocks of 4)."""
    _, h, w = masks.shape
    bound = h + w
    mt = jnp.swapaxes(masks, 1, 2)
    i = jnp.arange(h, dtype=jnp.int32).reshape(1, 1, h)
    above = jax.lax.associative_scan(jnp.maximum, jnp.where(mt, i, -2 * bound), axis=2)
    below = jax.lax.associative_scan(jnp.minimum, jnp.where(mt, i, 3 * bound), axis=2, reverse=True)
    g = jnp.minimum(jnp.minimum(i - above, below - i), bound).astype(jnp.float32)
    big = jnp.float32(jnp.finfo(jnp.float32).max / 4)
    fp = jnp.pad(jnp.swapaxes(g * g, 1, 2), ((0, 0), (0, 0), (0, -w % 4)), constant_values=big)
    j = jnp.arange(w, dtype=jnp.float32)

    def body(b, out):
        block = jax.lax.dynamic_slice_in_dim(fp, b * 4, 4, axis=-1)
        k0 = (b * 4).astype(jnp.float32)
        for q in range(4):
            out = jnp.minimum(out, block[..., q : q + 1] + jnp.square(j - (k0 + q)))
        return out

    d2 = jax.lax.fori_loop(0, fp.shape[-1] // 4, body, jnp.full(masks.shape, big))
    return jnp.minimum(d2, jnp.float32(bound**2))


_previous_edt = jax.jit(lambda m: jnp.sqrt(_previous_edt_sq(m)))
# session 8's transform: the same column pass and span window, the row pass in float32 (the
# library now runs it in uint16 where the squared distances fit, same integers)
_float_edt = jax.jit(lambda m: jnp.sqrt(_edt_sq_float(m)))


def _naive_1d(f):  # out_j = min_k f_k + (j - k)^2 along the last axis, one broadcast reduce
    k = jnp.arange(f.shape[-1], dtype=f.dtype)
    return jnp.min(f[..., :, None] + jnp.square(k[None, :] - k[:, None]), axis=-2)


@jax.jit
def _naive_edt(masks):
    _, h, w = masks.shape
    big = jnp.float32((h + w) ** 2)
    g = jnp.swapaxes(_naive_1d(jnp.where(jnp.swapaxes(masks, 1, 2), 0.0, big)), 1, 2)
    return jnp.sqrt(jnp.minimum(_naive_1d(jnp.minimum(g, big)), big))


# ----------------------------------------------------------------------------- alternatives
# Exact formulations measured against the library's blocked brute force (issue 21: the JAX EDT
# against cv2.distanceTransform); each checked against OpenCV in the run.


def _meijster_rows(f2):
    """Meijster / Felzenszwalb-Huttenlocher lower envelope, vectorised across all rows
    (lax.scan along the row, a while loop for the pops; int32, exact): O(w) per row."""
    R, w = f2.shape
    r = jnp.arange(R)
    ft = f2.T

    def fwd(carry, u):
        s, t, q = carry
        fu = ft[u]

        def pops(c):
            s, t, q = c
            qq = jnp.maximum(q, 0)
            sq, tq = s[r, qq], t[r, qq]
            return (q >= 0) & (((tq - sq) ** 2 + f2[r, sq]) > ((tq - u) ** 2 + fu))

        s, t, q = jax.lax.while_loop(
            lambda c: jnp.any(pops(c)), lambda c: (c[0], c[1], c[2] - pops(c)), (s, t, q)
        )
        empty = q < 0
        sq = s[r, jnp.maximum(q, 0)]
        wv = 1 + (u * u - sq * sq + fu - f2[r, sq]) // (2 * (u - sq))
        push = ~empty & (wv < w)
        qn = jnp.where(empty, 0, jnp.where(push, q + 1, q))
        s = s.at[r, qn].set(jnp.where(empty | push, u, s[r, qn]))
        t = t.at[r, qn].set(jnp.where(empty, 0, jnp.where(push, wv, t[r, qn])))
        return (s, t, qn), None

    z = jnp.zeros((R, w), jnp.int32)
    (s, t, q), _ = jax.lax.scan(fwd, (z, z, jnp.zeros(R, jnp.int32)), jnp.arange(1, w))

    def bwd(q, u):
        sq = s[r, q]
        return q - (u == t[r, q]), (u - sq) ** 2 + f2[r, sq]

    _, d = jax.lax.scan(bwd, q, jnp.arange(w - 1, -1, -1))
    return d[::-1].T


def _column_g2_int(masks):
    _, h, w = masks.shape
    bound = h + w
    i = jnp.arange(h, dtype=jnp.int32).reshape(1, h, 1)
    above = jax.lax.associative_scan(jnp.maximum, jnp.where(masks, i, -2 * bound), axis=1)
    below = jax.lax.associative_scan(
        jnp.minimum, jnp.where(masks, i, 3 * bound), axis=1, reverse=True
    )
    g = jnp.minimum(jnp.minimum(i - above, below - i), bound)
    return g * g


@jax.jit
def _meijster_edt(masks):
    n, h, w = masks.shape
    d2 = _meijster_rows(_column_g2_int(masks).reshape(-1, w)).reshape(n, h, w)
    return jnp.sqrt(jnp.minimum(d2, (h + w) ** 2).astype(jnp.float32))


@jax.jit
def _reduce_edt(masks):  # row pass as one (rows, w, w) broadcast + min reduction
    _, h, w = masks.shape
    g2 = _column_g2_int(masks).astype(jnp.float32)
    ll = jnp.arange(w, dtype=jnp.float32)
    d2 = jnp.min(g2[..., None, :] + jnp.square(ll[:, None] - ll[None, :]), axis=-1)
    return jnp.sqrt(jnp.minimum(d2, jnp.float32((h + w) ** 2)))


_OFFSET_BLOCK = 8  # offsets per loop iteration (4 and 16 measured: no better)


def _offsets_loop(rows, bound, k0=1, out0=None):
    """Row pass over the offsets k = |j - l| grown outward: out = min(out, g2[j -+ k] + k^2),
    stopping once k^2 >= the largest current best of the rows of non-empty masks (no later
    candidate can lower any pixel; exact) or k = w. ``rows`` (r, w) float32 g^2."""
    w = rows.shape[-1]
    big = jnp.float32(bound)
    gp = jnp.pad(rows, ((0, 0), (w, w)), constant_values=big)
    live = jnp.any(rows < big, axis=1)
    out0 = rows if out0 is None else out0

    def top(out):
        return jnp.max(jnp.where(live[:, None], out, 0.0))

    def body(c):
        k, out, _ = c
        for q in range(_OFFSET_BLOCK):
            kk = k + q
            near = jnp.minimum(jax.lax.dynamic_slice_in_dim(gp, w - kk, w, axis=1),
                               jax.lax.dynamic_slice_in_dim(gp, w + kk, w, axis=1))
            out = jnp.minimum(out, near + (kk * kk).astype(jnp.float32))
        return k + _OFFSET_BLOCK, out, top(out)

    def cond(c):
        return (c[0] < w) & (c[0].astype(jnp.float32) ** 2 < c[2])

    return jax.lax.while_loop(cond, body, (jnp.int32(k0), out0, top(out0)))[1]


@jax.jit
def _offsets_edt(masks):
    """Column pass of the library, row pass by offsets grown outward with one early stop for
    the whole stack (the largest distance of the stack decides)."""
    n, h, w = masks.shape
    bound = float((h + w) ** 2)
    g2 = _column_distance_sq(masks).reshape(n * h, w)
    d2 = _offsets_loop(g2, bound).reshape(n, h, w)
    return jnp.sqrt(jnp.minimum(d2, bound))


@functools.partial(jax.jit, static_argnames=("chunks", "first"))
def _offsets_sorted_edt(masks, chunks=8, first=4):
    """As :func:`_offsets_edt`, but every row's own bound decides: ``first`` offsets on all
    rows, then the rows sorted by their largest current best and cut into ``chunks`` groups,
    each group's loop stopping at its own largest best (exact)."""
    n, h, w = masks.shape
    bound = float((h + w) ** 2)
    rows = _column_distance_sq(masks).reshape(n * h, w)
    r = rows.shape[0]
    gp = jnp.pad(rows, ((0, 0), (w, w)), constant_values=jnp.float32(bound))
    out = rows
    for k in range(1, first + 1):
        near = jnp.minimum(gp[:, w - k : 2 * w - k], gp[:, w + k : 2 * w + k])
        out = jnp.minimum(out, near + jnp.float32(k * k))
    order = jnp.argsort(jnp.max(out, axis=1))
    per = -(-r // chunks)
    pad = ((0, per * chunks - r), (0, 0))
    sr = jnp.pad(rows[order], pad, constant_values=bound).reshape(chunks, per, w)
    so = jnp.pad(out[order], pad, constant_values=bound).reshape(chunks, per, w)
    done = jnp.concatenate([_offsets_loop(sr[c], bound, first + 1, so[c]) for c in range(chunks)])
    d2 = done[:r][jnp.argsort(order)].reshape(n, h, w)
    return jnp.sqrt(jnp.minimum(d2, bound))


def _alternatives(masks: np.ndarray, ref: np.ndarray, kernel: str, cv_ms: float) -> list[Row]:
    mj = jnp.asarray(masks)
    rows = []
    for label, fn, n in (
        ("alternative: lower envelope (Meijster), vectorised over rows, lax.scan", _meijster_edt,
         20),
        ("alternative: row pass as one broadcast + min reduction", _reduce_edt, 20),
        ("alternative: row pass over offsets |j - l| = k grown outward, exact early stop "
         "(k^2 >= the stack's largest current best)", _offsets_edt, 50),
        ("alternative: the same, rows sorted by their best after 4 offsets, 8 groups with "
         "their own early stop", _offsets_sorted_edt, 50),
    ):  # fmt: skip
        comp = time_compile(lambda fn=fn: fn(mj))
        err = float(np.abs(np.asarray(fn(mj)) - ref).max())
        med, mn = time_call(lambda fn=fn: fn(mj), n=n)
        note = f"max abs err vs cv2 {err:.1e} px; cv2/this {cv_ms / med:.2f}x"
        rows.append(Row(kernel, label, med, mn, n, comp, note))
    return rows


def _bench_size(rng: np.random.Generator, side: int, n: int = 20) -> tuple[list[Row], str]:
    # blob-like masks (a patch of a rendered id map) plus a few scattered pixels
    yy, xx = np.mgrid[:side, :side]
    masks = np.stack(
        [
            (
                (yy - rng.uniform(0, side)) ** 2 + (xx - rng.uniform(0, side)) ** 2
                < (side * rng.uniform(0.05, 0.2)) ** 2
            )
            | (rng.random((side, side)) < 0.002)
            for _ in range(n)
        ]
    )
    src = [(~m).astype(np.uint8) for m in masks]  # OpenCV: distance to the nearest zero
    kernel = f"EDT {n}x{side}x{side}"
    mj = jnp.asarray(masks)
    comp = time_compile(lambda: edt(mj))
    ref = np.stack([cv2.distanceTransform(s, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for s in src])
    err = float(np.abs(np.asarray(edt(mj)) - ref).max())
    sp_ms, sp_min = time_call(lambda: [ndimage.distance_transform_edt(s) for s in src], n=20)
    fl_comp = time_compile(lambda: _float_edt(mj))
    assert np.array_equal(np.asarray(_float_edt(mj)), np.asarray(edt(mj)))
    (cv_ms, cv_min), (jx_ms, jx_min), (fl_ms, fl_min) = _interleaved(
        [lambda: [cv2.distanceTransform(s, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for s in src],
         lambda: edt(mj), lambda: _float_edt(mj)]
    )  # fmt: skip
    pv_comp = time_compile(lambda: _previous_edt(mj))
    pv_ms, pv_min = time_call(lambda: _previous_edt(mj))
    nv_comp = time_compile(lambda: _naive_edt(mj))
    n_naive = 10 if side > 100 else 50
    nv_ms, nv_min = time_call(lambda: _naive_edt(mj), n=n_naive)
    rows = [
        Row(kernel, "cv2.distanceTransform PRECISE (loop)", cv_ms, cv_min, 30),
        Row(kernel, "scipy.ndimage.distance_transform_edt (loop)", sp_ms, sp_min, 20),
        Row(
            kernel,
            "jaxmocap.distance.edt (jit, column-span row pass; uint16 from 64 columns)",
            jx_ms,
            jx_min,
            30,
            comp,
            f"max abs err vs cv2 {err:.1e} px",
        ),
        Row(kernel, "session 8 jaxmocap.distance.edt (float32 row pass)", fl_ms, fl_min, 30,
            fl_comp, f"this/session 8 {jx_ms / fl_ms:.2f}; cv2, this and session 8 interleaved "
            "(median of 6 rounds' medians)"),
        Row(kernel, "previous jaxmocap.distance.edt (all w columns, associative scans)",
            pv_ms, pv_min, 50, pv_comp, f"this/previous {jx_ms / pv_ms:.2f}"),
        Row(kernel, "naive JAX (jit, broadcast min)", nv_ms, nv_min, n_naive, nv_comp),
    ]  # fmt: skip
    if side > 100:
        rows += _alternatives(masks, ref, kernel, cv_ms)
    summary = (
        f"{kernel}: jaxmocap {jx_ms:.3f} ms vs cv2 {cv_ms:.3f} ms "
        f"(cv2/jax = {cv_ms / jx_ms:.2f}x), vs SciPy {sp_ms:.3f} ms "
        f"(scipy/jax = {sp_ms / jx_ms:.2f}x), session 8 (float32 row pass) {fl_ms:.3f} ms, "
        f"previous library {pv_ms:.3f} ms, "
        f"naive JAX {nv_ms:.2f} ms"
    )
    return rows, summary


def _interleaved(fns, n: int = 5, rounds: int = 6) -> list[tuple[float, float]]:
    """Median and min ms of each of ``fns`` over ``rounds`` rounds of ``n`` calls each, the
    functions taking turns round by round."""
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(rounds):
        for k, fn in enumerate(fns):
            med, mn = time_call(fn, n=n, warmup=1)
            times[k] += [med, mn]
    return [(float(np.median(t[0::2])), float(np.min(t[1::2]))) for t in times]


def _patch_masks(n_poses: int, seed: int = 1) -> np.ndarray:
    """The colour-shirt tracker's EDT input: per pose and camera, the 20 patch masks of the
    bundled body's shirt rendered on the 128x128 working crop (a square of side ``CROP_FACTOR``
    x s centred on the shirt's pixels, s = the side of a square of the shirt's area, as the
    search's region is placed; the shirt covers ~15% of the crop), two 640x480 cameras of
    ``bench_shirt``. Shape (n_poses * 2, P, 128, 128)."""
    from benchmarks.bench_shirt import _cameras
    from jaxmocap.body import default_body
    from jaxmocap.garment import default_garment
    from jaxmocap.render import render_ids, render_uv
    from jaxmocap.sampling import crop_uv, crop_window
    from jaxmocap.trackers.shirt import CROP_FACTOR, WORK_SIZE

    model = default_body()
    garment = default_garment(model)
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(model.chain.lower)[6:], np.asarray(model.chain.upper)[6:]
    ids = np.arange(1, garment.n_patches + 1)[:, None, None]
    full = jax.jit(lambda q, cam: render_ids(model, garment, q, cam).patch)
    crop = jax.jit(lambda q, cam, win: render_uv(model, garment, q, cam, crop_uv(win, WORK_SIZE)))
    out = []
    for _ in range(n_poses):
        q = np.zeros(model.n_dof, np.float32)
        q[2] = 0.85
        q[6:] = np.clip(rng.uniform(-0.6, 0.6, model.n_dof - 6), lo, hi)
        for cam in _cameras(640, 480):
            ys, xs = np.nonzero(np.asarray(full(jnp.asarray(q), cam)) > 0)
            side = np.sqrt(xs.size)
            win = crop_window(jnp.float32(xs.mean()), jnp.float32(ys.mean()), jnp.float32(side),
                              CROP_FACTOR)  # fmt: skip
            out.append(np.asarray(crop(jnp.asarray(q), cam, win).patch)[None] == ids)
    return np.stack(out)


def _bench_patches(n_poses: int) -> tuple[list[Row], str]:
    masks = _patch_masks(n_poses)  # (n_poses * 2, P, n, n): one call per camera
    n_calls, P, n = masks.shape[0], masks.shape[1], masks.shape[-1]
    present = masks.any((2, 3))
    occupied = masks.any(2)  # (calls, P, n): columns holding a patch pixel
    first, last = occupied.argmax(-1), n - 1 - occupied[..., ::-1].argmax(-1)
    spans = np.where(present, last - first + 1, 0)  # column span per patch (0: absent)
    src = [[(~m).astype(np.uint8) for m in cam] for cam in masks]
    kernel = f"EDT {P}x{n}x{n} patch masks per camera, rendered shirt (per frame pair)"
    mj = [jnp.asarray(m) for m in masks]
    pairs = n_calls / 2

    def cv():
        return [
            cv2.distanceTransform(s, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for c in src for s in c
        ]

    ref = np.stack(cv()).reshape(masks.shape)
    comp = time_compile(lambda: edt(mj[0]))
    got = np.stack([np.asarray(edt(m)) for m in mj])
    err = float(np.abs(got - ref)[present].max())  # OpenCV's value for an absent patch differs
    assert np.all(got[~present] == 2 * n)
    pv_comp = time_compile(lambda: _previous_edt(mj[0]))
    # the three interleaved in rounds (a shared machine's load changes within a run)
    time_compile(lambda: _float_edt(mj[0]))
    assert all(np.array_equal(np.asarray(_float_edt(m)), np.asarray(edt(m))) for m in mj)
    (cv_ms, cv_min), (jx_ms, jx_min), (pv_ms, pv_min), (fl_ms, fl_min) = _interleaved(
        [cv, lambda: [edt(m) for m in mj], lambda: [_previous_edt(m) for m in mj],
         lambda: [_float_edt(m) for m in mj]]
    )  # fmt: skip
    note = (
        f"{n_poses} poses x 2 cameras; column span of a present patch median "
        f"{np.median(spans[present]):.0f}, widest per call median "
        f"{np.median(spans.max(1)):.0f}, max {spans.max()} of {n}"
    )
    rows = [
        Row(kernel, "cv2.distanceTransform PRECISE (loop)", cv_ms / pairs, cv_min / pairs, 30,
            None, note + "; median of 6 interleaved rounds' medians"),
        Row(kernel, "jaxmocap.distance.edt (jit, column-span row pass in uint16), one call per "
            "camera",
            jx_ms / pairs, jx_min / pairs, 30, comp,
            f"max abs err vs cv2 {err:.1e} px (present patches); cv2/this {cv_ms / jx_ms:.2f}x"),
        Row(kernel, "session 8 jaxmocap.distance.edt (float32 row pass)", fl_ms / pairs,
            fl_min / pairs, 30, None, f"this/session 8 {jx_ms / fl_ms:.2f}"),
        Row(kernel, "previous jaxmocap.distance.edt (all w columns, associative scans)",
            pv_ms / pairs, pv_min / pairs, 30, pv_comp, f"this/previous {jx_ms / pv_ms:.2f}"),
    ]  # fmt: skip
    summary = (
        f"{kernel}: jaxmocap {jx_ms / pairs:.3f} ms vs cv2 {cv_ms / pairs:.3f} ms "
        f"(cv2/jax = {cv_ms / jx_ms:.2f}x), session 8 (float32 row pass) {fl_ms / pairs:.3f} ms, "
        f"previous library {pv_ms / pairs:.3f} ms "
        f"(previous/now = {pv_ms / jx_ms:.2f}x); {note}"
    )
    return rows, summary


def main() -> None:
    rng = np.random.default_rng(0)
    load0 = os.getloadavg()[0]
    rows, summary = [], []
    for side in sized(full=(40, 160), quick=(40,)):
        r, s = _bench_size(rng, side)
        rows += r
        summary.append(s)
    r, s = _bench_patches(sized(full=6, quick=1))
    rows += r
    summary.append(s)

    # Wang §5.2 step 3: d_xy(r^b, k) for every id of a 40x40 tiny id map (16 ids)
    n_ids = 16
    ids = rng.integers(0, n_ids, size=(8, 5)).repeat(5, 0).repeat(8, 1)  # 40x40 blocky map
    ids_u8 = ids.astype(np.uint8)
    idj = jnp.asarray(ids, jnp.int32)
    f = jax.jit(id_map_distances, static_argnums=1)
    comp = time_compile(lambda: f(idj, n_ids))
    jx_ms, jx_min = time_call(lambda: f(idj, n_ids))
    cv_ms, cv_min = time_call(
        lambda: [
            cv2.distanceTransform(
                (ids_u8 != k).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )
            for k in range(n_ids)
        ]
    )
    kernel = f"id_map_distances 40x40, {n_ids} ids"
    rows += [
        Row(kernel, "cv2 per id (compare + distanceTransform)", cv_ms, cv_min, 50),
        Row(kernel, "jaxmocap.distance.id_map_distances (jit)", jx_ms, jx_min, 50, comp),
    ]
    summary.append(
        f"{kernel}: jaxmocap {jx_ms:.3f} ms vs cv2 {cv_ms:.3f} ms (cv2/jax = {cv_ms / jx_ms:.2f}x)"
    )
    summary.append(
        f"Load average (1 min) at the start {load0:.2f}, at the end {os.getloadavg()[0]:.2f} "
        "(2 cores)."
    )
    path = write_results("bench_distance", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
