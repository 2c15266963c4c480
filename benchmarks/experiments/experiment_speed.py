"""Speed of ``jaxmocap experiment`` on a local Dask cluster vs in-process, and of the IK
tuning gradient over clips on Dask workers vs in-process (docs/results/experiments.md).

A. ``experiment``: 4 held-out/train stereo sequences (320x240 pair, single-colour shirt,
   ``FRAMES`` frames) x 2 configurations of the stereo particle filter (the default tracker
   and Azad's filter, N = 1000): ``--workers 0`` (one process, cells in order) vs
   ``--workers 2``. Each mode runs once to warm JAX's compilation cache (the workers have
   other XLA flags than this process, hence other cache entries), then once timed into a
   fresh folder. The numbers of the two timed runs are compared cell by cell.
B. ``tune``: the IK loss and gradient over ``N_CLIPS`` clips (bundled body, the paper's shirt,
   two 320x240 webcams; centroids = the anchors projected at the clip's retargeted poses + 1.5
   px noise, 25% missing; q_b = truth + noise; windows of 10 frames): one jitted
   ``value_and_grad(ik_loss)`` on all windows stacked (vmapped), clip after clip in this
   process, and one task per clip on 2 Dask workers; median of ``REPEATS`` evaluations after
   a warm-up.

C. threads: one cell of A (default tracker, first sequence) in a fresh process with this
   environment and with the workers' (:data:`jaxmocap.experiment.cluster.WORKER_ENV`): wall
   time, CPU time (user + system) and the process's thread count at the end. CPU time above
   the wall time means the process kept more than one core busy.

    python benchmarks/experiments/experiment_speed.py [A|B|C|ABC]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("JAXMOCAP_SPEED_DATA", "/tmp/jaxmocap_experiment_speed"))
CLIPS = ("humanoid3d_punch", "humanoid3d_dance_b", "walker/turn_left0", "humanoid3d_walk")
FRAMES = int(os.environ.get("JAXMOCAP_SPEED_FRAMES", "80"))
CONFIG = """
[[config]]
name = "default"
method = "pf"
seeds = [0]

[[config]]
name = "azad"
method = "pf"
seeds = [0]
[config.options]
azad = true
blob_params = "azad"
"""
N_CLIPS, WINDOW, WINDOWS_PER_CLIP, REPEATS = 4, 10, 2, 5
OUT = ROOT / "docs" / "results" / "experiments.json"


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def cli(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "jaxmocap.cli", *args], check=True,
                   env=dict(os.environ, PYTHONPATH=str(ROOT)))
    return time.perf_counter() - t0


def part_a() -> dict:
    data = DATA / f"stereo{FRAMES}"
    for clip in CLIPS:
        folder = data / clip.replace("/", "_")
        if not folder.exists():
            cli("synth", str(folder), "--clip", clip, "--preset", "stereo", "--garment",
                "single", "--background", "plain", "--frames", str(FRAMES), "--fps", "25",
                "--noise", "0.01", "--seed", "0", "--no-colour-ids", "--quiet")
    cfg = DATA / "speed.toml"
    cfg.write_text(CONFIG)
    res = {"sequences": list(CLIPS), "frames": FRAMES, "size": [320, 240],
           "configs": ["default", "azad"], "particles": 1000}
    for mode, workers in (("sequential", "0"), ("workers2", "2")):
        warm = DATA / f"warm_{mode}_{FRAMES}"
        if not warm.exists():
            cli("experiment", str(data), str(cfg), "--out", str(warm), "--workers", workers,
                "--quiet")
    for mode, workers in (("sequential", "0"), ("workers2", "2")):
        out = DATA / f"timed_{mode}_{int(time.time())}"
        before = uptime()
        wall = cli("experiment", str(data), str(cfg), "--out", str(out), "--workers", workers,
                   "--quiet")
        res[mode] = {"wall_s": wall, "uptime_before": before, "uptime_after": uptime(),
                     "summary": json.loads((out / "summary.json").read_text())}
    a, b = (res[m]["summary"]["cells"] for m in ("sequential", "workers2"))
    res["numbers_equal"] = all(
        x["metrics"][k] == y["metrics"][k] for x, y in zip(a, b, strict=True)
        for k in ("mpjpe_cm", "mean_error_all_frames_cm", "per_joint_cm", "validity"))
    res["ratio"] = res["workers2"]["wall_s"] / res["sequential"]["wall_s"]
    for m in ("sequential", "workers2"):
        res[m]["summary"] = {"run": res[m]["summary"]["run"],
                             "table": res[m]["summary"]["table"]}
    print(json.dumps({k: v for k, v in res.items() if k not in ("sequential", "workers2")}))
    print("sequential", res["sequential"]["wall_s"], "workers2", res["workers2"]["wall_s"])
    return res


def part_b() -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    from distributed import Client

    from jaxmocap import tune
    from jaxmocap._config import enable_compilation_cache
    from jaxmocap.body import default_body
    from jaxmocap.camera import stack_cameras
    from jaxmocap.experiment.cluster import local_cluster
    from jaxmocap.experiment.tune_dask import clip_value_and_grad, dask_value_and_grad
    from jaxmocap.garment import default_garment
    from jaxmocap.ik import IKCovariances, anchors_from_garment, project_anchors
    from jaxmocap.posedb import source_pool
    from jaxmocap.synth import SceneConfig
    from jaxmocap.synth.scene import make_cameras

    enable_compilation_cache()
    model = default_body()
    anchors = anchors_from_garment(model, default_garment(model), jnp.float64)
    cams = stack_cameras(make_cameras(SceneConfig(rig="webcams", width=320, height=240),
                                      jnp.float64))
    setup = tune.ik_setup(model, cams, anchors)
    rng = np.random.default_rng(0)
    proj = jax.jit(jax.vmap(lambda q: project_anchors(cams, model.chain, anchors, q)))
    clips = []
    for clip in CLIPS[:N_CLIPS]:
        q = np.asarray(source_pool(model, (clip,))[: WINDOW * WINDOWS_PER_CLIP], np.float64)
        q[:, :3] -= q[:1, :3] - np.array([0.0, 0.0, q[0, 2]])  # start over the origin
        c = np.asarray(proj(jnp.asarray(q))) + rng.normal(0, 1.5, (len(q), 2, 20, 2))
        vis = rng.random(c.shape[:3]) > 0.25
        c[~vis] = np.nan
        q_b = q + rng.normal(0, 0.05, q.shape) * np.r_[[0.3] * 3, [1.0] * (q.shape[1] - 3)]
        clips.append(tune.ik_observations([(c, vis, q_b, q)], WINDOW, jnp.float64))
    theta = tune.ik_theta(IKCovariances.isotropic(2.0, 0.3, 0.5, model.n_dof))
    stacked = jax.tree.map(lambda *a: jnp.concatenate(a), *clips)
    vg_all = jax.jit(jax.value_and_grad(tune.ik_loss))

    def timed(fn):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        ts = []
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            ts.append(time.perf_counter() - t0)
        return first, float(np.median(ts))

    res = {"clips": N_CLIPS, "windows_per_clip": WINDOWS_PER_CLIP, "window": WINDOW,
           "n_dof": model.n_dof, "uptime_before": uptime()}
    v_all, g_all = vg_all(theta, setup, stacked)
    res["vmapped"] = timed(lambda: vg_all(theta, setup, stacked))
    local = clip_value_and_grad(setup, clips)
    v_loc, g_loc = local(theta)
    res["clip_by_clip"] = timed(lambda: local(theta))
    with local_cluster(2) as cluster, Client(cluster) as client:
        t0 = time.perf_counter()
        dist = dask_value_and_grad(client, setup, clips)
        v_d, g_d = dist(theta)
        res["dask2_first_incl_scatter_s"] = time.perf_counter() - t0
        res["dask2"] = timed(lambda: dist(theta))
    diff = lambda a, b: max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)) /
                                      (np.abs(np.asarray(y)) + 1e-300)))
                            for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))
    res["loss"] = {"vmapped": float(v_all), "clip_by_clip": float(v_loc), "dask2": float(v_d)}
    res["max_rel_grad_diff"] = {"dask2_vs_clip_by_clip": diff(g_d, g_loc),
                                "clip_by_clip_vs_vmapped": diff(g_loc, g_all)}
    res["uptime_after"] = uptime()
    print(json.dumps(res))
    return res


CELL_SCRIPT = """
import json, os, resource, sys, time
t0 = time.perf_counter()
from jaxmocap.experiment.config import load_config
from jaxmocap.experiment.cell import compute_cell
cfg = load_config(sys.argv[1]).configs[0].to_dict()
out = compute_cell({"folder": sys.argv[2], "config": cfg, "seed": 0, "x64": False})
r = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": time.perf_counter() - t0, "cpu_s": r.ru_utime + r.ru_stime,
                  "threads": len(os.listdir("/proc/self/task")),
                  "ms_per_frame": 1e3 * float(out["times"][1])}))
"""


def part_c() -> dict:
    from jaxmocap.experiment.cluster import worker_env

    folder = DATA / f"stereo{FRAMES}" / CLIPS[0]
    res = {"uptime_before": uptime()}
    for name, env in (("default", {}), ("worker_env", worker_env())):
        for k in ("XLA_FLAGS", "OMP_NUM_THREADS"):  # start from this shell's settings
            env.setdefault(k, os.environ.get(k, ""))
        p = subprocess.run([sys.executable, "-c", CELL_SCRIPT, str(DATA / "speed.toml"),
                            str(folder)], capture_output=True, text=True, check=True,
                           env=dict(os.environ, PYTHONPATH=str(ROOT), **env))
        res[name] = json.loads(p.stdout.strip().splitlines()[-1])
    res["uptime_after"] = uptime()
    print(json.dumps(res))
    return res


def main(parts: str = "ABC") -> None:
    res = json.loads(OUT.read_text()) if OUT.exists() else {}
    if "A" in parts:
        res["experiment"] = part_a()
    if "B" in parts:
        res["tune"] = part_b()
    if "C" in parts:
        res["threads"] = part_c()
    OUT.write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "ABC")
