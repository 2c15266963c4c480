"""Colour pipeline speed (Wang §4, §5.2 step 1) vs NumPy baselines, side by side.

1. Histogram search, 640 x 480, 100 bins, stride 6, six scales (DEFAULT_SCALES): jaxmocap (jit)
   vs NumPy with a stride-6 cell integral histogram and vs NumPy with a full-resolution one.
2. Mahalanobis classification, 10 colours, a 200 x 200 crop and a full 640 x 480 frame:
   jaxmocap ``classify`` (float32, fused per-class running minimum) vs the NumPy
   10-feature quadratic form as one GEMM, plus the same GEMM form in JAX for reference.

Run: ``python benchmarks/bench_color.py`` (writes results/bench_color.{json,md}).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap.color import ColorModel, classify, histogram_search
from jaxmocap.color.classify import quadratic_coefficients
from jaxmocap.color.search import DEFAULT_SCALES, MIN_INTENSITY, STRIDE, TAU


def scene(rng, h=480, w=640):
    img = np.repeat(rng.integers(70, 130, (h, w, 1)), 3, axis=-1).astype(float)
    for _ in range(6):  # colourful distractors
        x0, y0 = rng.integers(0, w - 100), rng.integers(0, h - 100)
        img[y0 : y0 + 80, x0 : x0 + 90] = rng.uniform(0, 255, 3)
    cols = rng.uniform(20, 240, (10, 3))
    for n, k in enumerate(rng.permutation(np.repeat(np.arange(10), 2))):  # the shirt
        r, c = divmod(n, 4)
        img[150 + 36 * r : 186 + 36 * r, 300 + 37 * c : 337 + 37 * c] = cols[k]
    return np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)


def np_bins(img):
    x = img.astype(np.float32)
    tot = x[..., 0] + x[..., 1] + x[..., 2]
    safe = np.where(tot > 0, tot, 1)
    ir = np.minimum(np.floor(10 * x[..., 0] / safe), 9)
    ig = np.minimum(np.floor(10 * x[..., 1] / safe), 9)
    return (ir * 10 + ig).astype(np.int64), tot >= MIN_INTENSITY


def np_locate(heat, valid, hc1, wc1, scales):
    umax = heat.max()
    wgt = np.where(valid, np.exp(-(((heat - umax) / (0.1 * umax)) ** 2)), 0)
    ys = STRIDE * np.arange(hc1) - 0.5
    xs = STRIDE * np.arange(wc1) - 0.5
    tot = wgt.sum()
    return (
        np.array(
            [
                (wgt.sum((0, 1)) * xs).sum(),
                (wgt.sum((0, 2)) * ys).sum(),
                (wgt.sum((1, 2)) * np.asarray(scales)).sum(),
            ]
        )
        / tot
    )


def np_search_cells(img, scales=DEFAULT_SCALES):
    """NumPy: bincount into 6x6 cells, two cumsums, 4-corner windows, u, weighted mean."""
    h, w = img.shape[0] // STRIDE, img.shape[1] // STRIDE
    bins, counted = np_bins(img[: h * STRIDE, : w * STRIDE])
    cell = (np.arange(h)[:, None] * w + np.arange(w)[None, :]).repeat(STRIDE, 0).repeat(STRIDE, 1)
    hist = np.bincount((cell * 100 + bins)[counted], minlength=h * w * 100).reshape(h, w, 100)
    integral = np.zeros((h + 1, w + 1, 100))
    integral[1:, 1:] = hist.cumsum(0).cumsum(1)
    return _np_windows(integral, scales, h + 1, w + 1, 1)


def np_search_fullres(img, scales=DEFAULT_SCALES):
    """NumPy: full-resolution integral histogram (481, 641, 100), windows every 6th pixel."""
    H, W = img.shape[:2]
    bins, counted = np_bins(img)
    onehot = np.zeros((H + 1, W + 1, 100), np.int32)
    yy, xx = np.nonzero(counted)
    onehot[yy + 1, xx + 1, bins[counted]] = 1
    integral = onehot.cumsum(0).cumsum(1)
    h, w = H // STRIDE, W // STRIDE
    return _np_windows(integral, scales, h + 1, w + 1, STRIDE)


def _np_windows(integral, scales, hc1, wc1, step):
    heat = np.zeros((len(scales), hc1, wc1))
    valid = np.zeros(heat.shape, bool)
    for k, s in enumerate(scales):
        m = s // STRIDE
        corner = integral[: (hc1 - 1) * step + 1 : step, : (wc1 - 1) * step + 1 : step]
        block = corner[m:, m:] - corner[:-m, m:] - corner[m:, :-m] + corner[:-m, :-m]
        block = block.astype(np.float32)
        tot = block.sum(-1)
        safe = np.where(tot > 0, tot, 1)
        u = np.minimum(block, TAU * safe[..., None]).sum(-1) / safe
        ok = tot >= 0.25 * s * s
        heat[k, m // 2 : hc1 - m // 2, m // 2 : wc1 - m // 2] = np.where(ok, u, 0)
        valid[k, m // 2 : hc1 - m // 2, m // 2 : wc1 - m // 2] = ok
    return np_locate(heat, valid, hc1, wc1, scales)


def random_model(rng, k=10):
    mean = rng.uniform(30, 220, (k, 3))
    a = rng.normal(size=(k, 3, 3)) * rng.uniform(3, 15, (k, 1, 1))
    return mean, a @ np.swapaxes(a, 1, 2) + 4 * np.eye(3)


def np_coefficients(W, mean, cov):
    """The same ten coefficients per colour as jaxmocap, in NumPy (float32)."""
    P = np.linalg.inv(cov)
    A = np.einsum("ji,kjl,lm->kim", W, P, W)
    m = mean - 127.5 * W.sum(axis=1)[None, :]
    Pm = np.einsum("kij,kj->ki", P, m)
    b = -2.0 * Pm @ W
    c = np.einsum("ki,ki->k", m, Pm)
    return np.stack(
        [
            A[:, 0, 0],
            A[:, 1, 1],
            A[:, 2, 2],
            2 * A[:, 0, 1],
            2 * A[:, 0, 2],
            2 * A[:, 1, 2],
            b[:, 0],
            b[:, 1],
            b[:, 2],
            c,
        ]
    ).astype(np.float32)


def np_gemm_classify(img, W, mean, cov, T=3.0):
    """NumPy baseline: the 10-feature quadratic form as one (N, 10) @ (10, k) GEMM."""
    x = img.reshape(-1, 3).astype(np.float32) - 127.5
    coef = np_coefficients(W, mean, cov)
    f = np.empty((len(x), 10), np.float32)
    f[:, 0], f[:, 1], f[:, 2] = x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2
    f[:, 3], f[:, 4], f[:, 5] = x[:, 0] * x[:, 1], x[:, 0] * x[:, 2], x[:, 1] * x[:, 2]
    f[:, 6:9], f[:, 9] = x, 1
    d2 = f @ coef
    best = d2.argmin(1)
    ids = np.where(d2[np.arange(len(x)), best] < T * T, best + 1, 0)
    return ids.reshape(img.shape[:2])


def jax_gemm_classify(img, W, model, T=3.0):
    x = img.reshape(-1, 3).astype(jnp.float32) - 127.5
    f = jnp.stack(
        [
            x[:, 0] ** 2,
            x[:, 1] ** 2,
            x[:, 2] ** 2,
            x[:, 0] * x[:, 1],
            x[:, 0] * x[:, 2],
            x[:, 1] * x[:, 2],
            x[:, 0],
            x[:, 1],
            x[:, 2],
            jnp.ones(x.shape[0], jnp.float32),
        ],
        axis=1,
    )
    d2 = f @ quadratic_coefficients(model, W)
    best = jnp.argmin(d2, axis=1)
    return jnp.where(jnp.min(d2, axis=1) < T * T, best + 1, 0).reshape(img.shape[:2])


def reference_ids(img, W, mean, cov, T=3.0):
    x = img.reshape(-1, 3).astype(np.float64) @ W.T
    d2 = np.stack(
        [
            np.einsum("ni,ij,nj->n", x - mean[k], np.linalg.inv(cov[k]), x - mean[k])
            for k in range(len(mean))
        ],
        1,
    )
    return np.where(d2.min(1) < T * T, d2.argmin(1) + 1, 0).reshape(img.shape[:2])


def main() -> None:
    rng = np.random.default_rng(0)
    rows, summary = [], []

    img = scene(rng)
    jimg = jnp.asarray(img)
    search = jax.jit(histogram_search, static_argnames=("scales", "stride"))
    comp = time_compile(lambda: search(jimg))
    res = search(jimg)
    ours = np.array([float(res.x), float(res.y), float(res.s)])
    k = "chroma-hist search 640x480"
    t_j = time_call(lambda: search(jimg), n=sized(full=50, quick=10))
    rows.append(
        Row(
            k,
            "jaxmocap jit (stride-6 cells, scan prefix sums, 64 reachable bins)",
            *t_j,
            50,
            comp,
            f"(x', y', s') = {np.round(ours, 1).tolist()}; scales {DEFAULT_SCALES}",
        )
    )
    t_c = time_call(lambda: np_search_cells(img), n=30)
    ref = np_search_cells(img)
    rows.append(
        Row(
            k,
            "numpy stride-6 cell integral histogram",
            *t_c,
            30,
            notes=f"max |diff| vs jaxmocap {np.abs(ref - ours).max():.2e} px",
        )
    )
    t_f = time_call(lambda: np_search_fullres(img), n=10, warmup=1)
    ref_f = np_search_fullres(img)
    rows.append(
        Row(
            k,
            "numpy full-res integral histogram",
            *t_f,
            10,
            notes=f"max |diff| vs jaxmocap {np.abs(ref_f - ours).max():.2e} px",
        )
    )
    summary.append(
        f"search: {t_c[0] / t_j[0]:.1f}x faster than NumPy stride-6 "
        f"({t_j[0]:.2f} vs {t_c[0]:.2f} ms), {t_f[0] / t_j[0]:.1f}x faster than "
        f"NumPy full-res ({t_f[0]:.1f} ms)"
    )

    mean, cov = random_model(rng)
    W = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    model = ColorModel(mean=jnp.asarray(mean, jnp.float32), cov=jnp.asarray(cov, jnp.float32))
    jW = jnp.asarray(W, jnp.float32)
    cls = jax.jit(classify)
    gemm = jax.jit(jax_gemm_classify)
    for name, (h, w) in [
        ("Mahalanobis 10 colours 200x200", (200, 200)),
        ("Mahalanobis 10 colours 640x480", (480, 640)),
    ][: sized(full=2, quick=1)]:
        px = mean[rng.integers(0, 10, h * w)] + rng.normal(0, 15, (h * w, 3))
        im = np.clip(px @ np.linalg.inv(W).T, 0, 255).astype(np.uint8).reshape(h, w, 3)
        jim = jnp.asarray(im)
        truth = reference_ids(im, W, mean, cov)
        n = sized(full=200 if h == 200 else 50, quick=10)
        comp = time_compile(lambda jim=jim: cls(model, jW, jim))
        t_j = time_call(lambda jim=jim: cls(model, jW, jim), n=n)
        mism = int((np.asarray(cls(model, jW, jim)[0]) != truth).sum())
        rows.append(
            Row(
                name,
                "jaxmocap classify jit float32 (fused class loop)",
                *t_j,
                n,
                comp,
                f"{mism} px differ from float64 reference (ties at T)",
            )
        )
        t_n = time_call(lambda im=im: np_gemm_classify(im, W, mean, cov), n=n)
        mism_n = int((np_gemm_classify(im, W, mean, cov) != truth).sum())
        rows.append(
            Row(
                name,
                "numpy float32 quadratic form, one GEMM",
                *t_n,
                n,
                notes=f"{mism_n} px differ from float64 reference",
            )
        )
        comp_g = time_compile(lambda jim=jim: gemm(jim, jW, model))
        t_g = time_call(lambda jim=jim: gemm(jim, jW, model), n=n)
        rows.append(
            Row(name, "jax jit float32 quadratic form, one GEMM (alternative)", *t_g, n, comp_g)
        )
        summary.append(
            f"{name}: {t_n[0] / t_j[0]:.1f}x faster than NumPy GEMM "
            f"({t_j[0]:.2f} vs {t_n[0]:.2f} ms); JAX GEMM form {t_g[0]:.2f} ms"
        )
    summary.append("Measured on a 2-core machine shared with other jobs (CPU contention).")
    path = write_results("bench_color", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
