"""`jaxmocap colors`: the fitted model equals NumPy's ML Gaussians of the labelled pixels;
the white balance undoes a known colour cast; bad scribbles and files are refused clearly."""

import json

import cv2
import numpy as np
import pytest
from test_cli_common import assert_refused, run_cli

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
    from jaxmocap.garment import load_garment

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
