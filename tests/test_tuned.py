"""Tests of jaxmocap.tuned (the tuned-parameters file of `jaxmocap tune`): exact round trip,
field refusals naming the field, the digest checks (API and `track --tuned`, exit code 2 before
any work), role-shared covariances carried as the bundled trained ones are."""

import json

import numpy as np
import pytest
from test_cli import assert_refused

from jaxmocap.body import body_digest, default_body
from jaxmocap.garment import default_garment, garment_digest, single_colour_garment
from jaxmocap.trackers.shirt.covariances import transfer_covariances
from jaxmocap.tuned import TunedFileError, TunedParameters, load_tuned


def _shirt(rng, body, transfer="none"):
    n = body.n_dof
    A = rng.normal(size=(n, n))
    return TunedParameters(
        tracker="shirt", transfer=transfer, body_digest=body_digest(body),
        dof_names=tuple(body.chain.dof_names), garment_digest=garment_digest(
            default_garment(body)) if transfer == "none" else None,
        parameters={"ik_centroid": np.array([[4.1, 0.3], [0.3, 2.0 / 3.0]]),
                    "ik_blend": A @ A.T / n + 0.1 * np.eye(n),
                    "ik_prior": rng.uniform(0.01, 0.3, n)},
        tuned_on={"sequences": ["shirt_00"]}, loss={"before": 0.2, "after": 0.1})


def test_round_trip_is_exact(tmp_path, rng):
    body = default_body()
    t = _shirt(rng, body)
    t.save(tmp_path / "t.json")
    back = TunedParameters.load(tmp_path / "t.json")
    for k, v in t.parameters.items():
        np.testing.assert_array_equal(back.parameters[k], v)  # bit for bit
    assert (back.tracker, back.body_digest, back.garment_digest, back.transfer,
            back.dof_names, back.tuned_on, back.loss) == (
        t.tracker, t.body_digest, t.garment_digest, t.transfer, t.dof_names, t.tuned_on, t.loss)
    cov = back.ik_covariances(body)
    np.testing.assert_array_equal(np.asarray(cov.blend), t.parameters["ik_blend"])
    pf = TunedParameters("pf", {"sigma_g": np.float64(0.21), "sigma_d": np.float64(0.05)},
                         body_digest(body))
    pf.save(tmp_path / "pf.json")
    assert TunedParameters.load(tmp_path / "pf.json").cue_widths() == {"sigma_g": 0.21,
                                                                      "sigma_d": 0.05}


def test_role_shared_parameters_are_carried_as_the_trained_ones(tmp_path, rng):
    """transfer = role: defined on the bundled body's DOFs, another body gets them through
    transfer_covariances (the same matching as the bundled trained covariances)."""
    from jaxmocap.body.scale import rename_body

    bundled = default_body()
    t = _shirt(rng, bundled, "role")
    t = TunedParameters(**{**t.__dict__, "parameters": {**t.parameters, "ik_blend":
                                                        rng.uniform(0.01, 0.2, bundled.n_dof)}})
    t.save(tmp_path / "r.json")
    other = rename_body(bundled, "mixamo")
    assert body_digest(other) != body_digest(bundled)
    got = load_tuned(tmp_path / "r.json", "shirt", other).ik_covariances(other)
    want, _ = transfer_covariances(t.ik_covariances(bundled), bundled, other)
    np.testing.assert_array_equal(np.asarray(got.blend), np.asarray(want.blend))
    np.testing.assert_array_equal(np.asarray(got.prior), np.asarray(want.prior))


def test_malformed_fields_and_mismatches_are_refused_naming_the_field(tmp_path, rng):
    body = default_body()
    t = _shirt(rng, body)
    doc = t.to_json()

    def refused(match, **change):
        p = tmp_path / "bad.json"
        p.write_text(json.dumps({**doc, **change}))
        with pytest.raises(TunedFileError, match=match) as e:
            TunedParameters.load(p)
        assert "bad.json" in str(e.value) and "\n" not in str(e.value)

    refused("field 'format'", format="other")
    refused("field 'tracker'", tracker="kalman")
    refused("field 'parameters'", parameters={"ik_centroid": [[1, 0], [0, 1]]})
    refused("field 'parameters.ik_centroid'", parameters={**doc["parameters"],
                                                          "ik_centroid": [[1, 2], [2, 1]]})
    refused("field 'parameters.ik_prior'", parameters={**doc["parameters"],
                                                       "ik_prior": [-1.0] * body.n_dof})
    refused("field 'transfer'", transfer="any")
    # digests: another body, another shirt, another tracker
    from jaxmocap.body.scale import rename_body

    with pytest.raises(TunedFileError, match="field 'body_digest'"):
        t.check_for("shirt", rename_body(body, "left_right"))
    with pytest.raises(TunedFileError, match="field 'garment_digest'"):
        t.check_for("shirt", body, single_colour_garment(body, (0.2, 0.3, 0.8)))
    with pytest.raises(TunedFileError, match="field 'tracker'"):
        t.check_for("pf", body)
    t.check_for("shirt", body, default_garment(body))  # the right ones pass


def test_track_refuses_a_file_of_another_body_with_exit_code_2(tmp_path, rng, capsys):
    """`track --tuned` checks the digests before the colour model, database or compile."""
    import cv2

    from jaxmocap.camera import look_at
    from jaxmocap.io.cameras import save_cameras

    body = default_body()
    t = _shirt(rng, body)
    doc = t.to_json()
    doc["body_digest"] = "0123456789abcdef"
    (tmp_path / "t.json").write_text(json.dumps(doc))
    save_cameras(tmp_path / "one.json", [look_at([2.5, 0, 1.2], [0, 0, 1.1], width=48,
                                                 height=36, fx=40.0)])
    d = tmp_path / "cam0"
    d.mkdir()
    cv2.imwrite(str(d / "0.png"), np.zeros((36, 48, 3), np.uint8))
    out = tmp_path / "out"
    line = assert_refused(capsys, "field 'body_digest' is 0123456789abcdef", "track",
                          "--cameras", tmp_path / "one.json", d, "--out", out, "--quiet",
                          "--tuned", tmp_path / "t.json", leaves=[out])
    assert "t.json" in line
    assert_refused(capsys, "field 'tracker' is 'shirt'", "track", "--method", "pf",
                   "--cameras", tmp_path / "one.json", d, "--out", out, "--quiet", "--tuned",
                   tmp_path / "t.json", leaves=[out])
