"""The head as a fitted sphere (:mod:`jaxmocap.trackers.stereo_pf.head`) against a sphere of
known centre ray-cast into a stereo pair (numpy: the ray-sphere intersection per pixel), lit
from one side so that only part of it is skin: the fit finds the centre, the lit skin's
triangulated centroid does not."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from _foreign_body import foreign_urdf

from jaxmocap import camera as camlib
from jaxmocap.body import keypoint_index, keypoints, load_body
from jaxmocap.trackers.stereo_pf import head

W, H, F = 320, 240, 300.0
RADIUS = 0.1


def _cams():
    return camlib.stack_cameras([
        camlib.look_at(jnp.array([2.5, y, 1.5]), jnp.array([0.0, y, 1.5]), width=W, height=H,
                       fx=F) for y in (0.055, -0.055)])  # fmt: skip


def _lit_sphere(cams, centre, light, shirt_below=False):
    """(skin (2, H, W), foreground (2, H, W)): the sphere's pixels whose surface faces
    ``light`` by more than 0.2 (lit skin); the dark side is neither skin nor shirt. With
    ``shirt_below`` the image rows below the sphere's lowest point are shirt."""
    skins, fgs = [], []
    v, u = np.mgrid[0:H, 0:W]
    for k in range(2):
        K, R, t = (np.asarray(a[k], np.float64) for a in (cams.K, cams.R, cams.t))
        eye = -R.T @ t
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)],
                     -1) @ R  # world rays (R^T d per pixel)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        oc = eye - centre
        b = d @ oc
        disc = b**2 - (oc @ oc - RADIUS**2)
        hit = disc > 0
        s = -b - np.sqrt(np.where(hit, disc, 0.0))
        normal = (eye + s[..., None] * d - centre) / RADIUS
        skins.append(hit & (normal @ light > 0.2))
        fg = np.zeros((H, W), bool)
        if shirt_below:
            low = camlib.project(camlib.unstack_cameras(cams)[k],
                                 jnp.asarray(centre - [0, 0, RADIUS * 1.05]))
            fg[int(np.ceil(float(low[1]))):] = True
        fgs.append(fg)
    return np.stack(skins), np.stack(fgs)


def _centroid_point(cams, skin):
    uv = [np.argwhere(skin[k])[:, ::-1].mean(axis=0) for k in range(2)]
    return np.asarray(camlib.triangulate(cams, jnp.asarray(np.stack(uv))), np.float64)


@pytest.mark.parametrize("light, shirt", [((0.0, -1.0, 0.4), False), ((0.5, 0.6, 0.6), True)])
def test_sphere_fit_finds_a_half_lit_head(light, shirt):
    cams = _cams()
    centre = np.array([0.05, 0.02, 1.55])
    light = np.asarray(light) / np.linalg.norm(light)
    skin, fg = _lit_sphere(cams, centre, light, shirt)
    assert 0.2 < skin.sum() / (np.pi * (F * RADIUS / 2.45) ** 2) / 2 < 0.8  # partly lit
    start = _centroid_point(cams, skin)
    c = head.fit_head(cams, skin, fg, start, RADIUS)
    assert c is not None
    view = centre - np.asarray(camlib.camera_center(camlib.unstack_cameras(cams)[0]))
    view /= np.linalg.norm(view)

    def split(p):  # (depth, lateral) error, m
        d = p - centre
        return abs(d @ view), np.linalg.norm(d - (d @ view) * view)

    (dep, lat), (dep0, lat0) = split(c), split(start)
    assert lat0 > 0.02  # the lit centroid is off to the lit side
    assert lat < 0.01 < lat0  # the rim places the head across the view within 1 cm
    assert np.hypot(dep, lat) < min(0.04, np.hypot(dep0, lat0))  # the 4 cm


def test_no_fit_without_an_outline():
    cams = _cams()
    skin = np.zeros((2, H, W), bool)
    assert head.fit_head(cams, skin, skin, np.array([0.0, 0.0, 1.5]), RADIUS) is None


def test_head_sphere_of_a_body(tmp_path):
    """The foreign body's skull: a sphere of radius 0.105 m, 0.09 m above its head link; the
    offset leads from its centre to the head keypoint."""
    model = load_body(foreign_urdf(tmp_path / "foreign.urdf"))
    r, off = head.head_sphere(model)
    assert r == pytest.approx(0.105)
    kp = np.asarray(keypoints(model, jnp.zeros(model.n_dof)))[keypoint_index(model, "head")[0]]
    from jaxmocap.body.chain import fk

    tr = np.asarray(fk(model.chain, jnp.zeros(model.n_dof)))
    skull = tr[model.chain.link_names.index("head")][:3, 3] + [0, 0, 0.09]
    np.testing.assert_allclose(skull + off, kp, atol=1e-6)


def test_make_params_takes_the_head_sphere_from_the_body(tmp_path):
    from jaxmocap.trackers import stereo_pf as sp

    model = load_body(foreign_urdf(tmp_path / "foreign.urdf"))
    cams = camlib.unstack_cameras(_cams())
    assert sp.make_params(cams, model=model).head_sphere is None  # off by default
    params = sp.make_params(cams, model=model, images=sp.Images(head_sphere=True))
    assert params.head_sphere[0] == pytest.approx(0.105)
