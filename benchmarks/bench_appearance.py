"""The per-patch colour states (issue 37, ``jaxmocap.appearance``): what they cost a tracked
frame of the colour-shirt tracker, and the state update beside a NumPy baseline.

1. ``shirt step, tracked frame``: the demo's two-camera scene (the JAX renderer, 12 frames),
   the shading-invariant set-up (``shading=(0.5, 4)``) with ``patch_colours`` off (one W per
   camera, reference illuminations) and on, each warmed up on the sequence, then timed on
   its tracked frames **alternately** (A B A B: this machine's speed drifts by tens of per cent
   over minutes, only interleaved timings compare). The issue's budget: at most 20% slower.
2. ``colour state update``: ``part_statistics`` + ``update_parts`` for two cameras' 96 x 96
   crops and 20 patches, jitted, beside the same trimmed statistics and moment-matched update in
   NumPy (``np.bincount`` segment sums; no relight solve: the baseline's cost is a floor).

    python -m benchmarks.bench_appearance      # JAXMOCAP_BENCH_QUICK=1: fewer repetitions
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, write_results
from jaxmocap import appearance as ap


def _numpy_update(mean, cov, img, parts, rate=ap.RATE, gate=ap.GATE):
    """Trimmed per-part statistics and the moment-matched update, NumPy (one camera)."""
    n = mean.shape[0]
    x = img.reshape(-1, 3).astype(np.float64)
    seg = parts.reshape(-1)
    idx = np.clip(seg - 1, 0, n - 1)
    prec = np.linalg.inv(cov)
    d = x - mean[idx]
    d2 = np.einsum("ni,nij,nj->n", d, prec[idx], d)
    seg = np.where(d2 <= gate, seg, 0)
    cnt = np.bincount(seg, minlength=n + 1)[1:].astype(np.float64)
    c = np.maximum(cnt, 1)
    m = np.stack([np.bincount(seg, x[:, i], n + 1)[1:] for i in range(3)], -1) / c[:, None]
    xx = np.stack([np.bincount(seg, x[:, i] * x[:, j], n + 1)[1:]
                   for i in range(3) for j in range(3)], -1).reshape(n, 3, 3) / c[:, None, None]
    cv = xx - m[:, :, None] * m[:, None, :]
    a = np.where(cnt >= ap.MIN_PIXELS, rate, 0.0)[:, None]
    mm = (1 - a) * mean + a * m
    d0, d1 = mean - mm, m - mm
    out = lambda u: u[:, :, None] * u[:, None, :]  # noqa: E731
    cov = (1 - a[:, :, None]) * (cov + out(d0)) + a[:, :, None] * (cv + out(d1))
    return mm, cov


def step_rows(reps: int) -> tuple[list[Row], list[str]]:
    from jaxmocap.synth import render_sequence
    from jaxmocap.trackers import shirt
    from jaxmocap.trackers.shirt.export import demo_scene, demo_setup

    seq = render_sequence(demo_scene(12), progress=False)
    _, params, W0, q0 = demo_setup(seq, progress=False)
    a = dataclasses.replace(params, shading=(0.5, 4.0))
    b = dataclasses.replace(a, patch_colours=True)
    frames = np.asarray(seq.frames)
    states, compile_ms = {}, {}
    for name, p in (("one W per camera", a), ("patch colours", b)):
        s = shirt.init(p, W0, q0)
        t0 = time.perf_counter()
        for t in range(frames.shape[0] - 2):
            s, out = shirt.step(p, s, frames[t])
            jax.block_until_ready(out.q)
            if t == 0:
                compile_ms[name] = (time.perf_counter() - t0) * 1e3
        states[name] = (p, s, bool(out.valid))
    times = {k: [] for k in states}
    for _ in range(reps):  # alternated
        for name, (p, s, _) in states.items():
            t0 = time.perf_counter()
            jax.block_until_ready(shirt.step(p, s, frames[-1])[1].q)
            times[name].append((time.perf_counter() - t0) * 1e3)
    rows = [Row("shirt step, tracked frame (demo scene)", name,
                float(np.median(v)), float(np.min(v)), len(v), compile_ms[name],
                notes=f"previous frame valid: {states[name][2]}")
            for name, v in times.items()]
    ra, rb = rows
    return rows, [f"patch colours / one W per camera, tracked frame: "
                  f"{rb.median_ms / ra.median_ms:.2f}x ({ra.median_ms:.1f} -> {rb.median_ms:.1f} "
                  f"ms, medians of {reps} alternated calls)"]


def update_rows(reps: int) -> tuple[list[Row], list[str]]:
    rng = np.random.default_rng(0)
    P, n = 20, 96
    means = rng.uniform(40, 220, (P, 3))
    covs = np.tile(np.eye(3) * 60.0, (P, 1, 1))
    parts = rng.integers(0, P + 1, (2, n, n))
    imgs = means[np.clip(parts - 1, 0, P - 1)] + rng.normal(0, 6, (2, n, n, 3))
    state = jax.tree.map(lambda x: jnp.stack([x, x]), ap.init_parts(jnp.asarray(means),
                                                                     jnp.asarray(covs)))
    fn = jax.jit(jax.vmap(lambda s, i, p: ap.update_parts(
        s, ap.part_statistics(s, i, p, shading=(0.5, 4.0)), jnp.array(True))[0]))
    ji, jp = jnp.asarray(imgs), jnp.asarray(parts)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(state, ji, jp))
    comp = (time.perf_counter() - t0) * 1e3
    med_j, min_j = time_call(lambda: fn(state, ji, jp), n=reps)
    med_n, min_n = time_call(lambda: [_numpy_update(means, covs, imgs[c], parts[c])
                                      for c in range(2)], n=reps)
    rows = [Row("colour state update, 2 cams x 96x96, 20 patches", "jax (jit, relight solve)",
                med_j, min_j, reps, comp),
            Row("colour state update, 2 cams x 96x96, 20 patches", "numpy (no relight)",
                med_n, min_n, reps)]
    return rows, [f"update: numpy / jax = {med_n / med_j:.2f}x ({med_j:.2f} ms jax, "
                  f"{med_n:.2f} ms numpy)"]


def main() -> None:
    reps = sized(full=21, quick=5)
    rows, summary = step_rows(reps)
    r2, s2 = update_rows(sized(full=50, quick=10))
    path = write_results("bench_appearance", rows + r2, summary + s2)
    print("\n".join(summary + s2))
    print(path)


if __name__ == "__main__":
    main()
