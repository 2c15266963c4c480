"""Head and hands of the stereo filter on the test world, per sequence (issue 37 item 4):
the share of frames with each hand within :data:`HAND_CM` of the truth, of the frames where
that hand is visible in both cameras, the head within :data:`HEAD_CM` (of the frames it is
visible in both), and the filter's mean joint error (the experiment's joints,
``PF_JOINTS``), for a configuration of :func:`jaxmocap.experiment.cell._track_pf`.

Visibility from the ground truth: the sequence's own body rendered at the true pose by the
ray caster (:func:`jaxmocap.trackers.stereo_pf.parts.render_parts`: self-occlusion, the
image border) shows at least :data:`MIN_VISIBLE_PX` pixels of the part in each camera, and no
camera's view of the body is occluded by an object by more than the world metrics' ``CLEAR``.

    python -m benchmarks.experiments.world_pf_parts run OUT CONFIG SEQ_FOLDER... [--seed 0]
    python -m benchmarks.experiments.world_pf_parts report OUT [--md X.md --json X.json]

``CONFIG``: ``base`` (the ``jaxmocap`` configuration of ``world_pf.toml``: the capture's
colours from scribbles, blob plausibility, hand swap) or ``parts`` (the same with the
per-part colours and the seeded search, ``make_params(part_colours=True)``: parts searched
where the blob line missed them) or ``parts-replace`` (the search's hands replace the blob
line's) or ``head`` (``base`` with the head as a fitted sphere, ``Images(head_sphere=True)``,
issue 39 item 2; ``docs/results/stereo_pf_round2.md``) or ``hands`` / ``hands-motion`` (``base``
with the hands gated by the filter's prediction, ``Images(hand_search=True)`` and the motion
map, issue 39 item 1; ``docs/results/stereo_pf_hands.md``) or ``learned`` (the learned
observation layer's parts, issue 50; ``docs/results/learned_pf.md``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

HAND_CM = 8.0  # issue 37: each hand within 8 cm
HEAD_CM = 4.0  # ... head within 4 cm
MIN_VISIBLE_PX = 6  # a part shows at least this many pixels in a camera to count as visible
CONFIGS = {
    "base": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True},
    "parts": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True,
              "part_colours": True},
    "head": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True,
             "head_sphere": True},
    "hands": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True,
              "hand_search": True},
    "hands-motion": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True,
                     "hand_search": True, "hand_motion": True},
    "parts-replace": {"skin": "scribbles", "plausible_blobs": True, "hand_swap": True,
                      "part_colours": True, "seed_replace": [False, True, True]},
    # the learned observation layer (issue 50): the sequence's body and shirt, the model
    # fine-tuned from the shipped "frame" model (jaxmocap learn --tracker pf)
    "learned": {"skin": "learned", "plausible_blobs": True, "hand_swap": True},
}


def visibility(seq, body) -> np.ndarray:
    """(T, 3) bool: head, left hand, right hand visible in both cameras (module docstring)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.camera import stack_cameras
    from jaxmocap.experiment.world_metrics import CLEAR
    from jaxmocap.trackers.stereo_pf import parts

    g = seq.groundtruth
    names = [str(n) for n in g["dof_names"]]
    if tuple(names) != tuple(body.chain.dof_names):
        raise ValueError("groundtruth dof_names differ from the body's")
    cams = stack_cameras(list(seq.cameras))
    scene = parts.part_scene(body)
    render = jax.jit(lambda q: parts.render_parts(scene, cams, q))
    out = []
    for t in range(g["q"].shape[0]):
        lab = np.asarray(render(jnp.asarray(g["q"][t], jnp.float32)))  # (2, h, w)
        px = np.stack([(lab == k + 1).sum(axis=(1, 2)) for k in range(3)])  # (3, 2)
        out.append((px >= MIN_VISIBLE_PX).all(axis=1))
    vis = np.asarray(out)
    clear = (np.asarray(g["occluded_fraction"]) <= CLEAR).all(axis=1)
    return vis & clear[:, None]


def pending(out: Path, config: str, folders: list[str], seed: int):
    """``(folder, dest, sequence)`` of each folder whose run ``CONFIG_SEQ_sSEED.npz`` is not in
    ``out`` yet (created)."""
    from jaxmocap.synth.dataset import load_dataset

    out.mkdir(parents=True, exist_ok=True)
    for folder in folders:
        dest = out / f"{config}_{Path(folder).name}_s{seed}.npz"
        if not dest.exists():
            yield folder, dest, load_dataset(folder)


def estimate_keypoints(path: Path):
    """A run file's ``(npz, body, groundtruth, its keypoint names, the estimate's keypoints
    (T, K, 3) over every frame, the body's keypoint names)``."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoints
    from jaxmocap.experiment.cell import _body

    z = np.load(path)
    folder = str(z["folder"])
    body = _body({"body": "sequence"}, folder)
    g = np.load(Path(folder) / "groundtruth.npz")
    q = np.asarray(z["q"])
    kp = np.asarray(jax.vmap(lambda x: keypoints(body, x))(jnp.asarray(np.nan_to_num(q))))
    return z, body, g, [str(n) for n in g["keypoint_names"]], kp, list(body.keypoint_names)


def run(out: Path, config: str, folders: list[str], seed: int) -> None:
    from jaxmocap.experiment.cell import _track_pf

    for folder, dest, seq in pending(out, config, folders, seed):
        cfg = {"name": config, "method": "pf", "body": "sequence", "garment": "sequence",
               "options": dict(CONFIGS[config])}
        t0 = time.perf_counter()
        res = _track_pf(seq, cfg, seed, folder)
        wall = time.perf_counter() - t0
        vis = visibility(seq, res["body"])
        np.savez(dest, q=res["q"], valid=res["valid"], times=res["times"],
                 points=res["blobs"][0], blob_valid=res["blobs"][1], visible=vis,
                 wall_s=wall, folder=str(folder))
        print(f"{dest.name}: {wall:.0f} s, {1e3 * res['times'][0]:.1f} ms/frame", flush=True)


def metrics(path: Path) -> dict:
    from jaxmocap.trackers.driver import PF_JOINTS

    z, _, g, gnames, kp, names = estimate_keypoints(path)
    row = {"file": path.name, "frames": int(kp.shape[0])}
    for k, (part, lim) in enumerate((("head", HEAD_CM), ("l_hand", HAND_CM),
                                     ("r_hand", HAND_CM))):
        e = 100 * np.linalg.norm(kp[:, names.index(part)] - g["keypoints"][:, gnames.index(part)],
                                 axis=-1)
        vis = z["visible"][:, k]
        bl = 100 * np.linalg.norm(z["points"][:, k] - g["keypoints"][:, gnames.index(part)],
                                  axis=-1)
        meas = z["blob_valid"][:, k] & vis
        row[part] = {"visible": int(vis.sum()), "within": float((e[vis] < lim).mean())
                     if vis.any() else None, "median_cm": float(np.median(e[vis]))
                     if vis.any() else None,
                     # the triangulated point handed to the filter (observation), same frames
                     "measured": float(meas.sum() / max(vis.sum(), 1)),
                     "measured_within": float(((bl < lim) & meas).sum() / max(vis.sum(), 1))}
    ip = [names.index(j) for j in PF_JOINTS]
    ig = [gnames.index(j) for j in PF_JOINTS]
    err = 100 * np.linalg.norm(kp[:, ip] - g["keypoints"][:, ig], axis=-1).mean(axis=1)
    row["mean_joint_cm"] = float(np.mean(err))
    # the cell's per-frame time (host line timed on its second pass); with part colours that
    # pass compiles its own filter step: timings come from pf_parts_timing.py instead
    row["cell_ms_per_frame"] = float(1e3 * np.median(z["times"]))
    return row


def report(out: Path, md: str | None, js: str | None) -> None:
    rows = [metrics(p) for p in sorted(out.glob("*.npz"))]

    def pct(v):
        return "-" if v is None else f"{100 * v:.0f}%"

    lines = ["| run | frames | head vis | head < 4 cm | L vis | L < 8 cm | R vis | R < 8 cm | "
             "head / L / R measured < lim | mean joint cm |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        h, lh, rh = r["head"], r["l_hand"], r["r_hand"]
        meas = " / ".join(pct(x["measured_within"]) for x in (h, lh, rh))
        lines.append(f"| {r['file'][:-4]} | {r['frames']} | {h['visible']} | {pct(h['within'])}"
                     f" | {lh['visible']} | {pct(lh['within'])} | {rh['visible']} | "
                     f"{pct(rh['within'])} | {meas} | {r['mean_joint_cm']:.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if md:
        Path(md).write_text(text)
    if js:
        Path(js).write_text(json.dumps(rows, indent=1) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("config", choices=sorted(CONFIGS))
    r.add_argument("folders", nargs="+")
    r.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("report")
    p.add_argument("out")
    p.add_argument("--md")
    p.add_argument("--json")
    a = ap.parse_args()
    if a.cmd == "run":
        run(Path(a.out), a.config, a.folders, a.seed)
    else:
        report(Path(a.out), a.md, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
