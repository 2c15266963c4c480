"""jaxmocap.metrics.depth_lateral: the error split along the rig's line of sight, on cases
computed by hand."""

import numpy as np

from jaxmocap.metrics import depth_lateral


def test_hand_computed_cases():
    # the line of sight along z: the z error is depth, (3, 4) cm across it is 5 cm lateral
    d, lat = depth_lateral(np.array([0.03, 0.04, 2.12]), np.array([0.0, 0.0, 2.0]), np.zeros(3))
    np.testing.assert_allclose([d, lat], [0.12, 0.05], atol=1e-12)
    # a diagonal line of sight: u = (0.6, 0.8, 0) from (1, 1, 1) to (4, 5, 1); an error of 0.2
    # back toward the rig along u and 0.1 along (0.8, -0.6, 0) and 0.1 along z
    gt = np.array([4.0, 5.0, 1.0])
    u, v = np.array([0.6, 0.8, 0.0]), np.array([0.8, -0.6, 0.0])
    pred = gt - 0.2 * u + 0.1 * v + np.array([0.0, 0.0, 0.1])
    d, lat = depth_lateral(pred, gt, np.array([1.0, 1.0, 1.0]))
    np.testing.assert_allclose([d, lat], [0.2, np.sqrt(0.02)], atol=1e-12)


def test_batches_and_the_components_make_up_the_error(rng):
    gt = rng.normal(size=(5, 4, 3)) + np.array([0.0, 0.0, 3.0])
    pred = gt + 0.1 * rng.normal(size=gt.shape)
    d, lat = depth_lateral(pred, gt, np.array([0.0, 0.1, -0.2]))
    assert d.shape == lat.shape == (5, 4) and (d >= 0).all() and (lat >= 0).all()
    np.testing.assert_allclose(d**2 + lat**2, np.sum((pred - gt) ** 2, axis=-1), rtol=1e-12)
    # a joint at the right place has neither
    d0, l0 = depth_lateral(gt, gt, np.zeros(3))
    assert not d0.any() and not l0.any()


def test_facing_angle_on_hand_placed_views():
    """A body facing +x at the origin (left shoulder +y): a camera ahead on +x is at 0 deg, one
    on +y (the body's left) at 90, one behind at 180, one at 45 deg ahead-left at 45; turning
    the body by 30 deg about z shifts each angle by 30 (a frame of its own)."""
    from jaxmocap.metrics import facing_angle

    centres = np.array([[3.0, 0, 1.5], [0, 3.0, 1.5], [-3.0, 0, 1.5], [2.0, 2.0, 1.5]])
    th = np.radians(30.0)
    rot = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    l_sh = np.array([[0, 0.2, 1.4], rot @ [0, 0.2, 1.4]])
    r_sh = np.array([[0, -0.2, 1.4], rot @ [0, -0.2, 1.4]])
    neck = np.array([[0, 0, 1.5], [0, 0, 1.5]])
    a = facing_angle(l_sh, r_sh, neck, centres)
    np.testing.assert_allclose(a[0], [0, 90, 180, 45], atol=1e-9)
    np.testing.assert_allclose(a[1], [30, 60, 150, 15], atol=1e-9)
