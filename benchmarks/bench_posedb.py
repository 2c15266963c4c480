"""Pose database (Wang et al. 2011 §5.2 Step 2): build rate, 10-NN search at 80,000 poses, and
how well the blended pose matches held-out truth.

* build: tiny 40x40 maps rendered per second (``render_maps``, jitted batches of 256);
* search, one query, 80,000 poses: ``query_exact`` (packed 4-bit codes, chunked) and
  ``query_fast`` (quarter-resolution first stage + exact re-rank) vs NumPy: chunked distance
  on the uint8 maps, the same packed-code algorithm with ``np.bitwise_count``, and the
  compressed 640-d histogram ``sgemv`` (8x8 cells x 10 colours); a naive JAX distance on the
  uint8 maps as in PERF-NOTES;
* agreement and accuracy on held-out queries (clips never in the database, random
  orientations, 3% random pixel ids, shifts of up to 1 px): identical 10-NN of the fast search
  (and of the histogram sgemv) vs the exact one; root-aligned mean joint error (cm) of the
  blend ``q_b``, of the best neighbour alone and of the database's mean pose.

Building 80,000 maps takes several minutes on the shared 2-core machine, so the database
built here has ``BUILD_SIZE`` poses; search times at 80,000 use it tiled 4x (same memory
traffic and work); agreement and accuracy use the real ``BUILD_SIZE`` database.
Run: python benchmarks/bench_posedb.py
"""

import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap import posedb
from jaxmocap._config import enable_compilation_cache
from jaxmocap.body import default_body, keypoints
from jaxmocap.garment import default_garment
from jaxmocap.synth import HELDOUT_CLIPS, TRAIN_CLIPS

BUILD_SIZE = sized(full=20_000, quick=2_000)
SEARCH_SIZE = sized(full=80_000, quick=8_000)
N_QUERIES = sized(full=200, quick=20)
NP_CHUNK = 4096


def numpy_distance_knn(maps_flat: np.ndarray, q: np.ndarray, k: int = 10) -> np.ndarray:
    """Best plain NumPy: the weighted distance on uint8 maps, in cache-sized chunks."""
    fg_q = q > 0
    out = np.empty(len(maps_flat), np.int32)
    for s in range(0, len(maps_flat), NP_CHUNK):
        a = maps_flat[s:s + NP_CHUNK]
        out[s:s + NP_CHUNK] = 2 * np.count_nonzero(a != q, axis=1) - np.count_nonzero(
            (a > 0) != fg_q, axis=1)
    return _stable_topk(out, k)


def _stable_topk(d2: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` smallest, ties to the lower index (as the library): one int64 key."""
    key = d2.astype(np.int64) * len(d2) + np.arange(len(d2))
    idx = np.argpartition(key, k)[:k]
    return idx[np.argsort(key[idx])]


def numpy_packed_knn(codes_rows: np.ndarray, qcode: np.ndarray, k: int = 10) -> np.ndarray:
    """The library's packed-code distance in NumPy (``np.bitwise_count``), chunked."""
    nib = posedb._search.NIBBLE_WORDS
    out = np.empty(len(codes_rows), np.int32)
    for s in range(0, len(codes_rows), NP_CHUNK):
        x = codes_rows[s:s + NP_CHUNK] ^ qcode
        t = x[:, :nib] | (x[:, :nib] >> 1)
        t = (t | (t >> 2)) & np.uint32(0x11111111)
        out[s:s + NP_CHUNK] = 2 * np.bitwise_count(t).sum(1, dtype=np.int32) - np.bitwise_count(
            x[:, nib:]).sum(1, dtype=np.int32)
    return _stable_topk(out, k)


def histograms(maps: np.ndarray) -> np.ndarray:
    """640-d float32: per colour 1..10, pixel counts in the 8x8 grid of 5x5 cells."""
    n = len(maps)
    oh = maps[..., None] == np.arange(1, 11, dtype=np.uint8)
    return oh.reshape(n, 8, 5, 8, 5, 10).sum((2, 4), dtype=np.float32).reshape(n, -1)


def sgemv_knn(h: np.ndarray, sq: np.ndarray, hq: np.ndarray, k: int = 10) -> np.ndarray:
    score = sq - 2.0 * (h @ hq)
    idx = np.argpartition(score, k)[:k]
    return idx[np.argsort(score[idx])]


def heldout_queries(model, garment):
    pool = posedb.source_pool(model, HELDOUT_CLIPS)
    cfg = posedb.SamplingConfig(size=N_QUERIES, seed=101, p_real=1.0, joint_noise=0.0,
                                clips=HELDOUT_CLIPS)
    poses = posedb.sample_poses(cfg, model, pool)
    clean = posedb.render_maps(model, garment, poses, progress=False)
    rng = np.random.default_rng(7)
    noisy = clean.copy()
    flip = rng.uniform(size=noisy.shape) < 0.03
    noisy[flip] = rng.integers(0, garment.n_colours + 1, flip.sum())
    for i in range(len(noisy)):
        noisy[i] = np.roll(noisy[i], tuple(rng.integers(-1, 2, 2)), axis=(0, 1))
    return poses, clean, noisy


def main() -> None:
    enable_compilation_cache()
    model, garment = default_body(), default_garment()
    rows: list[Row] = []
    summary = ["CPU contention: up to 7 engineers share this 2-core machine; absolute times "
               "are pessimistic, ratios measured side by side in the same run."]

    # --- build rate (2,048 maps, compiled program already warm after the first batch)
    pool = posedb.source_pool(model, TRAIN_CLIPS)
    n_probe = sized(full=2048, quick=512)
    probe = posedb.sample_poses(posedb.SamplingConfig(size=n_probe, seed=1), model, pool)
    posedb.render_maps(model, garment, probe[:256], progress=False)
    t0 = time.perf_counter()
    posedb.render_maps(model, garment, probe, progress=False)
    rate = len(probe) / (time.perf_counter() - t0)
    summary.append(f"build: {rate:.0f} tiny maps/s (ray casting, jit batches of 256): "
                   f"80,000 poses take about {80_000 / rate / 60:.1f} min here")
    t0 = time.perf_counter()
    db = posedb.load_or_build(posedb.SamplingConfig(size=BUILD_SIZE), model, garment)
    elapsed = time.perf_counter() - t0
    summary.append(f"database of {BUILD_SIZE} poses: load_or_build {elapsed:.1f} s "
                   f"(key {db.key}; built on the first run, loaded afterwards)")
    maps = posedb.unpack_codes(db)
    poses_db = np.asarray(db.poses)

    # --- search timings at 80,000 (the BUILD_SIZE database tiled)
    reps = SEARCH_SIZE // BUILD_SIZE
    big_maps = np.tile(maps, (reps, 1, 1))
    big = posedb.make_posedb(big_maps, np.tile(poses_db, (reps, 1)), garment.n_colours)
    big_flat = big_maps.reshape(SEARCH_SIZE, -1)
    codes_rows = np.asarray(big.codes).transpose(0, 2, 1).reshape(-1, big.codes.shape[1])
    codes_rows = np.ascontiguousarray(codes_rows[:SEARCH_SIZE])
    poses_q, clean, noisy = heldout_queries(model, garment)
    q = noisy[0]
    qj = jnp.asarray(q)
    kernel = f"10-NN, {SEARCH_SIZE} x 40x40, one query"
    exact_c = time_compile(lambda: posedb.query_exact(big, qj))
    fast_c = time_compile(lambda: posedb.query_fast(big, qj))
    # interleaved (the load on the shared machine drifts): 8 rounds of 5 calls each
    ex_t, fa_t = [], []
    for _ in range(8):
        ex_t.append(time_call(lambda: posedb.query_exact(big, qj), n=5, warmup=1))
        fa_t.append(time_call(lambda: posedb.query_fast(big, qj), n=5, warmup=1))
    ex_ms, ex_min = float(np.median([t[0] for t in ex_t])), min(t[1] for t in ex_t)
    fa_ms, fa_min = float(np.median([t[0] for t in fa_t])), min(t[1] for t in fa_t)
    np_ms, np_min = time_call(lambda: numpy_distance_knn(big_flat, q.reshape(-1)), n=15)
    qcode = np.asarray(posedb.pack_map(qj))
    pk_ms, pk_min = time_call(lambda: numpy_packed_knn(codes_rows, qcode), n=15)
    h_big = histograms(big_maps)
    sq_big = (h_big.astype(np.float64) ** 2).sum(1).astype(np.float32)
    hq = histograms(q[None])[0]
    sg_ms, sg_min = time_call(lambda: sgemv_knn(h_big, sq_big, hq), n=30)
    big_j = jnp.asarray(big_flat)

    @jax.jit
    def naive(maps_j, qq):
        fa, fq = maps_j > 0, qq > 0
        d = jnp.sum((maps_j != qq[None]) & fa & fq[None], axis=1) + 0.5 * jnp.sum(
            fa != fq[None], axis=1)
        return jax.lax.top_k(-d, 10)

    nv_c = time_compile(lambda: naive(big_j, jnp.asarray(q.reshape(-1))))
    nv_ms, nv_min = time_call(lambda: naive(big_j, jnp.asarray(q.reshape(-1))), n=10)
    ref = numpy_distance_knn(big_flat, q.reshape(-1))
    got = np.asarray(posedb.query_exact(big, qj).index)
    assert np.array_equal(ref, got), (ref, got)
    assert np.array_equal(numpy_packed_knn(codes_rows, qcode), got)
    rows += [
        Row(kernel, "NumPy chunked distance on uint8 maps (baseline)", np_ms, np_min, 15),
        Row(kernel, "NumPy packed codes + np.bitwise_count", pk_ms, pk_min, 15),
        Row(kernel, "NumPy compressed 640-d histogram sgemv (approximate)", sg_ms, sg_min, 30),
        Row(kernel, "JAX naive distance on uint8 maps (jit)", nv_ms, nv_min, 10, nv_c),
        Row(kernel, "jaxmocap query_exact (packed, chunked)", ex_ms, ex_min, 40, exact_c,
            f"{np_ms / ex_ms:.1f}x vs NumPy baseline"),
        Row(kernel, "jaxmocap query_fast (quarter-res + exact re-rank of 200)", fa_ms, fa_min, 40,
            fast_c, f"{np_ms / fa_ms:.1f}x vs NumPy baseline, {ex_ms / fa_ms:.1f}x vs exact"),
    ]
    summary.append(f"10-NN at {SEARCH_SIZE}: exact {ex_ms:.2f} ms ({np_ms / ex_ms:.1f}x NumPy "
                   f"{np_ms:.1f} ms), fast {fa_ms:.2f} ms ({np_ms / fa_ms:.1f}x NumPy, "
                   f"{sg_ms / fa_ms:.1f}x the 640-d sgemv {sg_ms:.1f} ms)")

    # --- agreement and accuracy on the real BUILD_SIZE database
    def vmapped(fn):
        return jax.jit(jax.vmap(fn, in_axes=(None, 0)))

    batch, fast_b, est_b = (vmapped(f) for f in (posedb.query_exact, posedb.query_fast,
                                                  posedb.estimate_pose))
    queries = np.concatenate([clean, noisy])
    exact = np.asarray(batch(db, jnp.asarray(queries)).index)
    fast = np.asarray(fast_b(db, jnp.asarray(queries)).index)
    agree = np.mean(np.all(exact == fast, axis=1))
    h_db = histograms(maps)
    sq_db = (h_db.astype(np.float64) ** 2).sum(1).astype(np.float32)
    hq_all = histograms(queries)
    sg_same = np.mean([set(sgemv_knn(h_db, sq_db, hq_all[i])) == set(exact[i])
                       for i in range(len(queries))])
    sg_overlap = np.mean([len(set(sgemv_knn(h_db, sq_db, hq_all[i])) & set(exact[i])) / 10
                          for i in range(len(queries))])
    sg_recall = np.mean([set(exact[i]) <= set(sgemv_knn(h_db, sq_db, hq_all[i], 200))
                         for i in range(len(queries))])
    summary.append(f"agreement with the exact 10-NN on {len(queries)} held-out queries "
                   f"({BUILD_SIZE} poses; clean + noisy): query_fast {100 * agree:.1f}% "
                   f"identical; 640-d histogram sgemv {100 * sg_same:.1f}% identical "
                   f"({sg_overlap * 10:.1f}/10 shared), its top-200 contains the exact 10 in "
                   f"{100 * sg_recall:.1f}%")
    kp = jax.jit(jax.vmap(lambda qq: keypoints(model, qq)))
    truth = np.asarray(kp(jnp.asarray(poses_q)))

    def mpjpe(qs):
        return float(np.linalg.norm(np.asarray(kp(jnp.asarray(qs))) - truth, axis=-1).mean()
                     * 100)

    for name, qset in (("clean", clean), ("noisy", noisy)):
        qb, nb = est_b(db, jnp.asarray(qset))
        e_blend = mpjpe(qb)
        e_best = mpjpe(poses_db[np.asarray(nb.index[:, 0])])
        e_mean = mpjpe(np.tile(poses_db.mean(0), (len(qset), 1)))
        summary.append(f"held-out {name} queries, root-aligned mean joint error: blend q_b "
                       f"{e_blend:.1f} cm, best neighbour {e_best:.1f} cm, mean DB pose "
                       f"{e_mean:.1f} cm ({BUILD_SIZE}-pose database)")
    path = write_results("bench_posedb", rows, summary)
    print("\n".join(summary))
    print(path.read_text())


if __name__ == "__main__":
    main()
