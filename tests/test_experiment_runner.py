"""``jaxmocap experiment``: a local Dask cluster gives the sequential numbers, a killed
worker's cell is retried, finished cells are not recomputed, bad configurations fail in one
line before any work.

Two tiny stereo sequences (64x48, 3 frames) rendered by ``jaxmocap synth``; two particle-filter
configurations that differ in a traced cue width (one compilation per process)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import cloudpickle
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.body import default_body, keypoints
from jaxmocap.cli import main
from jaxmocap.experiment.config import ExperimentError, load_config
from jaxmocap.experiment.runner import run_experiment

CLIPS = ("humanoid3d_punch", "humanoid3d_dance_b")
CONFIG = """
[experiment]
good_cm = 5.0
bad_cm = 15.0

[[config]]
name = "pf-a"
method = "pf"
seeds = [0]
[config.options]
particles = 32
sigma_g = {sigma_a}

[[config]]
name = "pf-b"
method = "pf"
seeds = [1]
[config.options]
particles = 32
sigma_g = 2.0
"""


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("stereo")
    for clip in CLIPS:
        assert main(["synth", str(root / clip), "--clip", clip, "--preset", "stereo",
                     "--garment", "single", "--background", "plain", "--frames", "3",
                     "--width", "64", "--height", "48", "--png", "--no-video",
                     "--no-colour-ids", "--quiet", "--seed", "0"]) == 0
    return root


def write_config(folder: Path, sigma_a: float = 1.0) -> Path:
    path = folder / "configs.toml"
    path.write_text(CONFIG.format(sigma_a=sigma_a))
    return path


def cells(out: Path) -> dict[str, dict]:
    return {c["cell"]: c for c in json.loads((out / "summary.json").read_text())["cells"]}


CALLS: list[str] = []


def counting_cell(spec: dict) -> dict:
    from jaxmocap.experiment.cell import compute_cell

    CALLS.append(spec["cell"])
    return compute_cell(spec)


def crash_once_cell(spec: dict) -> dict:
    """The worker process dies (os._exit) on its first attempt at one cell; a marker file
    records that attempt. Pickled by value (the workers do not import this module)."""
    from jaxmocap.experiment.cell import compute_cell

    marker = Path(spec["folder"]).parent.parent / f"crashed-{spec['cell']}"
    if spec["cell"].startswith(CLIPS[0]) and spec["config"]["name"] == "pf-b" \
            and not marker.exists():
        marker.write_text(str(os.getpid()))
        os._exit(3)
    return compute_cell(spec)


@pytest.fixture(scope="module")
def sequential(dataset, tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("seq")
    out = folder / "out"
    CALLS.clear()
    res = run_experiment(dataset, write_config(folder), out, workers=0, progress=False,
                         cell_fn=counting_cell)
    assert res["run"]["computed"] == 4 and res["run"]["failed"] == 0
    assert sorted(CALLS) == sorted(cells(out))
    return out


def test_cells_metrics_and_summary(sequential, dataset):
    got = cells(sequential)
    assert sorted(got) == sorted(f"{c}__{k}" for c in CLIPS for k in ("pf-a__0", "pf-b__1"))
    for name, c in got.items():
        m = c["metrics"]
        d = np.load(sequential / "cells" / name / "poses.npz")
        gt = np.load(dataset / c["sequence"] / "groundtruth.npz")
        # the per-frame error stored with the poses, recomputed from the keypoints
        names = list(d["keypoint_names"])
        joints = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")
        ip = [names.index(j) for j in joints]
        ig = [list(gt["keypoint_names"]).index(j) for j in joints]
        # (every frame's estimate is in the exported keypoints, valid or not: the error of
        # every frame is the raw estimate's, q_raw)
        kp = np.asarray(jax.vmap(lambda x: keypoints(default_body(), x))(
            jnp.asarray(d["q_raw"])))
        v = d["valid"]
        est = np.isfinite(d["q_raw"]).all(axis=1)
        np.testing.assert_allclose(d["keypoints"][est], kp[est], atol=1e-5)
        assert np.isnan(d["keypoints"][~est]).all() and not v[~est].any()
        err = 100 * np.linalg.norm(kp[:, ip] - gt["keypoints"][:, ig], axis=-1)
        np.testing.assert_allclose(d["error_cm"], err.mean(1), rtol=1e-5)
        np.testing.assert_allclose(m["mean_error_all_frames_cm"], err.mean(), rtol=1e-6)
        # the split along the line of sight from the cameras' mean centre (-R^T t) and across
        cams = json.loads((dataset / c["sequence"] / "cameras.json").read_text())["cameras"]
        origin = np.mean([-np.asarray(k["R"]).T @ np.asarray(k["t"]) for k in cams], axis=0)
        e = kp[:, ip] - gt["keypoints"][:, ig]
        u = gt["keypoints"][:, ig] - origin
        u /= np.linalg.norm(u, axis=-1, keepdims=True)
        along = np.einsum("tjk,tjk->tj", e, u)
        across = np.linalg.norm(np.cross(e, u), axis=-1)  # |e x u| = the lateral part
        np.testing.assert_allclose(m["depth_error_cm"], 100 * np.abs(along).mean(), rtol=1e-5)
        np.testing.assert_allclose(m["lateral_error_cm"], 100 * across.mean(), rtol=1e-5)
        if v.any():
            np.testing.assert_allclose(m["mpjpe_cm"],
                                       np.mean(list(m["per_joint_cm"].values())))
        else:  # no frame reported valid (64x48 views: no triangulated hands): no MPJPE
            assert m["mpjpe_cm"] is None and m["per_joint_cm"] is None
        assert m["frames"] == 3 and m["ms_per_frame"] > 0
        bad = err.mean(1) > 15.0
        v = m["validity"]
        assert v["frames_bad"] == int(bad.sum())
        assert v["bad_flagged_invalid"] == (None if not bad.any() else
                                            float(np.mean(~d["valid"][bad])))
        assert (sequential / "cells" / name / "diagnostics.csv").read_text().startswith(
            "frame,valid,ess")
    md = (sequential / "summary.md").read_text()
    assert "| **all** | pf-a |" in md and (sequential / "summary.png").stat().st_size > 1000
    assert "| depth cm | lateral cm |" in md
    assert "| mean cm (all frames) | seeds' spread cm |" in md  # one seed per config here: -
    # every cell says what its filter started from (64x48 views: no head is triangulated)
    anchors = {c["start_anchor"] for c in got.values()}
    assert anchors <= {"head", "shirt", "hands", "none"} and "Stereo filter started from" in md


def test_resume_skips_finished_cells_and_reruns_a_changed_config(sequential, dataset):
    cfg = sequential.parent / "configs.toml"
    CALLS.clear()
    res = run_experiment(dataset, cfg, sequential, workers=0, progress=False,
                         cell_fn=counting_cell)
    assert CALLS == [] and res["run"]["reused"] == 4
    # a changed option changes the configuration's hash: only its cells run again
    write_config(sequential.parent, sigma_a=1.5)
    res = run_experiment(dataset, cfg, sequential, workers=0, progress=False,
                         cell_fn=counting_cell)
    assert sorted(CALLS) == sorted(f"{c}__pf-a__0" for c in CLIPS)
    assert res["run"]["computed"] == 2 and res["run"]["reused"] == 2
    write_config(sequential.parent)  # back as the other tests expect
    CALLS.clear()
    run_experiment(dataset, cfg, sequential, workers=0, progress=False, cell_fn=counting_cell)
    assert len(CALLS) == 2
    # a configuration that fails in every cell: reported in the summary, the run goes on
    cfg.write_text(cfg.read_text() + "\n[[config]]\nname = 'broken'\nmethod = 'pf'\n"
                   "[config.options]\nguided_fraction = 2.0\n")
    assert main(["experiment", str(dataset), str(cfg), "--out", str(sequential),
                 "--workers", "0", "--quiet"]) == 1
    doc = json.loads((sequential / "summary.json").read_text())
    assert doc["run"]["failed"] == 2 and doc["run"]["reused"] == 4
    errors = [c["error"] for c in doc["cells"] if "error" in c]
    assert len(errors) == 2 and all("guided_fraction: expected in [0, 1]" in e for e in errors)
    assert "## Failed cells" in (sequential / "summary.md").read_text()
    assert not any(p.name.endswith("__broken__0") for p in (sequential / "cells").iterdir())
    write_config(sequential.parent)


def test_dask_cluster_equals_sequential_and_retries_a_killed_worker(sequential, dataset,
                                                                    tmp_path):
    from jaxmocap.experiment.cluster import local_cluster

    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    out = tmp_path / "dask"
    # the workers get this process's XLA flags so that they read its compilation cache; the
    # experiment reaches them through the scheduler's address, as --scheduler does
    env = {"XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    with local_cluster(2, env=env) as cluster:
        res = run_experiment(dataset, sequential.parent / "configs.toml", out,
                             scheduler=cluster.scheduler_address, progress=False,
                             cell_fn=crash_once_cell, retries=0)
    crashed = list(dataset.parent.glob("crashed-*"))
    assert [p.name for p in crashed] == [f"crashed-{CLIPS[0]}__pf-b__1"]
    assert res["run"]["computed"] == 4 and res["run"]["failed"] == 0
    a, b = cells(sequential), cells(out)
    assert len(b) == 4
    for name in b:
        ma, mb = a[name]["metrics"], b[name]["metrics"]
        for k in ("mpjpe_cm", "mean_error_all_frames_cm", "per_joint_cm", "validity",
                  "frames_below_good_cm", "frames_valid"):
            assert ma[k] == mb[k], (name, k)
        pa = np.load(sequential / "cells" / name / "poses.npz")
        pb = np.load(out / "cells" / name / "poses.npz")
        np.testing.assert_array_equal(pa["q_raw"], pb["q_raw"])


def test_worker_environment_holds_threads_to_one():
    from jaxmocap.experiment.cluster import worker_env

    env = worker_env()
    assert "--xla_cpu_multi_thread_eigen=false" in env["XLA_FLAGS"]
    assert env["OMP_NUM_THREADS"] == "1" and env["JAXMOCAP_CACHE_DIR"]


@pytest.mark.parametrize("text, expect", [
    ("[[config]]\nname='a'\nmethod='mlp'\n", "config 'a'.method: expected one of"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nparticle=3\n",
     "unknown option 'particle'"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nguided=3\n",
     "options.guided: expected a value like True"),
    ("[[config]]\nname='a'\nmethod='shirt'\n[config.options]\ncovariances='no.npz'\n",
     "options.covariances: no such file"),
    ("[[config]]\nname='a'\nmethod='pf'\nseeds=[0, 0]\n", "seeds: expected a list of distinct"),
    ("[[config]]\nname='a'\nmethod='pf'\n[[config]]\nname='a'\nmethod='pf'\n", "used twice"),
    ("[[config]]\nname='a b'\nmethod='pf'\n", ".name: expected a name"),
    ("[[config]]\nname='a'\nmethod='pf'\ngarment='configs.toml'\n", "takes no garment"),
    ("[[config]]\nname='a'\nmethod='pf'\njoints=['l_knee']\n", "not keypoints of the bundled"),
    ("config = 3\n", "config: expected a non-empty list"),
    ("[experiment]\ngood_cm = 20\n[[config]]\nname='a'\nmethod='pf'\n", "good_cm 20 > bad_cm"),
    ("[[config]\n", "not valid TOML"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nadapt_colors=true\n",
     "options.adapt_colors: adapts the capture's colours"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nsearch='hand'\n",
     "options.search: expected one of off, head, hands, all"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nsearch='all'\n",
     "options.search: searches with the capture's colours"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\nskin_grow='4'\n",
     "options.skin_grow: expected a value like 0"),
    ("[[config]]\nname='a'\nmethod='shirt'\n[config.options]\ntuned='t.json'\n"
     "covariances='isotropic'\n", "or covariances, not both"),
    ("[[config]]\nname='a'\nmethod='pf'\n[config.options]\ntuned='no.json'\n",
     "options.tuned: no such file"),
])
def test_bad_configs_fail_in_one_line(tmp_path, text, expect):
    path = tmp_path / "configs.toml"
    path.write_text(text)
    with pytest.raises(ExperimentError, match=expect.replace("[", r"\[").replace(".", r"\.")) \
            as e:
        load_config(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_cli_refuses_bad_inputs_before_any_work(dataset, tmp_path, capsys):
    cfg = write_config(tmp_path)
    out = tmp_path / "out"
    assert main(["experiment", str(tmp_path / "nothing"), str(cfg), "--out", str(out)]) == 2
    assert "not a dataset folder" in capsys.readouterr().err
    split = tmp_path / "split.json"
    split.write_text(json.dumps({"dev": [CLIPS[0]], "test": ["missing"]}))
    for extra, msg in ((["--split", str(split)], "choose one with --subset"),
                       (["--split", str(split), "--subset", "test"], "'missing'"),
                       (["--subset", "dev"], "--subset needs --split"),
                       (["--workers", "1", "--scheduler", "tcp://x:1"], "not both")):
        assert main(["experiment", str(dataset), str(cfg), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1, err
    assert not out.exists()
    # a shirt configuration needs colour ids (or colour files) in every sequence
    shirt = tmp_path / "shirt.toml"
    shirt.write_text("[[config]]\nname='s'\nmethod='shirt'\n")
    assert main(["experiment", str(dataset), str(shirt), "--out", str(out)]) == 2
    assert "has no colour_ids" in capsys.readouterr().err and not out.exists()


def test_a_tuned_file_of_another_body_is_refused_before_any_cell(dataset, tmp_path, capsys):
    """Option ``tuned``: the file's digests are checked against every configuration's body
    before any cell runs (exit code 2, one line naming the file and the field)."""
    from jaxmocap.body import default_body
    from jaxmocap.tuned import TunedParameters

    TunedParameters("pf", {"sigma_g": 0.3, "sigma_d": 0.05}, "0123456789abcdef").save(
        tmp_path / "t.json")
    cfg = tmp_path / "tuned.toml"
    cfg.write_text("[[config]]\nname='t'\nmethod='pf'\n[config.options]\nparticles=32\n"
                   "tuned='t.json'\n")
    out = tmp_path / "out"
    assert main(["experiment", str(dataset), str(cfg), "--out", str(out), "--workers", "0",
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "t.json: field 'body_digest' is 0123456789abcdef" in err and err.count("\n") == 1
    assert not out.exists()
    from jaxmocap.body import body_digest

    TunedParameters("pf", {"sigma_g": 0.3, "sigma_d": 0.05},
                    body_digest(default_body())).save(tmp_path / "t.json")
    TunedParameters.load(tmp_path / "t.json").check_for("pf", default_body())  # passes


def test_affinity_deals_configurations_to_workers_in_turn():
    from jaxmocap.experiment.cluster import affinity

    specs = [{"config": {"name": n}} for n in ("b", "a", "b", "c", "a", "c")]
    assert affinity(specs, ["tcp://w2", "tcp://w1"]) == {"b": "tcp://w1", "a": "tcp://w2",
                                                         "c": "tcp://w1"}
    assert affinity(specs, []) == {}


def test_flat_options_map_onto_the_settings_groups():
    """A configuration's tracker options keep their flat names; each lands on its settings
    group of make_params (over Azad's groups with ``azad``)."""
    from jaxmocap.experiment.config import tracker_settings
    from jaxmocap.trackers import shirt
    from jaxmocap.trackers import stereo_pf as sp

    kw = tracker_settings("shirt", {"pose_prior": False, "ik_passes": 3,
                                    "shading": [0.5, 4.0], "min_agreement": 0.2})
    assert kw["ablations"] == shirt.Ablations(pose_prior=False)
    assert kw["rounds"].ik_passes == 3 and kw["colours"].shading == (0.5, 4.0)
    assert float(kw["validity"].min_agreement) == pytest.approx(0.2)
    kw = tracker_settings("pf", {"n_particles": 10, "use_support": True}, dict(sp.AZAD_FILTER))
    assert kw["motion"].n_particles == 10
    assert kw["cues"].use_support and kw["cues"].edge_outside is None
    assert kw["proposals"] == sp.AZAD_FILTER["proposals"]


def test_seed_spread_is_the_min_max_of_the_seeds_means():
    """summary.aggregate: per seed the mean over its sequences, then min and max over the
    seeds (issue 39 decision 6: the spread of a sequence is part of the result)."""
    from jaxmocap.experiment.summary import _spread, aggregate

    def cell(seq, seed, cm):
        return {"sequence": seq, "seed": seed, "metrics": {
            "mean_error_all_frames_cm": cm, "frames": 3, "frames_valid": 1}}

    cells = [cell("a", 0, 10.0), cell("a", 1, 14.0), cell("a", 2, 11.0),
             cell("b", 0, 20.0), cell("b", 1, 16.0), cell("b", 2, 30.0)]
    one = aggregate(cells[:3])
    assert one["seed_range_cm"] == (10.0, 14.0) and _spread(one) == "10.00-14.00 (3)"
    both = aggregate(cells)  # seed means 15, 15, 20.5
    assert both["seed_range_cm"] == (15.0, 20.5) and both["seeds"] == 3
    assert _spread(aggregate(cells[:1])) == "-"
