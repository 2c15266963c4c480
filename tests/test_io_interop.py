"""Optional interop: the exports opened by the tools people use — Blender's BVH importer (the
`bpy` module), OpenSim's TRC readers (`opensim`) and a web browser (headless Chromium) for the
overlay video. Skipped when the tool is not installed (`pip install -e ".[interop]"`;
`apt-get install chromium`); each tool runs in its own process so that its libraries and
warnings stay out of the test process."""

import importlib.util
import io
import json
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pybullet_data
import pytest

from jaxmocap.body import default_body, fk, load_urdf
from jaxmocap.io.atomic import AtomicFiles
from jaxmocap.io.bvh import body_bvh_layout, write_body_bvh
from jaxmocap.io.export import bvh_poses, pose_track, write_exports
from jaxmocap.io.video import VideoWriter

FPS = 30.0


def needs(module: str):
    return pytest.mark.skipif(importlib.util.find_spec(module) is None,
                              reason=f"{module} not installed (pip install -e '.[interop]')")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A demo-like track of the bundled body (a turning, walking root, arms in motion, one
    invalid frame) written by write_exports."""
    model = default_body()
    rng = np.random.default_rng(3)
    n = 8
    q = np.zeros((n, model.n_dof))
    q[:, 0] = np.linspace(0, 0.5, n)
    q[:, 2] = 1.0
    q[:, 5] = np.linspace(-0.4, 0.6, n)
    q[:, 6:] = rng.uniform(-0.6, 0.6, (n, model.n_dof - 6))
    valid = np.ones(n, bool)
    valid[4] = False
    track = pose_track(model, q, valid, FPS)
    folder = tmp_path_factory.mktemp("interop")
    with AtomicFiles() as files:
        write_exports(files, folder, model, track, formats=("bvh", "trc", "npz"))
    return model, track, folder


def run_tool(script: str, *args) -> dict:
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(script), *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


BLENDER = """
    import json, sys
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=sys.argv[1], update_scene_fps=True,
                            update_scene_duration=True)  # default axis conversion, scale 1
    ob = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    sc = bpy.context.scene
    first, last = (int(round(f)) for f in ob.animation_data.action.frame_range)
    heads = []
    for f in range(first, last + 1):
        sc.frame_set(f)
        heads.append({b.name: list(ob.matrix_world @ b.head) for b in ob.pose.bones})
    print(json.dumps({"fps": sc.render.fps / sc.render.fps_base, "heads": heads}))
"""


@needs("bpy")
def test_blender_imports_bvh_with_joint_positions(exported):
    model, track, folder = exported
    out = run_tool(BLENDER, folder / "poses.bvh")
    assert out["fps"] == pytest.approx(FPS)  # Blender took the frame time as the scene's rate
    assert len(out["heads"]) == track.n_frames
    lay = body_bvh_layout(model)
    q = bvh_poses(track)  # BVH holds every estimate, the invalid frame's too
    origins = np.asarray(jax.vmap(fk, in_axes=(None, 0))(model.chain, jnp.asarray(q)))
    origins = origins[:, list(lay.links)][..., :3, 3]
    got = np.array([[frame[name] for name in lay.names] for frame in out["heads"]])
    # Blender's default axis conversion (-Z forward, Y up) maps the BVH frame onto our Z-up
    # world: bone heads are the body's joints, in metres
    np.testing.assert_allclose(got, origins, atol=1e-5)  # Blender stores float32
    for name in lay.names:
        if name in track.keypoint_names:
            k = track.keypoint_names.index(name)
            np.testing.assert_allclose(got[:, lay.names.index(name)], track.keypoints[:, k],
                                       atol=1e-5)


@needs("bpy")
def test_blender_imports_bvh_of_another_body(tmp_path):
    """pybullet's humanoid: other link names, legs, a rotated (Y-up) root offset and fixed
    wrists (0-channel joints), leaves without keypoints (End Sites of length 0)."""
    model = load_urdf(Path(pybullet_data.getDataPath()) / "humanoid" / "humanoid.urdf",
                      scale=0.25, up="y")
    rng = np.random.default_rng(4)
    q = rng.uniform(np.maximum(np.asarray(model.chain.lower), -1.2),
                    np.minimum(np.asarray(model.chain.upper), 1.2), size=(5, model.n_dof))
    q[:, :6] = rng.normal(0, 0.7, (5, 6))
    write_body_bvh(tmp_path / "h.bvh", model, q, fps=25.0)
    out = run_tool(BLENDER, tmp_path / "h.bvh")
    assert out["fps"] == pytest.approx(25.0) and len(out["heads"]) == 5
    lay = body_bvh_layout(model)
    origins = np.asarray(jax.vmap(fk, in_axes=(None, 0))(model.chain, jnp.asarray(q)))
    got = np.array([[frame[name] for name in lay.names] for frame in out["heads"]])
    np.testing.assert_allclose(got, origins[:, list(lay.links)][..., :3, 3], atol=1e-5)


OPENSIM = """
    import json, sys
    import opensim as osim
    t = osim.TimeSeriesTableVec3(sys.argv[1])
    rows = [[[t.getRowAtIndex(r)[c].get(i) for i in range(3)] for c in range(t.getNumColumns())]
            for r in range(t.getNumRows())]
    refs = osim.MarkersReference(sys.argv[1], osim.SetMarkerWeights())
    print(json.dumps({"labels": list(t.getColumnLabels()), "times": list(t.getIndependentColumn()),
                      "units": t.getTableMetaDataAsString("Units"),
                      "rate": t.getTableMetaDataAsString("DataRate"),
                      "xyz": [[[v if v == v else None for v in p] for p in r] for r in rows],
                      "n_refs": refs.getNumRefs()}))
"""


@needs("opensim")
def test_opensim_loads_trc_with_untracked_frame(exported):
    _, track, folder = exported
    out = run_tool(OPENSIM, folder / "poses.trc")
    assert out["labels"] == list(track.keypoint_names) and out["n_refs"] == 12
    assert out["units"] == "m" and float(out["rate"]) == FPS
    np.testing.assert_allclose(out["times"], track.times, atol=1e-6)
    xyz = np.array([[[np.nan if v is None else v for v in p] for p in r] for r in out["xyz"]])
    M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # OpenSim Y up -> our Z up
    assert np.isnan(xyz[~track.valid]).all()
    np.testing.assert_allclose(xyz[track.valid] @ M.T, track.keypoints[track.valid], atol=1e-5)


PAGE = """<!doctype html><html><body><div id="out">pending</div>
<video id="v" src="%s" muted playsinline></video><script>
const v = document.getElementById('v'), out = document.getElementById('out');
v.addEventListener('loadeddata', () => { out.textContent = JSON.stringify(
  {w: v.videoWidth, h: v.videoHeight, duration: v.duration, ready: v.readyState}); });
v.addEventListener('error', () => { out.textContent = JSON.stringify({error: v.error.code}); });
</script></body></html>"""


def browser_load(folder, video: str) -> dict:
    (folder / "page.html").write_text(PAGE % video)
    done = subprocess.run([shutil.which("chromium"), "--headless", "--no-sandbox",
                           "--disable-gpu", "--allow-file-access-from-files",
                           "--virtual-time-budget=8000", "--dump-dom",
                           (folder / "page.html").as_uri()],
                          capture_output=True, text=True, timeout=120)
    found = re.search(r'<div id="out">([^<]*)</div>', done.stdout)
    assert found, done.stderr[-2000:]
    return json.loads(found.group(1))


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium not installed")
def test_browser_plays_overlay_h264_at_its_rate(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (15, 47, 63, 3), dtype=np.uint8)  # odd size on purpose
    with VideoWriter(tmp_path / "h264.mp4", 30.0, 63, 47) as w:
        assert w.codec == "h264"
        for f in frames:
            w.write(f)
    got = browser_load(tmp_path, "h264.mp4")
    # decoded by the browser: 64x48 after padding, 15 frames at 30 fps last 0.5 s
    assert got["ready"] >= 2 and (got["w"], got["h"]) == (64, 48)
    assert got["duration"] == pytest.approx(0.5, abs=1e-3)
    monkeypatch.setitem(sys.modules, "av", None)  # the fallback: what browsers refuse
    with VideoWriter(tmp_path / "mp4v.mp4", 30.0, 64, 48, note=io.StringIO()) as w:
        for f in frames:
            w.write(np.pad(f, ((0, 1), (0, 1), (0, 0))))
    assert "error" in browser_load(tmp_path, "mp4v.mp4")
