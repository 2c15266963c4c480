"""Tests of the pose database (Wang et al. 2011 §5.2, Step 2).

Oracles: a NumPy brute-force k-NN on the raw maps (``np.lexsort``), the ray caster's own
renders, the body model's keypoints (mirror symmetry, camera frames), SciPy's rotation mean.
One small database (2,000 poses) is built on the first run and cached in the jaxmocap cache
folder (``test-posedb``), like JAX's compilation cache: later runs load it (its key covers the
settings and the renderer's source; the build test re-renders a few poses against it).
"""

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxmocap import posedb
from jaxmocap.body import default_body, keypoint_index, keypoints
from jaxmocap.camera import look_at, to_camera
from jaxmocap.cli import SUBCOMMANDS
from jaxmocap.commands import build_db as build_db_command
from jaxmocap.errors import InputError
from jaxmocap.garment import default_garment, single_colour_garment
from jaxmocap.posedb import _build
from jaxmocap.synth import HELDOUT_CLIPS, TRAIN_CLIPS

DB_SIZE = 2000
N_QUERIES = 48
CONFIG = posedb.SamplingConfig(size=DB_SIZE, seed=3)


@pytest.fixture(scope="module")
def cache():
    from jaxmocap._config import cache_dir

    return cache_dir() / "test-posedb"


@pytest.fixture(scope="module")
def db(cache):
    return posedb.load_or_build(CONFIG, cache=cache, progress=False)


@pytest.fixture(scope="module")
def maps(db):
    return posedb.unpack_codes(db)


@pytest.fixture(scope="module")
def heldout():
    """Held-out poses (punch, dance_b, left turns) at random orientations, rendered by the
    canonical camera, then corrupted: 3% of pixels set to a random id, shifted by <= 1 px."""
    model = default_body()
    pool = posedb.source_pool(model, HELDOUT_CLIPS)
    cfg = posedb.SamplingConfig(size=N_QUERIES, seed=11, p_real=1.0, joint_noise=0.0,
                                clips=HELDOUT_CLIPS)
    poses = posedb.sample_poses(cfg, model, pool)
    clean = posedb.render_maps(model, default_garment(model), poses, progress=False)
    rng = np.random.default_rng(5)
    noisy = clean.copy()
    flip = rng.uniform(size=noisy.shape) < 0.03
    noisy[flip] = rng.integers(0, 11, flip.sum())
    for i in range(len(noisy)):
        noisy[i] = np.roll(noisy[i], tuple(rng.integers(-1, 2, 2)), axis=(0, 1))
    return poses, clean, noisy


def reference_knn(maps, query, k=10):
    """NumPy oracle: the distance of the posedb docstring on raw maps, stable order."""
    a = maps.reshape(len(maps), -1).astype(np.int16)
    q = query.reshape(-1).astype(np.int16)
    fg_a, fg_q = a > 0, q > 0
    d = ((a != q) & fg_a & fg_q).sum(1) + 0.5 * (fg_a != fg_q).sum(1)
    order = np.lexsort((np.arange(len(d)), d))[:k]
    return order, d[order]


BATCH = 16  # every batched query uses this shape: one compilation per function


def _vmapped(fn, **kw):
    return jax.jit(jax.vmap(lambda db, t: fn(db, t, **kw), in_axes=(None, 0)))


EXACT = _vmapped(posedb.query_exact)
FAST = _vmapped(posedb.query_fast, candidates=100)
ESTIMATE = _vmapped(posedb.estimate_pose)
KEYPOINTS = jax.jit(jax.vmap(lambda q: keypoints(default_body(), q)))


def batched(fn, db, tinies):
    """``fn`` over the queries in batches of ``BATCH`` (the last one padded)."""
    tinies = np.asarray(tinies)
    n = len(tinies)
    pad = np.concatenate([tinies, np.repeat(tinies[-1:], -n % BATCH, axis=0)])
    outs = [fn(db, jnp.asarray(pad[s:s + BATCH])) for s in range(0, len(pad), BATCH)]
    return jax.tree.map(lambda *a: np.concatenate(a)[:n], *outs)


# ----------------------------------------------------------------------------- building


def test_build_cached_deterministic_and_versioned(db, maps, cache, monkeypatch):
    model, garment = default_body(), default_garment()
    assert db.size == DB_SIZE and maps.shape == (DB_SIZE, 40, 40) and maps.dtype == np.uint8
    assert maps.max() <= garment.n_colours and 0.15 < (maps > 0).mean() < 0.6
    key = posedb.database_key(CONFIG, model, garment)
    path = posedb.cache_path(key, cache)
    assert db.key == key and path.exists()
    with np.load(path) as f:
        np.testing.assert_array_equal(f["maps"], maps)  # codes round-trip to the maps
        assert json.loads(str(f["meta"]))["config"]["size"] == DB_SIZE

    def no_build(*a, **k):
        raise AssertionError("the second call must load the cache, not build")

    monkeypatch.setattr(_build, "build_arrays", no_build)
    again = posedb.load_or_build(CONFIG, cache=cache, progress=False)
    np.testing.assert_array_equal(np.asarray(again.codes), np.asarray(db.codes))
    np.testing.assert_array_equal(np.asarray(again.poses), np.asarray(db.poses))
    monkeypatch.undo()
    # any setting that changes the content changes the key; the default clips are TRAIN_CLIPS
    keys = {key, posedb.database_key(CONFIG._replace(seed=4), model, garment),
            posedb.database_key(CONFIG._replace(size=DB_SIZE + 1), model, garment),
            posedb.database_key(CONFIG._replace(yaw_range=1.0), model, garment),
            posedb.database_key(CONFIG, model, single_colour_garment(model, (0.8, 0.1, 0.1)))}
    assert len(keys) == 5
    assert key == posedb.database_key(CONFIG._replace(clips=TRAIN_CLIPS), model, garment)
    # building is deterministic: the same poses, and the same maps when rendered again
    pool = posedb.source_pool(model, TRAIN_CLIPS)
    np.testing.assert_array_equal(posedb.sample_poses(CONFIG, model, pool), np.asarray(db.poses))
    again = posedb.render_maps(model, garment, np.asarray(db.poses[:40]), progress=False)
    np.testing.assert_array_equal(again, maps[:40])


def test_sampling_and_mirror():
    model = default_body()
    pool = posedb.source_pool(model, TRAIN_CLIPS)
    cfg = posedb.SamplingConfig(size=300, seed=1)
    q = posedb.sample_poses(cfg, model, pool)
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    assert np.all(q[:, 6:] >= lo[6:] - 1e-6) and np.all(q[:, 6:] <= hi[6:] + 1e-6)
    assert np.all(q[:, :3] == 0)
    # camera-relative orientation: yaw all around, small pitch/roll (ZYX Euler, SciPy)
    ypr = Rotation.from_rotvec(q[:, 3:6].astype(np.float64)).as_euler("ZYX")
    assert ypr[:, 0].min() < -2.8 and ypr[:, 0].max() > 2.8
    assert np.abs(ypr[:, 1]).max() <= cfg.pitch_range + 1e-5
    assert np.abs(ypr[:, 2]).max() <= cfg.roll_range + 1e-5
    # real frames only, no mirror, no jitter: every pose's joints are a pool frame's
    real = posedb.sample_poses(cfg._replace(p_real=1.0, p_mirror=0.0, joint_noise=0.0),
                               model, pool)
    gap = np.abs(real[:, None, 6:] - pool[None, :, 6:]).max(-1).min(-1)
    assert gap.max() < 1e-6
    # the mirror reflects keypoints in the sagittal plane y -> -y, swapping l_ and r_
    mirror = posedb.mirror_table(model)
    qj = jnp.asarray(q[:20].astype(np.float64)).at[:, :3].set(jnp.asarray([0.1, 0.2, 0.9]))
    kp = np.asarray(KEYPOINTS(qj))
    kpm = np.asarray(KEYPOINTS(posedb.mirror_pose(mirror, qj)))
    names = model.keypoint_names
    swap = keypoint_index(model, [n.replace("l_", "#").replace("r_", "l_").replace("#", "r_")
                                  for n in names])
    np.testing.assert_allclose(kpm, kp[:, swap] * np.array([1.0, -1.0, 1.0]), atol=1e-9)
    np.testing.assert_allclose(posedb.mirror_pose(mirror, posedb.mirror_pose(mirror, qj)), qj)
    with pytest.raises(InputError, match="size"):
        posedb.SamplingConfig(size=0).validate()
    with pytest.raises(InputError, match="clips"):
        posedb.source_pool(model, ("no_such_clip",))


# ----------------------------------------------------------------------------- search


def test_exact_search_equals_numpy(db, maps, heldout):
    _, _, noisy = heldout
    queries = np.concatenate([maps[[0, 7, 1999]], noisy[:13]])
    got = batched(EXACT, db, queries)
    for i, q in enumerate(queries):
        idx, dist = reference_knn(maps, q)
        np.testing.assert_array_equal(np.asarray(got.index[i]), idx)
        np.testing.assert_array_equal(np.asarray(got.distance[i]), dist)
    # the distance on maps, directly (float32 distance of pixel counts)
    d = posedb.map_distance(jnp.asarray(queries[3]), jnp.asarray(maps[5]))
    assert float(d) == reference_knn(maps[5:6], queries[3], 1)[1][0]
    # jit and plain calls, chunked layout (several chunks, padding) give the same neighbours
    small = posedb.make_posedb(maps[:700], np.asarray(db.poses[:700]), 10, chunk=256)
    assert small.codes.shape == (3, 252, 256)
    np.testing.assert_array_equal(posedb.unpack_codes(small), maps[:700])
    nb = posedb.query_exact(small, jnp.asarray(queries[4]), k=12)
    idx, dist = reference_knn(maps[:700], queries[4], 12)
    np.testing.assert_array_equal(np.asarray(nb.index), idx)
    np.testing.assert_array_equal(np.asarray(nb.distance), dist)


def test_fast_search_agrees_with_exact(db, heldout):
    _, clean, noisy = heldout
    queries = np.concatenate([clean, noisy])
    exact = batched(EXACT, db, queries)
    # first stage on the quarter-resolution grid, 100 candidates of 2,000 re-ranked exactly
    fast = batched(FAST, db, queries)
    same = np.all(np.asarray(exact.index) == np.asarray(fast.index), axis=1)
    assert same.mean() >= 0.99
    np.testing.assert_array_equal(np.asarray(exact.distance)[same], np.asarray(fast.distance)[same])


def test_member_query_returns_itself(db, maps):
    members = np.array([3, 250, 1024, 1999])
    unique = [i for i in members if np.sum(np.all(maps == maps[i], axis=(1, 2))) == 1]
    assert len(unique) >= 3
    for fn in (EXACT, FAST):
        nb = batched(fn, db, maps[unique])
        np.testing.assert_array_equal(np.asarray(nb.index[:, 0]), unique)
        np.testing.assert_array_equal(np.asarray(nb.distance[:, 0]), 0.0)
        assert np.all(np.asarray(nb.distance[:, 1]) > 0)


# ----------------------------------------------------------------------------- blend


def test_blend(db, maps):
    q = np.asarray(db.poses[123], np.float64)
    same = posedb.blend_poses(jnp.asarray(np.tile(q, (10, 1))), jnp.arange(10.0))
    np.testing.assert_allclose(same, q, atol=1e-12)
    # two poses at equal distance: joints average, root rotation at the geodesic midpoint
    q2 = np.asarray(db.poses[456], np.float64)
    r1, r2 = Rotation.from_rotvec(q[3:6]), Rotation.from_rotvec(q2[3:6])
    if (r1.inv() * r2).magnitude() > 2.5:
        q2[3:6] = (r1 * Rotation.from_rotvec([0.0, 0.0, 1.0])).as_rotvec()
        r2 = Rotation.from_rotvec(q2[3:6])
    mid = posedb.blend_poses(jnp.asarray(np.stack([q, q2])), jnp.asarray([4.0, 4.0]))
    np.testing.assert_allclose(mid[6:], (q[6:] + q2[6:]) / 2, atol=1e-12)
    ref = Rotation.concatenate([r1, r2]).mean()  # SciPy's chordal L2 mean
    err = (Rotation.from_rotvec(np.array(mid[3:6])).inv() * ref).magnitude()
    assert err < 1e-9
    # the weights favour the nearest: a far second neighbour barely moves the blend
    far = posedb.blend_poses(jnp.asarray(np.stack([q, q2])), jnp.asarray([0.0, 120.0]))
    np.testing.assert_allclose(far, q, atol=1e-6)
    # estimate_pose of a member is that member's pose, plain, jit and vmap alike
    qb, nb = posedb.estimate_pose(db, jnp.asarray(maps[77]))
    assert int(nb.index[0]) == 77
    qv, nbv = batched(ESTIMATE, db, maps[[77, 78]])
    np.testing.assert_allclose(qv[0], qb, atol=1e-6)
    np.testing.assert_array_equal(nbv.index[0], nb.index)
    nb78 = jax.tree.map(lambda a: jnp.asarray(a[1]), nbv)
    np.testing.assert_allclose(qv[1], posedb.blend(db, nb78), atol=1e-6)


def test_heldout_pose_accuracy(db, heldout):
    """Blended held-out estimates beat the database's mean pose (root-aligned joint error)."""
    poses, _, noisy = heldout
    qb, _ = batched(ESTIMATE, db, noisy)
    truth = np.asarray(KEYPOINTS(jnp.asarray(poses, jnp.float64)))
    est = np.asarray(KEYPOINTS(jnp.asarray(qb, jnp.float64)))
    mean_pose = np.asarray(db.poses, np.float64).mean(0)
    base = np.asarray(KEYPOINTS(jnp.asarray(np.tile(mean_pose, (len(poses), 1)))))
    err = np.linalg.norm(est - truth, axis=-1).mean() * 100
    err_base = np.linalg.norm(base - truth, axis=-1).mean() * 100
    assert err < 0.6 * err_base, (err, err_base)


# ----------------------------------------------------------------------------- cameras


def test_pose_in_camera(db):
    model = default_body()
    q = jnp.asarray(db.poses[42], jnp.float64)
    canon = posedb.canonical_camera(jnp.float64)
    cam = look_at((1.0, -2.5, 1.8), (0.3, 0.4, 1.0), width=640, height=480, fx=600.0)
    x = jnp.asarray([0.4, -0.2, 2.2])

    @jax.jit
    def frames(q):
        kp_cam = jax.vmap(lambda qw: to_camera(cam, keypoints(model, qw)))
        qs = jnp.stack([posedb.pose_in_camera(q, cam), posedb.pose_in_camera(q, cam, x)])
        grad = jax.grad(lambda w: jnp.sum(posedb.pose_in_camera(q.at[3:6].set(w), cam)))
        return to_camera(canon, keypoints(model, q)), kp_cam(qs), grad(q[3:6])

    x_canon, (x_default, x_moved), g = frames(q)
    # default: the root where the canonical camera sees it: same camera-frame keypoints
    np.testing.assert_allclose(x_default, x_canon, atol=1e-9)
    # another line of sight: the body turns with it, R_x (x_canon - t_canon) + x
    t_c = np.asarray(canon.t)
    a, b = t_c / np.linalg.norm(t_c), np.asarray(x) / np.linalg.norm(x)
    axis = np.cross(a, b)
    r_x = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(a @ b)).as_matrix()
    expect = (np.asarray(x_canon) - t_c) @ r_x.T + np.asarray(x)
    np.testing.assert_allclose(x_moved, expect, atol=1e-9)
    # gradients flow (no NaN at the default, where R_x is the identity)
    assert np.all(np.isfinite(g))


# ----------------------------------------------------------------------------- files and CLI


def test_files_and_cli(tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    np.savez(bad, nothing=np.zeros(3))
    with pytest.raises(InputError, match="bad.npz"):
        posedb.load_database(bad)
    with pytest.raises(InputError, match="maps"):
        posedb.make_posedb(np.zeros((3, 40, 40), np.int32), np.zeros((3, 24)), 10)
    assert "jaxmocap.commands.build_db" in SUBCOMMANDS
    parser = argparse.ArgumentParser(prog="jaxmocap")
    build_db_command.add_parser(parser.add_subparsers(dest="command"))

    def build_db(*argv):
        args = parser.parse_args(["build-db", *argv])
        return args.func(args)

    with pytest.raises(InputError, match="size"):
        build_db("--size", "0")
    with pytest.raises(InputError, match="expected a path ending in .npz"):
        build_db("--size", "5", "--out", str(tmp_path / "db.txt"))
    out = tmp_path / "db.npz"
    assert build_db("--size", "12", "--seed", "2", "--out", str(out), "--quiet") == 0
    loaded = posedb.load_database(out)
    assert loaded.size == 12 and "12 poses" in capsys.readouterr().out
    cfg = posedb.SamplingConfig(size=12, seed=2)
    assert loaded.key == posedb.database_key(cfg, default_body(), default_garment())


def test_tiny_maps_skip_geoms_below_the_shirt():
    """A body with legs (pybullet's MJCF humanoid, 19 geoms): the database renders only the
    geoms that can show or hide the shirt, and its maps equal the full model's render (the
    oracle) for poses with the legs at rest."""
    from pathlib import Path

    import pybullet_data

    from jaxmocap import render
    from jaxmocap.body import load_mjcf
    from jaxmocap.garment import make_garment

    model = load_mjcf(Path(pybullet_data.getDataPath()) / "mjcf" / "humanoid.xml")
    patches = [("chest", "torso1", [], 1), ("waist", "uwaist", [], 2), ("belly", "lwaist", [], 3),
               ("r_upper", "right_uarm1", [], 2), ("l_upper", "left_uarm1", [], 3),
               ("r_fore", "right_larm", [], 1), ("l_fore", "left_larm", [], 2)]  # fmt: skip
    garment = make_garment(model, patches, [("red", (0.9, 0.1, 0.1)), ("green", (0.1, 0.9, 0.1)),
                                            ("blue", (0.1, 0.1, 0.9))],
                           skin_geoms=("head", "right_hand", "left_hand"))  # fmt: skip
    sub, sub_garment = _build.tiny_map_subset(model, garment)
    dropped = set(model.geometry.names) - set(sub.geometry.names)
    assert dropped == {f"{s}_{p}" for s in ("left", "right")
                       for p in ("thigh1", "shin1", "foot_cap1", "foot_cap2")}  # fmt: skip
    assert sub_garment.patch_names == garment.patch_names
    assert [sub.geometry.names[i] for i in np.asarray(sub_garment.patch_geom)] == [
        p[1] for p in patches]
    rng = np.random.default_rng(0)
    upper = [i for i, n in enumerate(model.chain.dof_names)
             if i >= 6 and not any(w in n for w in ("hip", "knee", "ankle"))]  # fmt: skip
    poses = np.zeros((24, model.n_dof), np.float32)
    poses[:, upper] = rng.uniform(-0.8, 0.8, (24, len(upper)))
    poses[:, 5] = rng.uniform(-np.pi, np.pi, 24)  # yaw about the vertical
    poses[:, 2] = 1.0
    maps = posedb.render_maps(model, garment, poses, progress=False)
    cam = posedb.canonical_camera(jnp.float32)
    full = np.asarray(jax.jit(lambda qs: render.tiny_id_maps(model, garment, qs, cam))(poses))
    assert (maps > 0).mean() > 0.2  # the shirt fills a good part of each map
    assert (maps != full).mean() < 5e-4  # float rounding at silhouettes only


# ----------------------------------------------------------------------------- orientations


def test_orientation_hypotheses_recover_a_known_yaw(db):
    """A pose turned by a known yaw is recovered from its rendered id map by the first
    orientation hypothesis, and the same arms seen from behind form a separate hypothesis:
    a small database holds the pose at yaw psi +-3, +-6 deg, at psi + 180 +-3, +-6 deg and
    twelve other poses turned at least 60 deg from both; the query is the canonical render
    at psi exactly (not in it)."""
    model, garment = default_body(), default_garment(default_body())
    base = np.asarray(db.poses[321], np.float64)
    psi = np.radians(50.0)

    def at(yaw):
        q = base.copy()
        q[3:6] = Rotation.from_euler("z", yaw).as_rotvec()
        return q

    offs = np.radians([-6.0, -3.0, 3.0, 6.0])
    # other poses: none within 60 deg of either orientation (each is its own cluster)
    others = np.asarray(db.poses, np.float64)
    R = Rotation.from_rotvec(others[:, 3:6])
    far = [(Rotation.from_rotvec(at(y)[3:6]).inv() * R).magnitude() > np.radians(60)
           for y in (psi, psi + np.pi)]
    others = others[far[0] & far[1]][:12]
    poses = np.stack([at(psi + o) for o in offs] + [at(psi + np.pi + o) for o in offs]
                     + list(others))
    maps = posedb.render_maps(model, garment, poses.astype(np.float32), progress=False)
    small = posedb.make_posedb(maps, poses, garment.n_colours)
    query = posedb.render_maps(model, garment, at(psi)[None].astype(np.float32),
                               progress=False)[0]
    hyp = posedb.estimate_hypotheses(small, jnp.asarray(query), n_hyp=14, k=20)
    yaw = Rotation.from_rotvec(np.asarray(hyp.poses[:, 3:6], np.float64)).as_euler("zyx")[:, 0]
    assert np.isfinite(hyp.distance[:2]).all()
    assert np.all(np.diff(np.asarray(hyp.distance)[np.isfinite(hyp.distance)]) >= 0)
    # the first hypothesis: the pose's own orientation (its cluster's four copies blended),
    # nearer psi than any copy (3 deg)
    assert abs(np.degrees(np.angle(np.exp(1j * (yaw[0] - psi))))) < 2.0
    np.testing.assert_allclose(hyp.poses[0, 6:], base[6:], atol=1e-5)
    # the back view is one of the others, never blended into the first
    back = [abs(np.degrees(np.angle(np.exp(1j * (y - psi - np.pi))))) for y in yaw[1:]]
    assert min(back) < 3.0, np.degrees(yaw)


def test_damaged_cache_is_detected_rebuilt_and_reported(tmp_path, capsys):
    """Issue 52 item 4: a cached database cut short (a crash while the disk wrote it) or with
    changed bytes inside a well-formed archive (found by the content digest recorded at build
    time) is reported in one line and built again, equal to the first build (the oracle); the
    same for the cached pose pool. A user's --db file with changed content is refused."""
    cfg = posedb.SamplingConfig(size=12, seed=2)
    first = posedb.load_or_build(cfg, cache=tmp_path, progress=False)
    path = posedb.cache_path(first.key, tmp_path)
    raw = path.read_bytes()
    capsys.readouterr()

    def rebuilt_equal():
        again = posedb.load_or_build(cfg, cache=tmp_path, progress=False)
        err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        np.testing.assert_array_equal(np.asarray(again.codes), np.asarray(first.codes))
        np.testing.assert_array_equal(np.asarray(again.poses), np.asarray(first.poses))
        return err

    path.write_bytes(raw[: len(raw) // 2])
    err = rebuilt_equal()
    assert len(err) == 1 and err[0].startswith(f"jaxmocap: the cached pose database {path} is "
                                               "damaged (cannot read: truncated"), err
    assert err[0].endswith("building it again")
    with np.load(path) as z:  # a bit changed inside: the archive is still well formed
        arrays = {k: z[k] for k in z.files}
    arrays["maps"] = arrays["maps"].copy()
    arrays["maps"].flat[7] ^= 1
    np.savez_compressed(path, **arrays)
    with pytest.raises(InputError, match=rf"{path.name}: damaged: its maps and poses do not "
                                         "match the digest"):
        posedb.load_database(path)
    err = rebuilt_equal()
    assert len(err) == 1 and "is damaged (damaged: its maps and poses" in err[0], err
    assert rebuilt_equal() == []  # now intact: loaded, nothing said
    # the cached pose pool (the clips retargeted to the body)
    from jaxmocap.posedb._sample import source_pool

    pool = source_pool(default_body(), TRAIN_CLIPS[:1], cache=str(tmp_path))
    (cached,) = tmp_path.glob("pool-*.npz")
    cached.write_bytes(cached.read_bytes()[:100])
    capsys.readouterr()
    np.testing.assert_array_equal(source_pool(default_body(), TRAIN_CLIPS[:1],
                                              cache=str(tmp_path)), pool)
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and f"the cached pose pool {cached} is damaged" in err[0], err
