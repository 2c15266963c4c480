"""The colour-shirt tracker on a test-world sequence through the commands alone, as a new user
runs it (issue 17): scribbles on the capture's first frames -> ``jaxmocap colors --shading``,
the white balance and the room from frame 0 -> ``jaxmocap colors --white-balance
--room-label``, ``jaxmocap build-db --body --garment``, ``jaxmocap track --validity footage``
on the sequence's videos, then the error of the exported poses against the ground truth.

The scribbles are the ground truth's colour ids eroded as in the experiment
(``shirt.scribbles``; the frames of ``experiment.cell.scribble_frames``), the room label is the
non-shirt pixels of frame 0 eroded ``SCRIBBLE_EROSION + 2`` px away from the shirt. Tune on dev
sequences only.

    python -m benchmarks.experiments.world_cli /work/tw_dev_shirt/shirt_03 /tmp/cli_03 \
        [--db-size 80000]

Writes ``summary.json`` into the output folder: the share of frames exported as valid and the
mean per-joint error (cm) over issue 17's joints on them (NaN frames are the invalid ones).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

JOINTS = ("head", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist",
          "r_wrist", "l_hand", "r_hand")
ROOM_LABEL = 255


def _cli(*argv) -> None:
    cmd = [sys.executable, "-m", "jaxmocap.cli", *map(str, argv)]
    print("$ jaxmocap " + " ".join(map(str, argv[:6])) + (" ..." if len(argv) > 6 else ""),
          flush=True)
    subprocess.run(cmd, check=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("out")
    ap.add_argument("--db-size", type=int, default=80_000)
    ap.add_argument("--shading", nargs=2, type=float, default=(0.5, 4.0))
    args = ap.parse_args()
    from jaxmocap.body import load_body
    from jaxmocap.experiment.cell import scribble_frames
    from jaxmocap.io.garment_file import load_garment
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.synth.world.render import sequence_body_file
    from jaxmocap.trackers.shirt import SCRIBBLE_EROSION, scribbles

    seq_dir, out = Path(args.sequence), Path(args.out)
    if seq_dir.resolve() in out.resolve().parents or seq_dir.resolve() == out.resolve():
        ap.error(f"{args.out}: inside the sequence {args.sequence}; write elsewhere")
    out.mkdir(parents=True, exist_ok=False)  # never over an earlier run
    seq = load_dataset(seq_dir)
    body_file, body_kw = sequence_body_file(seq_dir)  # body.urdf, or a package's own file
    body = load_body(body_file, **body_kw)
    body_args = ["--body", body_file]
    if body_kw:  # a URDF in other units / up axis, as its package loads it
        body_args += ["--body-scale", body_kw["scale"], "--body-up", body_kw["up"]]
    garment = load_garment(seq_dir / "garment.json", body)
    cids = seq.groundtruth["colour_ids"]
    names = seq.camera_names
    scrib = out / "scribbles"
    scrib.mkdir()
    images, masks = [], []
    for t in scribble_frames(cids, garment.n_colours):
        for c, n in enumerate(names):
            img, lab = scrib / f"{n}_{t}.png", scrib / f"{n}_{t}_labels.png"
            cv2.imwrite(str(img), np.asarray(seq.frames[t, c])[..., ::-1])
            cv2.imwrite(str(lab), scribbles(np.asarray(cids[t, c])).astype(np.uint8))
            images.append(img)
            masks.append(lab)
    _cli("colors", "--images", *images, "--masks", *masks, *body_args,
         "--garment", seq_dir / "garment.json", "--shading", *args.shading,
         "--out", out / "colors.json")
    wb_img, wb_lab = [], []
    for c, n in enumerate(names):
        lab = scribbles(np.asarray(cids[0, c])).astype(np.uint8)
        room = scribbles((np.asarray(cids[0, c]) == 0).astype(np.int32), SCRIBBLE_EROSION + 2)
        lab[room > 0] = ROOM_LABEL
        wb_img.append(scrib / f"{n}_0.png")
        wb_lab.append(scrib / f"{n}_0_wb.png")
        cv2.imwrite(str(wb_lab[-1]), lab)
    _cli("colors", "--white-balance", "--colors", out / "colors.json", "--images", *wb_img,
         "--masks", *wb_lab, "--names", *names, "--room-label", ROOM_LABEL,
         "--out", out / "white_balance.json")
    _cli("build-db", *body_args, "--garment", seq_dir / "garment.json",
         "--size", args.db_size, "--out", out / "db.npz", "--quiet")
    _cli("track", "--cameras", seq_dir / "cameras.json",
         *[seq_dir / f"{n}.mp4" for n in names], *body_args,
         "--garment", seq_dir / "garment.json", "--colors", out / "colors.json",
         "--white-balance", out / "white_balance.json", "--db", out / "db.npz",
         "--validity", "footage", "--formats", "npz", "--out", out / "track", "--quiet")
    with np.load(out / "track" / "poses.npz") as z:
        kp, valid, kn = z["keypoints"], z["valid"], [str(s) for s in z["keypoint_names"]]
    g = seq.groundtruth
    gn = [str(s) for s in g["keypoint_names"]]
    ip, ig = [kn.index(j) for j in JOINTS], [gn.index(j) for j in JOINTS]
    err = np.linalg.norm(kp[:, ip] - g["keypoints"][:, ig], axis=-1).mean(axis=1) * 100
    summary = {"sequence": str(seq_dir), "frames": int(len(valid)),
               "valid_fraction": float(valid.mean()),
               "mean_cm_valid": float(np.mean(err[valid])) if valid.any() else None,
               "joints": list(JOINTS), "db_size": args.db_size}
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
