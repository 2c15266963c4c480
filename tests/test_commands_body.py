"""``--body`` / ``--garment`` through the commands, the database's body record, and IK
covariances for any body (issue: your body, your shirt).

Oracles: the digests of the loaded body and garment, the bundled covariance file, rest-pose
joint axes computed from the chain.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest
from _foreign_body import foreign_urdf

from jaxmocap.body import body_digest, default_body, load_body
from jaxmocap.body.roles import rest_transforms
from jaxmocap.cli import main
from jaxmocap.garment import garment_digest, garment_from_model
from jaxmocap.io.garment_file import save_garment
from jaxmocap.trackers.shirt.covariances import (
    AXIS_COS,
    DEFAULT_BLEND_STD,
    covariances_for_body,
    trained_covariances,
)


def _axes(model):
    rest = rest_transforms(model.chain)
    out = {}
    for link, (_, _, d) in enumerate(model.chain.topology):
        if d >= 6:
            a = rest[link][:3, :3] @ np.asarray(model.chain.joint_axis[link], float)
            out[model.chain.dof_names[d]] = a / np.linalg.norm(a)
    return out


def test_covariances_transfer_by_role(tmp_path):
    bundled, foreign = default_body(), load_body(foreign_urdf(tmp_path / "subject.urdf"))
    cov0 = trained_covariances(bundled.n_dof)
    same, defaults = covariances_for_body(bundled)
    assert defaults == () and np.array_equal(np.asarray(same.blend), np.asarray(cov0.blend))
    cov, defaults = covariances_for_body(foreign)
    assert np.asarray(cov.blend).shape == (foreign.n_dof,)
    np.testing.assert_array_equal(np.asarray(cov.blend)[:6], np.asarray(cov0.blend)[:6])
    np.testing.assert_array_equal(np.asarray(cov.centroid), np.asarray(cov0.centroid))
    src, tgt = _axes(bundled), _axes(foreign)
    src_roles, b0 = dict(bundled.roles.joints), np.asarray(cov0.blend)
    n_matched = 0
    for role, dofs in foreign.roles.joints:  # each arm/spine DOF: the bundled DOF of its role
        for name in dofs:                    # turning about the most parallel axis
            i = foreign.chain.dof_names.index(name)
            cands = [(abs(tgt[name] @ src[c]), c) for c in src_roles[role]]
            cos, best = max(cands)
            if cos >= AXIS_COS:
                n_matched += 1
                j = bundled.chain.dof_names.index(best)
                assert np.asarray(cov.blend)[i] == b0[j] and name not in defaults
    assert n_matched >= 14  # both shoulders (3+3), elbows, spine, neck at least
    legs = [n for n in foreign.chain.dof_names[6:] if "hip" in n or "knee" in n]
    assert legs and set(legs) <= set(defaults)
    for n in defaults:
        assert np.asarray(cov.blend)[foreign.chain.dof_names.index(n)] == DEFAULT_BLEND_STD**2


@pytest.mark.slow
def test_build_db_for_your_body_and_refusal(tmp_path, capsys):
    """build-db --body --garment records the body and shirt; track refuses a database built
    for another body or shirt in one line, before any frame is read."""
    body_file = foreign_urdf(tmp_path / "subject.urdf")
    body = load_body(body_file)
    garment = garment_from_model(body)
    save_garment(tmp_path / "garment.json", garment, body)
    db = tmp_path / "db.npz"
    rc = main(["build-db", "--body", str(body_file), "--garment", str(tmp_path / "garment.json"),
               "--size", "300", "--out", str(db), "--quiet"])
    assert rc == 0
    with np.load(db) as f:
        meta = json.loads(str(f["meta"]))
        assert f["poses"].shape == (300, body.n_dof)
    assert meta["body_digest"] == body_digest(body)
    assert meta["garment_digest"] == garment_digest(garment)
    assert meta["dof_names"] == list(body.chain.dof_names)
    capsys.readouterr()
    from jaxmocap.camera import look_at
    from jaxmocap.io.cameras import save_cameras

    save_cameras(tmp_path / "cams.json", [look_at([2.5, 0, 1.2], [0, 0, 1.1], width=32,
                                                  height=24, fx=30.0)])  # fmt: skip
    (tmp_path / "cam0").mkdir()
    import cv2

    cv2.imwrite(str(tmp_path / "cam0" / "0.png"), np.zeros((24, 32, 3), np.uint8))
    from jaxmocap.color import ColorModel, save_color_model
    from jaxmocap.garment import default_garment

    for name, g in (("colors", garment), ("colors10", default_garment(default_body()))):
        save_color_model(tmp_path / f"{name}.json", ColorModel(
            mean=jnp.asarray(g.colours) * 200 + 20,
            cov=jnp.stack([jnp.eye(3) * 50.0] * g.n_colours), names=g.colour_names))  # fmt: skip
    out = tmp_path / "out"
    base = ["track", "--cameras", str(tmp_path / "cams.json"), str(tmp_path / "cam0"),
            "--db", str(db), "--out", str(out), "--quiet"]  # fmt: skip
    c3 = ["--colors", str(tmp_path / "colors.json")]
    c10 = ["--colors", str(tmp_path / "colors10.json")]
    other = json.loads((tmp_path / "garment.json").read_text())  # same patches, other dyes
    for c in other["colours"]:
        c["rgb"] = [min(1.0, v + 0.05) for v in c["rgb"]]
    (tmp_path / "other.json").write_text(json.dumps(other))
    for extra, what in ((c10, f"built for a body with {body.n_dof} DOFs"),
                        (c3 + ["--body", str(body_file), "--garment", str(tmp_path / "other.json")],
                         "built for another shirt")):  # fmt: skip
        rc = main(base + extra)
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and what in err[0] and str(db) in err[0], err
        assert not out.exists()
    rc = main(base + c3 + ["--method", "pf", "--garment", str(tmp_path / "garment.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and "--garment describes the colour shirt" in err[-1]
