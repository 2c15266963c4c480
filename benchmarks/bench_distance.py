"""Exact EDT: jaxmocap.distance vs cv2.distanceTransform (DIST_L2, DIST_MASK_PRECISE) and SciPy.

20 masks of 40x40 (the pose database's tiny id maps) and of 160x160 (a shirt crop), float32
(the user default). Also a naive JAX formulation (one broadcast min over all candidates per
1D pass), which motivated the blocked fori_loop form of the library.
Run: python benchmarks/bench_distance.py
"""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap.distance import edt, id_map_distances


def _naive_1d(f):  # out_j = min_k f_k + (j - k)^2 along the last axis, one broadcast reduce
    k = jnp.arange(f.shape[-1], dtype=f.dtype)
    return jnp.min(f[..., :, None] + jnp.square(k[None, :] - k[:, None]), axis=-2)


@jax.jit
def _naive_edt(masks):
    _, h, w = masks.shape
    big = jnp.float32((h + w) ** 2)
    g = jnp.swapaxes(_naive_1d(jnp.where(jnp.swapaxes(masks, 1, 2), 0.0, big)), 1, 2)
    return jnp.sqrt(jnp.minimum(_naive_1d(jnp.minimum(g, big)), big))


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
    cv_ms, cv_min = time_call(
        lambda: [cv2.distanceTransform(s, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) for s in src]
    )
    sp_ms, sp_min = time_call(lambda: [ndimage.distance_transform_edt(s) for s in src], n=20)
    jx_ms, jx_min = time_call(lambda: edt(mj))
    nv_comp = time_compile(lambda: _naive_edt(mj))
    n_naive = 10 if side > 100 else 50
    nv_ms, nv_min = time_call(lambda: _naive_edt(mj), n=n_naive)
    rows = [
        Row(kernel, "cv2.distanceTransform PRECISE (loop)", cv_ms, cv_min, 50),
        Row(kernel, "scipy.ndimage.distance_transform_edt (loop)", sp_ms, sp_min, 20),
        Row(
            kernel,
            "jaxmocap.distance.edt (jit, blocked fori)",
            jx_ms,
            jx_min,
            50,
            comp,
            f"max abs err vs cv2 {err:.1e} px",
        ),
        Row(kernel, "naive JAX (jit, broadcast min)", nv_ms, nv_min, n_naive, nv_comp),
    ]
    summary = (
        f"{kernel}: jaxmocap {jx_ms:.3f} ms vs cv2 {cv_ms:.3f} ms "
        f"(cv2/jax = {cv_ms / jx_ms:.2f}x), vs SciPy {sp_ms:.3f} ms "
        f"(scipy/jax = {sp_ms / jx_ms:.2f}x), naive JAX {nv_ms:.2f} ms"
    )
    return rows, summary


def main() -> None:
    rng = np.random.default_rng(0)
    rows, summary = [], []
    for side in sized(full=(40, 160), quick=(40,)):
        r, s = _bench_size(rng, side)
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
    summary.append("Measured on a 2-core machine shared with other engineers' jobs (noisy).")
    path = write_results("bench_distance", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
