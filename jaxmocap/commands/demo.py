"""``jaxmocap demo``: the main job on bundled data, offline.

1. Renders a short two-webcam sequence (Wang et al.'s set-up, 320x240) from a **held-out**
   real motion-capture clip (DeepMimic ``punch``, shipped in pybullet's wheel), with a lamp
   switched off mid-way, an occluder passing in front and a cluttered background.
2. Builds (once, then cached) a small pose database from the *training* clips, fits the colour
   model from scribbles on white-light renders and the initial white balance from one
   scribbled frame of the scene (§5.1).
3. Tracks the sequence with the colour-shirt tracker (all five steps of §5.2 per frame) and
   prints the per-joint error against ground truth and the frame rate.
3b. Renders the same clip for Azad et al.'s set-up (a stereo pair 11 cm apart, 320x240, a
   single-colour shirt) and tracks it with the stereo particle filter (N = 1000, 14 DOF,
   automatic initialisation, edge + 3D distance cues), with its error and frame rate.
4. Writes to ``--out``: ``shirt.*`` and ``pf.*`` (BVH / TRC / C3D / CSV / NPZ) of the motion, an
   overlay video (``overlay.mp4``, H.264 at the capture's frame rate: estimated skeleton and
   classified crop windows over camera 0),
   a plot of estimated vs true joint traces (``traces.png``) and ``summary.json``.

The demo database is small (``DEMO_DB_SIZE`` poses instead of the paper's 80,000) so that
the demo runs in about a minute on 2 cores; ``jaxmocap build-db`` builds the full one.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxmocap.errors import UsageError
from jaxmocap.io.overlay import BONES
from jaxmocap.trackers.driver import PF_JOINTS, SHIRT_JOINTS
from jaxmocap.trackers.shirt.export import (
    DEMO_CLIP,
    DEMO_DB_SIZE,
    DEMO_FRAMES,
    DEMO_LAMP_OFF,
    DEMO_OCCLUDER,
    DEMO_SIZE,
    demo_scene,
    demo_setup,
)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="render a held-out clip, track it, report errors, write exports (offline)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--out", default="jaxmocap-demo", help="output folder (default: %(default)s)")
    from jaxmocap.io.preflight import int_range

    p.add_argument("--frames", type=int_range(2), default=DEMO_FRAMES,
                   help="number of frames to render and track (default: %(default)s)")
    p.set_defaults(func=run)


def _track(params, W0, cams, frames, progress: bool):
    """The shirt tracker over the frames through the driver (the shipped program: no trace)."""
    import jax

    from jaxmocap.trackers.driver import ShirtFrameTracker, drive, sequence_frames

    tracker = ShirtFrameTracker(params, W0, list(cams), [f"cam{i}" for i in range(len(cams))])
    run = drive(tracker, sequence_frames(frames), frames.shape[0], progress=progress,
                keep_outputs=True, desc="shirt tracker")
    stacked = jax.tree.map(lambda *a: np.stack(a), *run.outputs)
    return stacked, run.times


def _track_pf(clip: str, n_frames: int, progress: bool):
    """The stereo particle filter of Azad et al. on its own set-up (module docstring, 3b)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.segment import HSVInterval, SegmentParams
    from jaxmocap.synth import SceneConfig, render_sequence
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.driver import stereo_offline

    config = SceneConfig(clip=clip, rig="stereo", garment="single", background="plain",
                         n_frames=n_frames, noise_sigma=0.01, seed=0)
    seq = render_sequence(config, progress=progress)
    params = sp.make_params(list(seq.cameras), images=sp.Images(
        segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))))
    run = stereo_offline(params, jax.random.key(0), seq.frames)
    obs, est, cold = run.observations, run.estimate, run.timings["filter_first"]
    t0 = time.perf_counter()
    # the same call as stereo_offline made (smooth_lag 0 given): the compiled scan, no retrace
    jax.block_until_ready(sp.run_top_level(params, run.initial_state, obs, 0)[1].q)
    warm_ms = 1e3 * (time.perf_counter() - t0) / n_frames
    return seq, np.asarray(est.q, np.float64), cold, warm_ms, float(jnp.mean(obs.valid))


def _overlay(files, path: Path, frames, cam, kp_est, kp_true, windows, names,
             fps: float) -> None:
    import cv2

    from jaxmocap.camera import project
    from jaxmocap.io.video import VideoWriter

    idx = {n: i for i, n in enumerate(names)}
    est = np.asarray(project(cam, np.nan_to_num(kp_est)))
    true = np.asarray(project(cam, kp_true))
    h, w = frames.shape[1:3]
    scale = 2
    with VideoWriter(files.path(path), fps, w * scale, h * scale) as writer:
        for t in range(frames.shape[0]):
            img = cv2.resize(cv2.cvtColor(frames[t], cv2.COLOR_RGB2BGR), (w * scale, h * scale),
                             interpolation=cv2.INTER_NEAREST)
            x0, y0, s, _ = windows[t] * scale
            cv2.rectangle(img, (int(x0), int(y0)), (int(x0 + s), int(y0 + s)), (255, 255, 255), 1)
            for pts, colour in ((true[t], (0, 200, 0)), (est[t], (0, 0, 255))):
                for a, b in BONES:
                    pa, pb = pts[idx[a]] * scale, pts[idx[b]] * scale
                    if np.all(np.isfinite([*pa, *pb])):
                        cv2.line(img, tuple(int(v) for v in pa), tuple(int(v) for v in pb),
                                 colour, 2, cv2.LINE_AA)
            cv2.putText(img, f"frame {t}  green: truth  red: jaxmocap", (6, 16),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            writer.write(img[..., ::-1])


def _plot(files, path: Path, times, kp_est, kp_true, names) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    joints = ("r_wrist", "l_wrist", "r_elbow")
    fig, axes = plt.subplots(len(joints), 3, figsize=(11, 7), sharex=True)
    for r, j in enumerate(joints):
        i = names.index(j)
        for c, axis in enumerate("xyz"):
            ax = axes[r, c]
            ax.plot(times, kp_true[:, i, c], "g-", label="ground truth")
            ax.plot(times, kp_est[:, i, c], "r.-", label="jaxmocap (shirt)")
            ax.set_ylabel(f"{j} {axis} (m)")
            if r == len(joints) - 1:
                ax.set_xlabel("time (s)")
    axes[0, 0].legend(loc="best", fontsize=8)
    fig.suptitle("Estimated vs true joint positions (world, Z up)")
    fig.tight_layout()
    fig.savefig(files.path(path), dpi=90, format="png")
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.io.atomic import AtomicFiles, check_output_folder
    from jaxmocap.io.export import pose_track, write_exports
    from jaxmocap.synth import render_sequence

    if args.frames < 2:
        raise UsageError(f"--frames: expected an integer >= 2, got {args.frames}")
    out = check_output_folder(args.out)
    progress = True
    print(f"jaxmocap demo: held-out clip '{DEMO_CLIP}', two {DEMO_SIZE[0]}x{DEMO_SIZE[1]} "
          f"webcams, {args.frames} frames, lamp off at frame {DEMO_LAMP_OFF}, occluder during "
          f"frames {DEMO_OCCLUDER[0]}-{DEMO_OCCLUDER[1]}")
    t0 = time.perf_counter()
    config = demo_scene(args.frames)
    seq = render_sequence(config, progress=progress)
    print(f"  rendered in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    model, params, W0, _ = demo_setup(seq, progress)
    print(f"  set-up (pose database of {DEMO_DB_SIZE} poses, colour model, white balance) in "
          f"{time.perf_counter() - t0:.1f} s")
    res, step_s = _track(params, W0, seq.cameras, seq.frames, progress)

    fps = float(config.fps)
    track = pose_track(model, res.q_frame, res.valid, fps)  # every frame's own estimate
    names = list(model.keypoint_names)
    kp_true = np.asarray(seq.groundtruth["keypoints"], np.float64)
    # scored, drawn and plotted: the frames the tracker reports valid
    kp_valid = np.where(track.valid[:, None, None], track.keypoints, np.nan)
    err = np.linalg.norm(kp_valid - kp_true, axis=-1) * 100.0  # cm
    eval_idx = [names.index(j) for j in SHIRT_JOINTS]
    warm = step_s[1:] if step_s.size > 1 else step_s
    print(f"  tracked {len(step_s)} frames: first step {step_s[0]:.1f} s (compilation), then "
          f"{1e3 * np.median(warm):.0f} ms/frame ({1.0 / np.median(warm):.1f} fps); "
          f"valid frames {int(track.valid.sum())}/{len(step_s)}")
    print("  mean per-joint position error (cm), shirt tracker vs ground truth:")
    for j, i in zip(SHIRT_JOINTS, eval_idx, strict=True):
        print(f"    {j:12s} {np.nanmean(err[:, i]):6.1f}")
    overall = float(np.nanmean(err[:, eval_idx]))
    print(f"    {'mean':12s} {overall:6.1f}")

    # The stereo particle filter (Azad et al.) on its own stereo set-up.
    pf_seq, pf_q, pf_cold, pf_ms, blob_frac = _track_pf(DEMO_CLIP, args.frames, progress)
    pf_track = pose_track(model, pf_q, None, fps)
    pf_true = np.asarray(pf_seq.groundtruth["keypoints"], np.float64)
    pf_idx = [names.index(j) for j in PF_JOINTS]
    pf_err = np.linalg.norm(pf_track.keypoints - pf_true, axis=-1)[:, pf_idx] * 100.0
    print(f"  stereo particle filter (N=1000, 14 DOF, 320x240 pair 11 cm apart): first run "
          f"{pf_cold:.1f} s (compilation + annealed initialisation), then {pf_ms:.1f} ms/frame "
          f"for the filter; hands/head triangulated in {100 * blob_frac:.0f}% of cases")
    print("  mean per-joint position error (cm), stereo particle filter vs ground truth:")
    for j, e in zip(PF_JOINTS, pf_err.mean(axis=0), strict=True):
        print(f"    {j:12s} {e:6.1f}")
    print(f"    {'mean':12s} {pf_err.mean():6.1f}")

    summary = {
        "clip": DEMO_CLIP, "frames": int(args.frames), "size": list(DEMO_SIZE),
        "db_size": DEMO_DB_SIZE, "lamp_off": config.lamp_off, "occluder": config.occluder,
        "shirt": {"mean_error_cm": overall,
                  "per_joint_error_cm": {j: float(np.nanmean(err[:, i]))
                                         for j, i in zip(SHIRT_JOINTS, eval_idx, strict=True)},
                  "median_step_ms": float(1e3 * np.median(warm)),
                  "first_step_s": float(step_s[0]),
                  "valid_frames": int(track.valid.sum()),
                  "used_reference": res.used_reference.any(axis=1).tolist()},
        "stereo_pf": {"mean_error_cm": float(pf_err.mean()),
                      "per_joint_error_cm": dict(zip(PF_JOINTS, pf_err.mean(axis=0).tolist(),
                                                     strict=True)),
                      "filter_ms_per_frame": pf_ms, "first_run_s": pf_cold},
    }
    out.mkdir(parents=True, exist_ok=True)
    with AtomicFiles(out) as files:  # one group: an interrupt leaves nothing half-written
        write_exports(files, out, model, track, stem="shirt")
        write_exports(files, out, model, pf_track, stem="pf")
        files.path(out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        _overlay(files, out / "overlay.mp4", seq.frames[:, 0], seq.cameras[0], kp_valid,
                 kp_true, res.window[:, 0], names, fps)
        _plot(files, out / "traces.png", track.times, kp_valid, kp_true, names)
    print(f"  wrote {out}/: shirt.* and pf.* (bvh trc c3d csv npz), overlay.mp4, traces.png, "
          "summary.json")
    return 0
