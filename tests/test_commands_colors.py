"""`jaxmocap colors`: the fitted model equals NumPy's ML Gaussians of the labelled pixels;
the white balance undoes a known colour cast; bad scribbles and files are refused clearly."""

import json

import cv2
import numpy as np
import pytest
from test_cli import assert_refused, run_cli

from jaxmocap.color.model import MIN_VARIANCE
from jaxmocap.commands.colors import load_white_balance

H, W = 30, 40
COLOURS = np.array([[200, 40, 40], [40, 180, 60], [50, 60, 200], [210, 200, 50]], float)


def shirt(rng, cast=None):
    """Four vertical colour bands with noise (seen through ``cast``) and their labels."""
    cast = np.eye(3) if cast is None else cast
    lab = np.zeros((H, W), np.uint8)
    img = np.full((H, W, 3), 128.0)
    for k in range(4):
        cols = slice(10 * k + 1, 10 * k + 9)
        img[2:-2, cols] = COLOURS[k] @ cast.T + rng.normal(0, 4, (H - 4, 8, 3))
        lab[4:-4, cols] = k + 1  # scribbles inside the bands
    return np.clip(np.round(img), 0, 255).astype(np.uint8), lab


def save(path, img, lab):
    cv2.imwrite(str(path) + ".png", img[..., ::-1])
    cv2.imwrite(str(path) + "_labels.png", lab)
    return f"{path}.png", f"{path}_labels.png"


def test_model_equals_numpy_ml_fit(tmp_path, capsys):
    rng = np.random.default_rng(0)
    (i1, m1), (i2, m2) = save(tmp_path / "a", *shirt(rng)), save(tmp_path / "b", *shirt(rng))
    out = tmp_path / "colors.json"
    rc, stdout, err = run_cli(capsys, "colors", "--images", i1, i2, "--masks", m1, m2,
                              "--names", "red", "green", "blue", "yellow", "--out", out)
    assert rc == 0 and err == []
    doc = json.loads(out.read_text())
    assert [c["name"] for c in doc["colors"]] == ["red", "green", "blue", "yellow"]
    imgs = [cv2.imread(p)[..., ::-1].astype(float) for p in (i1, i2)]
    labs = [cv2.imread(p, cv2.IMREAD_UNCHANGED) for p in (m1, m2)]
    for k, c in enumerate(doc["colors"]):
        x = np.concatenate([im[lb == k + 1] for im, lb in zip(imgs, labs, strict=True)])
        np.testing.assert_allclose(c["mean"], x.mean(0), atol=1e-9)
        np.testing.assert_allclose(c["cov"], np.cov(x.T, bias=True) + MIN_VARIANCE * np.eye(3),
                                   atol=1e-9)
    assert "colour 2 green" in stdout


def test_white_balance_undoes_a_cast(tmp_path, capsys):
    rng = np.random.default_rng(1)
    i0, m0 = save(tmp_path / "ref", *shirt(rng))
    model = tmp_path / "colors.json"
    assert run_cli(capsys, "colors", "--images", i0, "--masks", m0, "--out", model)[0] == 0
    cast = np.array([[0.8, 0.05, 0.0], [0.0, 0.7, 0.05], [0.05, 0.0, 0.55]])  # dim, warm light
    i1, m1 = save(tmp_path / "cam0", *shirt(rng, cast))
    i2, m2 = save(tmp_path / "cam1", *shirt(rng))
    out = tmp_path / "wb.json"
    rc, _, err = run_cli(capsys, "colors", "--white-balance", "--colors", model, "--images", i1,
                         i2, "--masks", m1, m2, "--out", out)
    assert rc == 0 and err == []
    Wb = load_white_balance(out, ["cam0", "cam1"])
    fitted = np.array(json.loads(model.read_text())["colors"][0]["mean"])
    observed = np.round(COLOURS[0] @ cast.T)
    assert np.linalg.norm(Wb[0] @ observed - fitted) < 4  # W maps the cast colour back
    np.testing.assert_allclose(Wb[0], np.linalg.inv(cast), atol=0.05)
    np.testing.assert_allclose(Wb[1], np.eye(3), atol=0.03)


def test_refusals(tmp_path, capsys):
    rng = np.random.default_rng(2)
    img, lab = shirt(rng)
    i, m = save(tmp_path / "a", img, lab)
    out = tmp_path / "colors.json"
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), lab[:-1])
    assert_refused(capsys, f"label mask is {W}x{H - 1} but image {i} is {W}x{H}", "colors",
                   "--images", i, "--masks", small, "--out", out, leaves=[out])
    assert_refused(capsys, "labels [4] out of range: expected 0 (none) or a colour 1..3",
                   "colors", "--images", i, "--masks", m, "--n-colors", "3", "--out", out,
                   leaves=[out])
    few = lab.copy()
    few[few == 3] = 0
    few[5, 21:24] = 3
    fm = tmp_path / "few.png"
    cv2.imwrite(str(fm), few)
    assert_refused(capsys, "colour 3 has 3 labelled pixels in the masks (need >= 20)", "colors",
                   "--images", i, "--masks", fm, "--out", out, leaves=[out])
    rgb = tmp_path / "rgb.png"
    cv2.imwrite(str(rgb), np.dstack([lab, lab * 0, lab]))
    assert_refused(capsys, "label mask must be single-channel", "colors", "--images", i,
                   "--masks", rgb, "--out", out, leaves=[out])
    assert_refused(capsys, "no such label mask file", "colors", "--images", i, "--masks",
                   tmp_path / "none.png", "--out", out, leaves=[out])
    (tmp_path / "empty.png").write_bytes(b"")
    assert_refused(capsys, "not a readable image", "colors", "--images", tmp_path / "empty.png",
                   "--masks", m, "--out", out, leaves=[out])
    assert_refused(capsys, "need one label mask per image", "colors", "--images", i, i,
                   "--masks", m, "--out", out, leaves=[out])
    # white balance: bad colour model files are named with their field
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "jaxmocap.colors", "version": 1, "colors": [
        {"mean": [1, 2, float("nan")], "cov": np.eye(3).tolist()}]}))
    wb = tmp_path / "wb.json"
    assert_refused(capsys, "bad.json: colors[0].mean", "colors", "--white-balance", "--colors",
                   bad, "--images", i, "--masks", m, "--out", wb, leaves=[wb])
    assert_refused(capsys, "--white-balance needs --colors", "colors", "--white-balance",
                   "--images", i, "--masks", m, "--out", wb, leaves=[wb])
    assert run_cli(capsys, "colors", "--images", i, "--masks", m, "--out", out)[0] == 0
    two = lab.copy()
    two[two > 2] = 0
    tm = tmp_path / "two.png"
    cv2.imwrite(str(tm), two)
    assert_refused(capsys, "2 colours have >= 20 labelled pixels, need >= 3", "colors",
                   "--white-balance", "--colors", out, "--images", i, "--masks", tm,
                   "--out", wb, leaves=[wb])
    (tmp_path / "dir.json").mkdir()
    assert_refused(capsys, "is a folder", "colors", "--images", i, "--masks", m, "--out",
                   tmp_path / "dir.json")


def test_load_white_balance_errors(tmp_path):
    from jaxmocap.commands.colors import WhiteBalanceFileError

    p = tmp_path / "wb.json"
    p.write_text(json.dumps({"format": "jaxmocap.white_balance", "version": 1,
                             "cameras": {"cam0": [[1, 0], [0, 1]]}}))
    with pytest.raises(WhiteBalanceFileError, match="field 'cameras.cam0': expected a finite"):
        load_white_balance(p, ["cam0"])
    with pytest.raises(WhiteBalanceFileError, match="no entry for camera 'cam1'"):
        load_white_balance(p, ["cam1"])


def test_model_named_by_garment(tmp_path, capsys):
    """With --garment, label k is the garment's k-th colour and the model carries its names,
    so the garment loads against the model with the same colour ids."""
    from jaxmocap.body import default_body
    from jaxmocap.color import load_color_model
    from jaxmocap.io.garment_file import load_garment

    names = ["yellow", "red", "blue", "green"]  # the file's order, not alphabetical
    garment = {"format": "jaxmocap.garment", "version": 1,
               "colours": [{"name": n} for n in names],
               "patches": [{"name": f"p{k}", "geom": g, "colour": names[k]} for k, g in
                           enumerate(("thorax", "abdomen", "l_upper_arm", "r_upper_arm"))]}
    (tmp_path / "garment.json").write_text(json.dumps(garment))
    rng = np.random.default_rng(1)
    i1, m1 = save(tmp_path / "a", *shirt(rng))
    out = tmp_path / "colors.json"
    rc, stdout, err = run_cli(capsys, "colors", "--images", i1, "--masks", m1, "--garment",
                              tmp_path / "garment.json", "--out", out)
    assert rc == 0 and err == [], err
    model = load_color_model(out)
    assert model.names == tuple(names)
    np.testing.assert_allclose(np.asarray(model.mean)[1], COLOURS[1], atol=3)  # label 2 = red
    g = load_garment(tmp_path / "garment.json", default_body(), model)
    assert g.colour_names == tuple(names)
    assert list(np.asarray(g.patch_colour)) == [1, 2, 3, 4]
    assert_refused(capsys, "leave out --names", "colors", "--images", i1, "--masks", m1,
                   "--garment", tmp_path / "garment.json", "--names", "a", "b", "c", "d",
                   "--out", tmp_path / "c2.json")


def test_pf_colours_from_scribbles(tmp_path, capsys):
    """`colors --pf`: label 1 skin, 2 shirt -> a pf_colors.json whose classes are the ML
    Gaussians of the labelled pixels' features (pf.colors.features, variance floors added)."""
    from jaxmocap.pf import colors as PC

    rng = np.random.default_rng(1)
    img = np.full((120, 160, 3), 110.0) + rng.normal(0, 3, (120, 160, 3))
    img[60:120, 65:95] = [40, 70, 190]  # the shirt (the background > 40 px from it is learned)
    cv2.circle(img, (80, 48), 10, (200, 150, 120), -1)  # the face
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    lab = np.zeros((120, 160), np.uint8)
    lab[45:52, 77:84] = 1
    lab[75:95, 70:90] = 2
    i, m = save(tmp_path / "a", img, lab)
    out = tmp_path / "pf.json"
    rc, stdout, err = run_cli(capsys, "colors", "--pf", "--images", i, "--masks", m, "--out",
                              out)
    assert rc == 0 and err == [], err
    c = PC.load_capture_colors(out)
    f = PC.features(img)
    for k, cls in ((1, c.skin), (2, c.shirt)):
        px = f[lab == k].astype(np.float64)
        np.testing.assert_allclose(np.asarray(cls.mean), px.mean(0), rtol=1e-5)
        np.testing.assert_allclose(np.asarray(cls.cov),
                                   np.cov(px.T) + np.diag(PC.MIN_VARIANCE), rtol=1e-4)
    assert_refused(capsys, "give one of them", "colors", "--pf", "--white-balance",
                   "--images", i, "--masks", m, "--out", tmp_path / "x.json")


def shaded_shirt(rng, room=False):
    """The four bands under a brightness ramp 0.55..1.45 along the rows (a lamp's falloff);
    ``room``: label 255 on two wall strips left and right of the bands, of a dull yellow near
    the shirt's yellow (the failure of spot-lit rooms: walls that pass as a shirt colour)."""
    img, lab = shirt(rng)
    ramp = np.linspace(0.55, 1.45, H)[:, None, None]
    img = np.clip(np.round(img.astype(float) * ramp), 0, 255).astype(np.uint8)
    if room:
        wall = np.clip(np.round(np.array([192.0, 180, 48]) * ramp[:, 0]
                                + rng.normal(0, 3, (H, 3))), 0, 255)
        img[:, 0] = img[:, -1] = wall.astype(np.uint8)
        lab[:, 0] = lab[:, -1] = 255
    return img, lab


def test_shading_model_recorded_and_narrower(tmp_path, capsys):
    """`--shading 0.5 4` fits the model for the shading-invariant distance: the file records
    the range, the model equals the API's fit, and its brightness spread is a fraction of the
    plain ML fit's (which holds the ramp)."""
    from jaxmocap.color import fit_color_model, load_color_model

    rng = np.random.default_rng(3)
    img, lab = shaded_shirt(rng)
    i, m = save(tmp_path / "a", img, lab)
    plain, shaded = tmp_path / "plain.json", tmp_path / "shaded.json"
    assert run_cli(capsys, "colors", "--images", i, "--masks", m, "--out", plain)[0] == 0
    rc, stdout, err = run_cli(capsys, "colors", "--images", i, "--masks", m, "--shading", "0.5",
                              "4", "--out", shaded)
    assert rc == 0 and err == [], err
    assert "shading-invariant distance, brightness 0.5..4" in stdout
    assert json.loads(shaded.read_text())["shading"] == [0.5, 4.0]
    assert "shading" not in json.loads(plain.read_text())
    a, b = load_color_model(plain), load_color_model(shaded)
    assert a.shading is None and b.shading == (0.5, 4.0)
    ref = fit_color_model([img], [lab.astype(np.int32)], 4, gain=(0.5, 4.0))
    np.testing.assert_allclose(np.asarray(b.cov), np.asarray(ref.cov), rtol=1e-5)
    for k in range(4):  # variance along the colour's own direction: the shading's
        u = COLOURS[k] / np.linalg.norm(COLOURS[k])
        assert u @ np.asarray(b.cov[k]) @ u < 0.2 * (u @ np.asarray(a.cov[k]) @ u)
    bad = json.loads(shaded.read_text())
    bad["shading"] = [2, 4]
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(Exception, match=r"bad.json: shading: expected \(lo, hi\) with 0 < lo"):
        load_color_model(tmp_path / "bad.json")
    assert_refused(capsys, "--shading: expected (lo, hi) with 0 < lo <= 1 <= hi", "colors",
                   "--images", i, "--masks", m, "--shading", "1.5", "4", "--out",
                   tmp_path / "x.json", leaves=[tmp_path / "x.json"])
    assert_refused(capsys, "--shading applies to the shirt's colour model", "colors", "--pf",
                   "--images", i, "--masks", m, "--shading", "0.5", "4", "--out",
                   tmp_path / "x.json", leaves=[tmp_path / "x.json"])


def test_room_colours_in_white_balance(tmp_path, capsys):
    """`--white-balance --room-label 255`: the room's Gaussians (white-balanced by each
    camera's W) are stored beside W, equal the API's fit of the same pixels, and make the
    tracker's classification call the wall background while the bands stay classified."""
    import jax.numpy as jnp

    from jaxmocap.color import classify, fit_scene_colors, load_color_model
    from jaxmocap.commands.colors import load_room_colors

    rng = np.random.default_rng(4)
    img, lab = shaded_shirt(rng)
    i0, m0 = save(tmp_path / "ref", img, lab)
    model = tmp_path / "colors.json"
    assert run_cli(capsys, "colors", "--images", i0, "--masks", m0, "--shading", "0.5", "4",
                   "--out", model)[0] == 0
    cams = [save(tmp_path / f"cam{c}", *shaded_shirt(rng, room=True)) for c in range(2)]
    out = tmp_path / "wb.json"
    rc, stdout, err = run_cli(capsys, "colors", "--white-balance", "--colors", model,
                              "--images", *[c[0] for c in cams], "--masks",
                              *[c[1] for c in cams], "--room-label", "255", "--room-colors",
                              "2", "--out", out)
    assert rc == 0 and err == [], err
    assert f"room: 2 colours from {4 * H} px (label 255)" in stdout
    Wb = load_white_balance(out, ["cam0", "cam1"])
    room = load_room_colors(out)
    images = [cv2.imread(c[0])[..., ::-1] for c in cams]
    masks = [cv2.imread(c[1], cv2.IMREAD_UNCHANGED) == 255 for c in cams]
    ref = fit_scene_colors(images, masks, list(Wb), 2)
    def by_red(m):
        m = np.asarray(m.mean)
        return m[np.argsort(m[:, 0])]

    np.testing.assert_allclose(by_red(room), by_red(ref), atol=1e-3)
    color = load_color_model(model)
    ids, _ = classify(color, jnp.asarray(Wb[0]), jnp.asarray(images[0]), gain=color.shading,
                      background=room)
    ids0, _ = classify(color, jnp.asarray(Wb[0]), jnp.asarray(images[0]), gain=color.shading)
    ids, ids0, lab0 = np.asarray(ids), np.asarray(ids0), cv2.imread(cams[0][1], 0)
    walls = np.s_[:, [0, -1]]
    assert (ids0[walls] > 0).mean() > 0.5  # without the room: the wall passes as yellow
    assert (ids[walls] == 0).mean() > 0.8
    for k in (1, 2, 3):  # colours unlike the wall: classified as without the room
        np.testing.assert_array_equal(ids[lab0 == k], ids0[lab0 == k])
        assert (ids[lab0 == k] == k).mean() > 0.95
    # the yellow band, a few sd from the wall, loses part of its pixels to it (the trade-off)
    assert 0.3 < (ids[lab0 == 4] == 4).mean() < (ids0[lab0 == 4] == 4).mean()
    plain = tmp_path / "plain_wb.json"
    assert run_cli(capsys, "colors", "--white-balance", "--colors", model, "--images",
                   cams[0][0], "--masks", m0, "--names", "cam0", "--out", plain)[0] == 0
    assert load_room_colors(plain) is None
    assert_refused(capsys, "--room-label 3: labels 1..4 are the shirt's colours", "colors",
                   "--white-balance", "--colors", model, "--images", cams[0][0], "--masks",
                   cams[0][1], "--room-label", "3", "--out", tmp_path / "x.json",
                   leaves=[tmp_path / "x.json"])
    assert_refused(capsys, f"{2 * H} pixels carry the room label 255, need >= 160", "colors",
                   "--white-balance", "--colors", model, "--images", cams[0][0], "--masks",
                   cams[0][1], "--room-label", "255", "--out", tmp_path / "x.json",
                   leaves=[tmp_path / "x.json"])
    assert_refused(capsys, "give it with --white-balance", "colors", "--images", i0, "--masks",
                   m0, "--room-label", "255", "--out", tmp_path / "x.json",
                   leaves=[tmp_path / "x.json"])


def test_masks_of_another_tool_through_a_label_map(tmp_path, capsys):
    """Issue 36: masks labelled 0..3 with 255 = unlabelled and 254 = room (another tool's
    convention) and a --labels map give exactly the model and white balance our own masks
    give; values the map does not know are refused naming the mask and the map."""
    rng = np.random.default_rng(4)
    img, lab = shirt(rng)
    theirs = np.full_like(lab, 255)
    order = [2, 0, 3, 1]  # their value of our colour k (red green blue yellow)
    for k, v in enumerate(order):
        theirs[lab == k + 1] = v
    theirs[:2, :] = 254  # a strip of room along the top
    i1, m1 = save(tmp_path / "ours", img, lab)
    cv2.imwrite(str(tmp_path / "theirs_labels.png"), theirs)
    m2 = str(tmp_path / "theirs_labels.png")
    names = ["red", "green", "blue", "yellow"]
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps({**{str(v): names[k] for k, v in enumerate(order)},
                                  "255": "unlabelled", "254": "room"}))
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert run_cli(capsys, "colors", "--images", i1, "--masks", m1, "--names", *names,
                   "--out", a)[0] == 0
    assert run_cli(capsys, "colors", "--images", i1, "--masks", m2, "--labels", labels,
                   "--names", *names, "--out", b)[0] == 0
    assert json.loads(a.read_text())["colors"] == json.loads(b.read_text())["colors"]
    # without --names the map's order (by value) names the model
    c = tmp_path / "c.json"
    assert run_cli(capsys, "colors", "--images", i1, "--masks", m2, "--labels", labels,
                   "--out", c)[0] == 0
    assert [x["name"] for x in json.loads(c.read_text())["colors"]] == \
        ["green", "yellow", "red", "blue"]
    # white balance: the room strip becomes room colours
    wb = tmp_path / "wb.json"
    rc, out, _ = run_cli(capsys, "colors", "--white-balance", "--colors", a, "--images", i1,
                         "--masks", m2, "--labels", labels, "--room-colors", "2", "--out", wb)
    assert rc == 0 and "from 80 px (label 5)" in out  # the 2-row strip, after the 4 colours
    labels.write_text(json.dumps({"0": "red", "255": "unlabelled"}))
    assert_refused(capsys, "mask values [1, 2, 3, 254] are not in the label map", "colors",
                   "--images", i1, "--masks", m2, "--labels", labels, "--out", c)
