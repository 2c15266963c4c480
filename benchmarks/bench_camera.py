"""Camera kernels vs OpenCV: projecting 10^5 points with distortion (``cv2.projectPoints``) and
triangulating 10^4 points from two views (``cv2.triangulatePoints``, linear DLT only).

Run: ``python benchmarks/bench_camera.py`` (float32, the library default).
"""

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._common import Row, sized, time_call, time_compile, write_results
from jaxmocap.camera import look_at, project, stack_cameras, triangulate

N_PROJECT = sized(full=100_000, quick=10_000)
N_TRIANGULATE = sized(full=10_000, quick=1_000)
DIST = (-0.28, 0.09, 0.0012, -0.0008, -0.012)


def main() -> None:
    rng = np.random.default_rng(0)
    cams = [
        look_at(
            np.array(eye, np.float32),
            np.array([0, 0, 1.0], np.float32),
            width=640,
            height=480,
            fx=600.0,
            dist=np.array(DIST, np.float32),
        )
        for eye in ([3.0, -1.0, 1.6], [2.5, 1.5, 1.4])
    ]
    rows: list[Row] = []

    # --- project 10^5 points --------------------------------------------------------------
    X = (rng.normal(scale=0.4, size=(N_PROJECT, 3)) + [0, 0, 1.0]).astype(np.float32)
    Xj = jnp.asarray(X)
    cam = cams[0]
    proj = jax.jit(project)
    compile_ms = time_compile(lambda: proj(cam, Xj))
    jax_med, jax_min = time_call(lambda: proj(cam, Xj), n=30)
    rvec, _ = cv2.Rodrigues(np.asarray(cam.R, np.float64))
    args = (
        rvec,
        np.asarray(cam.t, np.float64),
        np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
    )
    cv_med, cv_min = time_call(lambda: cv2.projectPoints(X, *args), n=30)
    err = np.abs(np.asarray(proj(cam, Xj)) - cv2.projectPoints(X, *args)[0][:, 0]).max()
    rows += [
        Row(
            "project 1e5 pts (dist)",
            "jaxmocap jit f32",
            jax_med,
            jax_min,
            N_PROJECT,
            compile_ms,
            f"max |diff| vs cv2 {err:.1e} px",
        ),
        Row("project 1e5 pts (dist)", "cv2.projectPoints", cv_med, cv_min, N_PROJECT),
    ]

    # --- triangulate 10^4 points, 2 views ----------------------------------------------------
    s = stack_cameras(cams)
    Xt = (rng.normal(scale=0.4, size=(N_TRIANGULATE, 3)) + [0, 0, 1.0]).astype(np.float32)
    uv = np.asarray(jax.vmap(project, (0, None))(s, jnp.asarray(Xt)))
    uv = (uv + rng.normal(scale=0.5, size=uv.shape)).astype(np.float32)
    uvj = jnp.asarray(uv)
    P = [
        np.asarray(c.K, np.float64) @ np.hstack([np.asarray(c.R), np.asarray(c.t)[:, None]])
        for c in cams
    ]
    # OpenCV baseline: undistortPoints (as a user must, the lens is distorted) + DLT
    Kd = [(np.asarray(c.K, np.float64), np.asarray(c.dist, np.float64)) for c in cams]

    def cv_triangulate():
        ideal = [cv2.undistortPoints(uv[i][:, None], *Kd[i], P=Kd[i][0]) for i in range(2)]
        h = cv2.triangulatePoints(P[0], P[1], ideal[0][:, 0].T, ideal[1][:, 0].T)
        return (h[:3] / h[3]).T

    cv_med, cv_min = time_call(cv_triangulate, n=20)
    cv_err = np.sqrt(np.mean(np.sum((cv_triangulate() - Xt) ** 2, -1)))
    for refine in (False, True):
        tri = jax.jit(lambda c, u, refine=refine: triangulate(c, u, refine=refine))
        compile_ms = time_compile(lambda tri=tri: tri(s, uvj))
        med, mn = time_call(lambda tri=tri: tri(s, uvj), n=20)
        e = np.sqrt(np.mean(np.sum((np.asarray(tri(s, uvj)) - Xt) ** 2, -1)))
        name = "jaxmocap jit f32 DLT" + (" + 5 GN steps" if refine else "")
        rows.append(
            Row(
                "triangulate 1e4 pts 2 views",
                name,
                med,
                mn,
                N_TRIANGULATE,
                compile_ms,
                f"RMS 3D error {e * 1e3:.2f} mm",
            )
        )
    rows.append(
        Row(
            "triangulate 1e4 pts 2 views",
            "cv2.undistortPoints + triangulatePoints",
            cv_med,
            cv_min,
            N_TRIANGULATE,
            None,
            f"RMS 3D error {cv_err * 1e3:.2f} mm",
        )
    )

    by = {(r.kernel, r.implementation): r.median_ms for r in rows}
    p_jax = by[("project 1e5 pts (dist)", "jaxmocap jit f32")]
    p_cv = by[("project 1e5 pts (dist)", "cv2.projectPoints")]
    summary = [
        "Measured on a shared 2-core machine under contention from other jobs: absolute "
        "numbers are noisy, ratios within one run are what to compare.",
        f"project: jit {p_jax:.2f} ms vs cv2 {p_cv:.2f} ms (x{p_cv / p_jax:.2f} speed-up)",
    ]
    k = "triangulate 1e4 pts 2 views"
    cv = by[(k, "cv2.undistortPoints + triangulatePoints")]
    for name in ("jaxmocap jit f32 DLT", "jaxmocap jit f32 DLT + 5 GN steps"):
        summary.append(
            f"triangulate: {name} {by[(k, name)]:.2f} ms vs OpenCV {cv:.2f} ms "
            f"(x{cv / by[(k, name)]:.2f} speed-up)"
        )
    path = write_results("bench_camera", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
