"""Tests of the synthetic sequences (jaxmocap.synth.scene / sequence / dataset).

Oracles: cv2.projectPoints of the body's patch surface samples (posed from the *written*
ground truth) against the written id maps; the written PNG frames' colours, white-balanced
with the written illuminant, against the shirt's albedo table; the leave-view geometry; and
re-rendering (determinism). Every render uses 80x60 pixels and two cameras, so the whole file
compiles the frame renderer twice (1 and 3 motion-blur sub-frames).
"""

import json
import shutil

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import render
from jaxmocap.body import default_body
from jaxmocap.camera import camera_center
from jaxmocap.cli import main
from jaxmocap.errors import InputError
from jaxmocap.garment import SHIRT_COLOURS, SKIN_RGB
from jaxmocap.render._image import SURFACE_SAMPLES
from jaxmocap.synth import dataset, scene
from jaxmocap.synth.scene import SceneConfig, SceneError
from jaxmocap.synth.sequence import config_garment, render_sequence

T = 6
SMALL = dict(n_frames=T, width=80, height=60, lamp_off=3, background="clutter")
CLI_SMALL = ["--frames", str(T), "--width", "80", "--height", "60", "--lamp-off", "3",
             "--quiet"]


@pytest.fixture(scope="module")
def seq():
    return render_sequence(SceneConfig(**SMALL))


@pytest.fixture(scope="module")
def written(tmp_path_factory, seq):
    out = tmp_path_factory.mktemp("synth") / "ds"
    assert main(["synth", str(out), *CLI_SMALL, "--png"]) == 0
    return out


# ----------------------------------------------------------------------------- settings


def test_config_validation_and_json_round_trip():
    c = SceneConfig(rig="stereo", occluder=(1, 4), shirt_rgb=(0.2, 0.3, 0.9), seed=3)
    assert SceneConfig.from_dict(json.loads(c.to_json())["scene"]) == c
    for bad in (dict(motion_blur=2), dict(n_cameras=5), dict(rig="x"), dict(occluder=(4, 1)),
                dict(noise_sigma=-1.0), dict(width=3), dict(shirt_rgb=(1.0, 2.0, 3.0))):
        with pytest.raises(InputError, match=next(iter(bad))):
            SceneConfig(**bad)
    for bad in (dict(fps="fast"), dict(occluder=(1.5, 3)), dict(moving_object=1)):
        with pytest.raises(SceneError, match=next(iter(bad))):
            SceneConfig.from_dict(bad)
    assert SceneConfig.from_dict({"fps": 25, "shirt_rgb": [0, 0, 1]}).fps == 25.0
    with pytest.raises(SceneError, match="unknown field"):
        SceneConfig.from_dict({"colour": 1})


def test_rig_presets():
    stereo = scene.make_cameras(SceneConfig(rig="stereo"))
    web = scene.make_cameras(SceneConfig(rig="webcams"))
    c_s = np.array([np.asarray(camera_center(c)) for c in stereo])
    c_w = np.array([np.asarray(camera_center(c)) for c in web])
    # Azad: ~11 cm apart at eye height, 320x240, parallel optical axes
    assert (stereo[0].width, stereo[0].height) == (320, 240)
    np.testing.assert_allclose(np.linalg.norm(c_s[0] - c_s[1]), 0.11, atol=1e-6)
    np.testing.assert_allclose(c_s[:, 2], 1.6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(stereo[0].R), np.asarray(stereo[1].R), atol=1e-6)
    # Wang: two 640x480 webcams 1.5 m apart, 2.5-3 m from the subject, converging on it
    assert (web[0].width, web[0].height) == (640, 480)
    np.testing.assert_allclose(np.linalg.norm(c_w[0] - c_w[1]), 1.5, atol=1e-6)
    assert np.all((np.linalg.norm(c_w[:, :2], axis=1) > 2.5)
                  & (np.linalg.norm(c_w[:, :2], axis=1) < 3.0))
    target = np.array([0.0, 0.0, scene.LOOK_HEIGHT])
    for cam, c in zip(web, c_w, strict=True):
        axis = np.asarray(cam.R)[2]
        np.testing.assert_allclose(axis, (target - c) / np.linalg.norm(target - c), atol=1e-6)
    four = scene.make_cameras(SceneConfig(n_cameras=4, baseline=0.5))
    gaps = np.diff(np.array([np.asarray(camera_center(c))[1] for c in four]))
    np.testing.assert_allclose(gaps, 0.5, atol=1e-6)


def test_props_include_look_alike_distractors():
    p = scene.make_props(SceneConfig(n_distractors=8))
    rgb = np.asarray(p.rgb)[np.asarray(p.active)]
    shirt = np.array([c for _, c in SHIRT_COLOURS])
    assert sum(np.any(np.all(np.isclose(shirt, c), axis=1)) for c in rgb) >= 2
    assert np.any(np.all(np.isclose(rgb, SKIN_RGB), axis=1))
    plain = scene.make_props(SceneConfig(background="plain"))
    assert not np.any(np.asarray(plain.active)) and float(np.max(plain.wave_amp)) == 0


def test_schedule_illuminant_blur_and_leave_view():
    c = SceneConfig(drift=0.3, lamp_off=5, motion_blur=3, shutter=0.6, leave_view=(2, 8))
    M, intensity = scene.illuminant_schedule(c, 10)
    gains = np.einsum("tii->ti", M)
    assert np.allclose(M - gains[:, :, None] * np.eye(3), 0)
    np.testing.assert_allclose(gains[0].mean(), 1.0)  # normalised: full lamp, no drift yet
    blue_red = gains[:, 2] / gains[:, 0]
    assert blue_red[5] > 1.5 * blue_red[4] and np.all(gains[5:] == gains[5])  # lamp step
    assert np.all(np.abs(np.diff(gains[:5], axis=0)) < 0.05)  # smooth drift
    np.testing.assert_allclose(scene.subframe_offsets(c), [-0.2, 0.0, 0.2])
    rng = np.random.default_rng(0)
    q = rng.normal(size=(10, 24)) * 0.3
    sch = scene.make_schedule(c, q)
    np.testing.assert_allclose(sch.q[:, 1], sch.q_frame, atol=1e-12)  # middle = the frame
    off = scene.leave_offset(c, np.arange(10.0))
    assert np.all(off[[0, 1, 2, 8, 9]] == 0) and np.all(off[4:7] > 2.0)
    mid = scene.interpolate_poses(q, np.array([3.5]))[0]
    np.testing.assert_allclose(mid[6:], (q[3, 6:] + q[4, 6:]) / 2)


# ----------------------------------------------------------------------------- rendering


def _project_cv2(cam, pts):
    rvec, _ = cv2.Rodrigues(np.asarray(cam.R, np.float64))
    uv, _ = cv2.projectPoints(pts.astype(np.float64), rvec, np.asarray(cam.t, np.float64),
                              np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64))
    return uv.reshape(-1, 2)


def test_ground_truth_reprojects_onto_written_id_maps(written):
    ds = dataset.load_dataset(written)
    gt = ds.groundtruth
    model, garment = default_body(), config_garment(ds.config)
    n_patch = garment.n_patches
    label = np.repeat(np.arange(1, n_patch + 1), SURFACE_SAMPLES)
    agree, total, agree_shifted, total_shifted, dists = 0, 0, 0, 0, []
    for t in range(T):
        pts, valid = render.shirt_points(model, garment, jnp.asarray(gt["q"][t]))
        pts, valid = np.asarray(pts), np.asarray(valid)
        lab = label[: pts.shape[0]]
        for c, cam in enumerate(ds.cameras):
            ids = gt["patch_ids"][t, c]
            uv = _project_cv2(cam, pts[valid])
            lv = lab[valid]
            # every labelled pixel lies on the projection of its own patch
            ys, xs = np.nonzero(ids)
            for p in np.unique(ids[ids > 0]):
                m = ids[ys, xs] == p
                pix = np.stack([xs[m], ys[m]], axis=1).astype(float)
                d = np.linalg.norm(pix[:, None] - uv[lv == p][None], axis=-1).min(axis=1)
                assert d.max() < 2.0, (t, c, p, d.max())  # sample spacing: ~1-2 px
                dists.append(d)
            # nearest projected sample (splatted z-buffer) agrees with the id map
            depth = (pts[valid] @ np.asarray(cam.R).T + np.asarray(cam.t))[:, 2]
            px = np.round(uv).astype(int)
            inside = (px[:, 0] >= 0) & (px[:, 0] < 80) & (px[:, 1] >= 0) & (px[:, 1] < 60)
            zbuf = np.full((60, 80), np.inf)
            zlab = np.zeros((60, 80), int)
            for (x, y), z, p in zip(px[inside], depth[inside], lv[inside], strict=True):
                if z < zbuf[y, x]:
                    zbuf[y, x], zlab[y, x] = z, p
            both = (ids > 0) & (zlab > 0)
            agree += int(np.sum(zlab[both] == ids[both]))
            total += int(np.sum(both))
            shifted = np.roll(ids, 2, axis=1)  # negative control: a 2-pixel misalignment
            both = (shifted > 0) & (zlab > 0)
            agree_shifted += int(np.sum(zlab[both] == shifted[both]))
            total_shifted += int(np.sum(both))
    dists = np.concatenate(dists)
    assert len(dists) > 200 and total > 100 and np.median(dists) < 0.5
    # the splatted samples leak through at back faces and patch borders, but a misaligned
    # map agrees far less
    assert agree / total > 0.75 and agree_shifted / total_shifted < agree / total - 0.2


def test_written_frames_show_the_patch_colours_under_the_written_illuminant(written):
    ds = dataset.load_dataset(written)
    gt = ds.groundtruth
    albedo = np.array([c for _, c in SHIRT_COLOURS])
    chroma_ref = albedo / albedo.sum(axis=1, keepdims=True)
    correct = total = 0
    for t in range(T):
        M_inv = np.linalg.inv(gt["illuminant"][t]) / gt["intensity"][t]
        for c in range(len(ds.cameras)):
            k = gt["colour_ids"][t, c]
            lin = (ds.frames[t, c].astype(float) / 255) ** render.CAMERA_GAMMA
            rho = lin @ M_inv.T
            bright = rho.sum(axis=-1) > 0.15
            sel = (k > 0) & bright
            chroma = rho[sel] / rho[sel].sum(axis=-1, keepdims=True)
            nearest = np.argmin(np.linalg.norm(chroma[:, None] - chroma_ref[None], axis=-1), 1)
            correct += int(np.sum(nearest + 1 == k[sel]))
            total += int(np.sum(sel))
    assert total > 200 and correct / total > 0.97, (correct, total)
    # the lamp step is in the ground truth and in the frames' mean colour
    means = ds.frames.reshape(T, -1, 3).mean(axis=1)
    steps = np.abs(np.diff(means.mean(axis=1)))
    assert np.argmax(steps) == 2 and steps[2] > 5 * np.delete(steps, 2).max()
    assert means[3, 2] / means[3, 0] > means[2, 2] / means[2, 0]  # bluer without tungsten
    assert np.all(ds.groundtruth["visible"]) and np.all(gt["occluded_fraction"] == 0)


def test_dataset_is_complete_and_deterministic(written, seq, tmp_path):
    names = sorted(p.name for p in written.iterdir())
    assert names == ["cam0", "cam0.mp4", "cam1", "cam1.mp4", "cameras.json",
                     "groundtruth.npz", "scene.json"]
    assert not [p for p in written.parent.iterdir() if p.name.startswith(".")]
    ds = dataset.load_dataset(written)
    # two runs (CLI on disk, API in memory) give identical arrays
    np.testing.assert_array_equal(ds.frames, seq.frames)
    for k, v in seq.groundtruth.items():
        np.testing.assert_array_equal(ds.groundtruth[k], v, err_msg=k)
    assert seq.groundtruth["patch_ids"].dtype == np.uint8
    assert seq.groundtruth["keypoints"].shape == (T, 12, 3)
    # the mp4 videos hold the same frames (lossy codec)
    shutil.rmtree(written / "cam0"), shutil.rmtree(written / "cam1")
    try:
        from_video = dataset.load_dataset(written)
        assert np.mean(np.abs(from_video.frames.astype(float) - seq.frames)) < 8
    finally:
        dataset.write_dataset(seq, tmp_path / "again", video=False, png=True)
        for cam in ("cam0", "cam1"):
            shutil.copytree(tmp_path / "again" / cam, written / cam)
    # regenerate from scene.json: bit-identical
    out = tmp_path / "regen"
    assert main(["synth", str(out), "--scene", str(written / "scene.json"), "--png",
                 "--no-video", "--quiet"]) == 0
    np.testing.assert_array_equal(dataset.load_dataset(out).frames, seq.frames)


def test_occluder_hides_body_pixels(seq):
    occ = render_sequence(SceneConfig(**SMALL, occluder=(1, 4)))
    free, hid = seq.groundtruth["patch_ids"], occ.groundtruth["patch_ids"]
    np.testing.assert_array_equal(occ.groundtruth["q"], seq.groundtruth["q"])
    shown = hid > 0
    np.testing.assert_array_equal(hid[shown], free[shown])  # hiding never relabels
    lost = np.sum((free > 0) & ~shown, axis=(2, 3))
    assert lost.sum() > 20 and np.all(lost[[0, 5]] == 0)
    frac = occ.groundtruth["occluded_fraction"]
    body = occ.groundtruth["body_pixels"]
    assert np.all(frac[lost > 0] > 0)
    # occluded fraction counts every body pixel (incl. skin) the panel hides: at least the
    # shirt pixels lost
    assert np.all(frac * body >= lost - 1e-9)
    np.testing.assert_array_equal(body, seq.groundtruth["body_pixels"])
    # hidden pixels show the panel's cardboard colour, not the body's
    diff = np.any(occ.frames != seq.frames, axis=-1)
    assert np.all(diff[(free > 0) & ~shown])


def test_subject_leaves_the_view_and_comes_back():
    s = render_sequence(SceneConfig(**SMALL, leave_view=(0, 5)))
    gt = s.groundtruth
    vis = gt["visible"]
    assert np.all(vis[[0, 5]]) and not np.any(vis[[2, 3]])
    assert np.all(gt["patch_ids"][[2, 3]] == 0) and np.all(gt["body_pixels"][[2, 3]] == 0)
    assert np.all(gt["keypoints"][[2, 3], :, 1] > 2.0)


def test_motion_blur_averages_sub_frames(seq):
    sharp = render_sequence(SceneConfig(**{**SMALL, "n_frames": 3}, motion_blur=3, shutter=0.0))
    blur = render_sequence(SceneConfig(**{**SMALL, "n_frames": 3}, motion_blur=3, shutter=1.0))
    ref = seq.frames[:3]
    assert np.max(np.abs(sharp.frames.astype(int) - ref)) <= 1  # mean of 3 equal renders
    for s in (sharp, blur):  # ground truth is the frame's own pose
        np.testing.assert_array_equal(s.groundtruth["patch_ids"], seq.groundtruth["patch_ids"][:3])
    changed = np.any(np.abs(blur.frames.astype(int) - ref) > 1, axis=-1)
    assert changed.sum() > 10
    body = seq.groundtruth["body_pixels"]
    assert body.min() > 0
    near = np.zeros_like(changed)
    masks = seq.groundtruth["patch_ids"] > 0
    for t in range(3):  # blur only touches pixels near the moving body
        m = masks[max(t - 1, 0): t + 2].any(axis=0).astype(np.uint8)
        for c in range(2):
            near[t, c] = cv2.dilate(m[c], np.ones((7, 7), np.uint8)) > 0
    skin_or_body = near | (np.abs(blur.frames.astype(int) - ref).max(-1) <= 1)
    assert np.mean(changed & ~near) < 0.002 and skin_or_body.mean() > 0.99


# ----------------------------------------------------------------------------- errors / CLI


def _err_lines(capsys):
    return [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


@pytest.mark.parametrize("args", [
    ["--blur", "2"], ["--cameras", "5"], ["--occluder", "5", "2"], ["--no-video"],
    ["--clip", "no_such_clip"], ["--noise", "-0.1"]])  # fmt: skip
def test_cli_bad_arguments_exit_2_with_one_line(tmp_path, capsys, args):
    assert main(["synth", str(tmp_path / "out"), *args, "--frames", "1"]) == 2
    lines = _err_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("jaxmocap synth: error:")
    assert not (tmp_path / "out").exists()


def test_cli_refuses_existing_target(tmp_path, capsys):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep")
    (tmp_path / "file").write_text("keep")
    for name, why in (("full", "not empty"), ("file", "a file is in the way")):
        assert main(["synth", str(tmp_path / name), *CLI_SMALL]) == 2
        lines = _err_lines(capsys)
        assert len(lines) == 1 and why in lines[0]
    assert (tmp_path / "full" / "x").read_text() == "keep"
    assert (tmp_path / "file").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "full"]


def test_write_is_atomic(tmp_path, seq, monkeypatch):
    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(dataset, "_write_video", broken)
    with pytest.raises(OSError, match="disk full"):
        dataset.write_dataset(seq, tmp_path / "ds")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "empty").mkdir()  # an existing empty folder is fine
    dataset.write_dataset(seq, tmp_path / "empty", video=False, png=True)
    assert (tmp_path / "empty" / "groundtruth.npz").is_file()


def test_load_dataset_reports_missing_and_corrupt_files(written, tmp_path):
    def broken_copy(name):
        d = tmp_path / name
        shutil.copytree(written, d)
        return d

    d = broken_copy("no_gt")
    (d / "groundtruth.npz").unlink()
    with pytest.raises(dataset.DatasetError, match="groundtruth.npz: missing"):
        dataset.load_dataset(d)
    d = broken_copy("bad_scene")
    (d / "scene.json").write_text("{not json")
    with pytest.raises(dataset.DatasetError, match="scene.json: not valid JSON"):
        dataset.load_dataset(d)
    d = broken_copy("bad_field")
    doc = json.loads((d / "scene.json").read_text())
    doc["scene"]["motion_blur"] = 4
    (d / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(dataset.DatasetError, match="motion_blur"):
        dataset.load_dataset(d)
    d = broken_copy("no_frame")
    (d / "cam1" / "000004.png").unlink()
    with pytest.raises(dataset.DatasetError, match="000004.png"):
        dataset.load_dataset(d)
    d = broken_copy("bad_gt")
    gt = dict(np.load(d / "groundtruth.npz"))
    gt["patch_ids"] = gt["patch_ids"][:, :, :10]
    np.savez(d / "groundtruth.npz", **gt)
    with pytest.raises(dataset.DatasetError, match="'patch_ids' has shape"):
        dataset.load_dataset(d)
    d = broken_copy("bad_cams")
    (d / "cameras.json").write_text("[]")
    with pytest.raises(InputError, match="cameras.json"):
        dataset.load_dataset(d)
    with pytest.raises(dataset.DatasetError, match="not a dataset folder"):
        dataset.load_dataset(tmp_path / "nothing")


def test_contact_sheet_tiles_frames_by_camera(seq):
    sheet = dataset.contact_sheet(seq, n=3, width=40)
    assert sheet.shape == (2 * 32, 3 * 42, 3) and sheet.dtype == np.uint8
    tile = sheet[33:63, 43:83]  # camera 1, middle frame (index 2 or 3 of 0..5), no label rows
    ref = cv2.resize(seq.frames[round(2.5), 1], (40, 30), interpolation=cv2.INTER_AREA)
    assert np.mean(np.abs(tile[16:].astype(int) - ref[16:])) < 1e-9
