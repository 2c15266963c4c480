"""A lamp switched off mid-way in a rendered sequence (Wang §5.2 steps 1 and 5, colour only):
benchmarks/experiments/wang_lamp.py run at a tiny scale, scored against the renderer's
ground-truth colour-id maps; and the scene's ``lamp_share`` setting that makes the step strong."""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.experiments import wang_lamp  # the experiment, imported (pytest pythonpath ".")
from jaxmocap.synth import SceneConfig
from jaxmocap.synth.scene import (
    FLUORESCENT_RGB,
    TUNGSTEN_RGB,
    SceneError,
    illuminant_schedule,
)


def test_lamp_share_default_is_the_original_mix():
    # default (None): bit-identical to M_t = diag(c_f + L_t c_l) / mean(c_f + c_l)
    cfg = SceneConfig(drift=0.3, lamp_off=5)
    M, _ = illuminant_schedule(cfg, 8)
    cf, cl = np.array(FLUORESCENT_RGB), np.array(TUNGSTEN_RGB)
    level = 1 + 0.3 * np.sin(2 * np.pi * (np.arange(8) / cfg.fps) / 4.0)
    level[5:] = 0.0
    ref = (cf[None] + level[:, None] * cl[None]) / np.mean(cf + cl)
    np.testing.assert_array_equal(np.diagonal(M, axis1=1, axis2=2), ref)
    # the same mix written as a share: s = mean(c_l) / mean(c_f + c_l) (about 0.48)
    s = float(np.mean(cl) / np.mean(cf + cl))
    M_s, _ = illuminant_schedule(dataclasses.replace(cfg, lamp_share=s), 8)
    np.testing.assert_allclose(M_s, M, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("s", [0.3, 0.7, 0.9])
def test_lamp_share_sets_the_lamp_part_of_the_light(s):
    M, _ = illuminant_schedule(SceneConfig(lamp_share=s, lamp_off=1), 2)
    on, off = np.diag(M[0]), np.diag(M[1])
    cf, cl = np.array(FLUORESCENT_RGB), np.array(TUNGSTEN_RGB)
    np.testing.assert_allclose(on.mean(), 1.0, rtol=1e-12)  # nominal brightness, lamp on
    np.testing.assert_allclose(off.mean(), 1 - s, rtol=1e-12)  # lamp off: the rest
    np.testing.assert_allclose((on - off) / s, cl / cl.mean(), rtol=1e-12)  # lamp's colour
    np.testing.assert_allclose(off / (1 - s), cf / cf.mean(), rtol=1e-12)


def test_lamp_share_validation_and_round_trip():
    cfg = SceneConfig(lamp_share=0.7, lamp_off=3)
    d = json.loads(cfg.to_json())["scene"]
    assert d["lamp_share"] == 0.7 and SceneConfig.from_dict(d) == cfg
    assert SceneConfig.from_dict({**d, "lamp_share": None}).lamp_share is None
    assert "lamp_share" in SceneConfig().to_dict()  # null by default
    for bad in (0.0, 1.0, -0.2, 1.5):  # in range? (the constructor also type-checks)
        with pytest.raises(SceneError, match="field 'lamp_share'"):
            SceneConfig(lamp_share=bad)
    for bad in (0, 1, 1.5, "0.5", True, [0.5]):  # JSON: range and type
        with pytest.raises(SceneError, match=r"where\.json: field 'lamp_share'"):
            SceneConfig.from_dict({"lamp_share": bad}, "where.json")


@pytest.fixture(scope="module")
def result():
    return wang_lamp.run(wang_lamp.render("test", jnp.float64))


def test_lamp_off_is_darker_and_bluer(result):
    cfg = result["config"]
    assert cfg["lamp_share"] == wang_lamp.LAMP_SHARE
    M, _ = illuminant_schedule(SceneConfig.from_dict(cfg), cfg["n_frames"])
    k = cfg["lamp_off"]
    on, off = np.diag(M[k - 1]), np.diag(M[k])
    assert np.all(off < 0.45 * on)  # a real step in every channel (measured 0.22/0.31/0.44)
    assert off.mean() < 0.35 * on.mean()  # 0.3 of the light is left
    assert off[2] / off[0] > 2 * on[2] / on[0]  # blue/red ratio more than doubles (x2.05)


def test_reference_illuminations_carry_the_step(result):
    k = result["lamp_off"]
    refs, none, fixed = (np.array(result[m]["accuracy"]) for m in wang_lamp.METHODS)
    print({m: np.round(result[m]["accuracy"], 3).tolist() for m in wang_lamp.METHODS})
    # before the step all methods classify most shirt pixels correctly (measured 0.91-0.99)
    assert np.all(refs[:k] > 0.85) and np.all(none[:k] > 0.85) and np.all(fixed[:k] > 0.85)
    # the step frame: the carried W classifies < 40% of the shirt region, so step 1 falls back
    # to the stored matrices (the lamp-off W of the pre segment) -- on that frame only
    used = result["references"]["used_reference"]
    assert used[k] and not any(used[:k]) and not any(used[k + 1 :])
    assert result["no_references"]["classified_fraction"][k] < 0.4  # measured 0.14
    # with references: every frame from the step on is >= 90% correct (measured 0.97-0.98)
    assert np.all(refs[k:] >= 0.9)
    # without references W is carried (no re-fit below 40% classified) and accuracy collapses
    # and stays collapsed (measured 0.09-0.10); a fixed W0 too (0.15-0.17)
    assert np.all(np.array(result["no_references"]["classified_fraction"][k:]) < 0.4)
    assert np.all(none[k:] < 0.2) and np.all(fixed[k:] < 0.3)
    # the stored reference set: W0 and the pre segment's lamp-off W (no reference added later)
    assert result["references"]["n_references"] == 2
    # classified pixels are nearly all right (false positives over shirt pixels, measured 0)
    assert max(result["references"]["false_positive"]) < 0.02
