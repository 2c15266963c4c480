"""Development harness for the colour-shirt tracker (diagnostic, small scale).

Tracks rendered sequences with given covariances / flags and prints per-frame shirt-joint
errors, so that a change to ``jaxmocap/trackers/shirt/`` can be measured on both held-out
clips and on the recovery sequence without the whole of ``wang_accuracy.py``. Rendered
sequences and trained covariances are cached under ``/tmp/wang_dev``.

    python benchmarks/experiments/wang_dev.py train CLIP[,CLIP...] NAME
    python benchmarks/experiments/wang_dev.py eval COVNAME|iso [flag=value ...]
    python benchmarks/experiments/wang_dev.py recovery COVNAME|iso [flag=value ...]
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import wang_accuracy as wa  # noqa: E402

from jaxmocap.body import default_body, keypoints  # noqa: E402
from jaxmocap.garment import default_garment  # noqa: E402
from jaxmocap.ik import IKCovariances  # noqa: E402
from jaxmocap.posedb import SamplingConfig, load_or_build, sample_poses, source_pool  # noqa: E402
from jaxmocap.synth import HELDOUT_CLIPS, TRAIN_CLIPS, SceneConfig, render_sequence  # noqa: E402
from jaxmocap.trackers import shirt  # noqa: E402

CACHE = Path("/tmp/wang_dev")
CACHE.mkdir(exist_ok=True)
DB_SIZE = int(os.environ.get("WANG_DEV_DB", 3000))  # 80000: the full-scale database
N_FRAMES = 20
DIAG = False


def _seq(cfg: SceneConfig):
    key = CACHE / f"seq_{hashlib.sha1(repr(cfg).encode()).hexdigest()[:16]}.pkl"
    if key.exists():
        return pickle.loads(key.read_bytes())
    seq = render_sequence(cfg, jnp.float32)
    key.write_bytes(pickle.dumps(seq))
    return seq


def _base():
    model = default_body()
    garment = default_garment(model)
    db = load_or_build(SamplingConfig(size=DB_SIZE), model, garment, progress=False)
    pool = source_pool(model, TRAIN_CLIPS)
    poses = sample_poses(SamplingConfig(size=5, seed=3, yaw_range=0.3), model, pool)
    poses[:, 2] = 0.85
    train = _seq(wa._scene("humanoid3d_dance_a", N_FRAMES, 2, False))
    color = shirt.fit_color_model_from_renders(model, garment, poses, train.cameras[0])
    return model, garment, db, color


def _cov(name, model):
    if name == "iso":
        return IKCovariances.isotropic(2.0, 0.3, 0.5, model.n_dof)
    if name == "committed":
        return shirt.trained_covariances()
    return IKCovariances.load(CACHE / f"cov_{name}.npz")


def _flags(args):
    out = {}
    for a in args:
        k, v = a.split("=")
        out[k] = (
            {"True": True, "False": False, "None": None}.get(v, None)
            if v in ("True", "False", "None")
            else (float(v) if "." in v else int(v))
        )
    return out


def main(argv):
    global DIAG
    if argv[0] == "diag":
        DIAG, argv = True, ["recovery"] + argv[1:]
    model, garment, db, color = _base()
    kp = jax.jit(jax.vmap(lambda q: keypoints(model, q)))
    sidx = [model.keypoint_names.index(n) for n in wa.SHIRT_JOINTS]
    cmd = argv[0]
    if cmd == "full":  # train every "name:clip,clip" set, then eval + recovery with each
        names = ["iso"]
        for spec in argv[1].split("|"):
            name, clips = spec.split(":")
            _train(clips.split(","), name, argv[2:], model, garment, db, color, kp, sidx)
            names.append(name)
        for c in ("eval", "recovery"):
            for cname in names:
                _evaluate(c, cname, argv[2:], model, garment, db, color, kp, sidx)
        return
    for c in ("eval", "recovery") if cmd == "both" else (cmd,):
        for cname in argv[1].split(","):
            _evaluate(c, cname, argv[2:], model, garment, db, color, kp, sidx)


def _train(clips, name, fargs, model, garment, db, color, kp, sidx):
    iso = _cov("iso", model)
    runs = []
    for clip in clips:
        seq = _seq(wa._scene(clip, N_FRAMES, 2, False))
        params, state = wa._setup(seq, model, garment, db, iso, color, **_flags(fargs))
        out, wall = wa._track(params, state, seq.frames)
        e = np.linalg.norm(np.asarray(kp(out.q)) - seq.groundtruth["keypoints"], axis=-1)
        print(clip, f"iso {100 * e.mean():.2f} / {100 * e[:, sidx].mean():.2f}", flush=True)
        runs.append((params, seq, out))
    cov = wa.train_covariances(model, runs)
    cov.save(CACHE / f"cov_{name}.npz")
    print(name, "sb", np.sqrt(wa._variances(cov.blend)).round(2).tolist())
    print(name, "sp", np.sqrt(wa._variances(cov.prior)).round(2).tolist(), flush=True)


def _evaluate(cmd, cname, fargs, model, garment, db, color, kp, sidx):
    cov = _cov(cname, model)
    flags = _flags(fargs)
    if cmd == "eval":
        for clip in HELDOUT_CLIPS[:2]:
            seq = _seq(wa._scene(clip, N_FRAMES, 2, True))
            params, state = wa._setup(seq, model, garment, db, cov, color, **flags)
            out, wall = wa._track(params, state, seq.frames)
            e = np.linalg.norm(np.asarray(kp(out.q)) - seq.groundtruth["keypoints"], axis=-1)
            print(json.dumps({"clip": clip, "cov": cname, "flags": fargs,
                              "all": round(float(100 * e.mean()), 2),
                              "shirt": round(float(100 * e[:, sidx].mean()), 2),
                              "frames": (100 * e[:, sidx].mean(1)).round(1).tolist(),
                              "valid": int(np.asarray(out.valid).sum()), "wall": round(wall)}),
                  flush=True)  # fmt: skip
    elif cmd == "recovery":
        n_rec, leave = wa.SCALES["small"]["recovery"]
        cfg = SceneConfig(clip=HELDOUT_CLIPS[0], n_frames=n_rec, n_cameras=2, width=320,
                          height=240, background="clutter", noise_sigma=0.01, seed=2,
                          leave_view=leave)  # fmt: skip
        seq = _seq(cfg)
        params, state = wa._setup(seq, model, garment, db, cov, color, **flags)
        out, wall = wa._track(params, state, seq.frames)
        err = 100 * np.linalg.norm(np.asarray(kp(out.q)) - seq.groundtruth["keypoints"], axis=-1)
        r = wa._recovery(err[:, sidx].mean(1), np.asarray(seq.groundtruth["body_pixels"]),
                         np.asarray(out.valid))  # fmt: skip
        r["valid"] = "".join("1" if v else "0" for v in r["valid"])
        if DIAG:
            e = np.linalg.norm(np.asarray(kp(out.q)) - seq.groundtruth["keypoints"], axis=-1)
            eb = np.linalg.norm(np.asarray(kp(out.q_blend)) - seq.groundtruth["keypoints"], axis=-1)
            bp = np.asarray(seq.groundtruth["body_pixels"])
            for t in range(26, n_rec):
                print(
                    t,
                    int(out.valid[t]),
                    f"agr {float(out.agreement[t]):.2f}",
                    f"blend {100 * eb[t][sidx].mean():.1f}",
                    "frac",
                    np.asarray(out.fraction[t]).round(2).tolist(),
                    "px",
                    bp[t].tolist(),
                    "vis",
                    int(np.asarray(out.visible[t]).sum()),
                    dict(zip(wa.SHIRT_JOINTS, (100 * e[t][sidx]).round(1).tolist(), strict=True)),
                )
        print(json.dumps(r | {"cov": cname, "flags": fargs, "wall": round(wall)}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
