"""
``friction_curves.png`` (dgp-replay, the robot demo): the learned friction against velocity.

Drawn from a model fitted to a known friction: the curve is the model's answer along each joint's
velocity with the others at rest, plus the joint's offset; the file is a PNG; the replay of a
robot bag writes it beside its other plots.
"""
import numpy as np

from dgp_ros.apps.friction_plot import _curves, friction_curves
from dgp_ros.gp import DiagDGP


def _model():
    rng = np.random.default_rng(0)
    Q = rng.uniform(-1.0, 1.0, (150, 2))
    T = 0.5 * Q + 0.3 * np.tanh(Q / 0.05) + 0.01 * rng.normal(size=Q.shape)
    return DiagDGP(prior='friction').fit(Q, T), Q, T


def test_the_curve_is_the_models_answer_along_each_joint():
    m, Q, T = _model()
    v, tau, band, prior, param = _curves(m, Q, 1)
    V = np.zeros((v.size, 2))
    V[:, 1] = v
    assert np.allclose(tau, m.predict(V)[:, 1])
    assert np.all(band[0] <= tau + 1e-12) and np.all(tau <= band[1] + 1e-12)
    assert np.allclose(prior, m.mean_.force(V)[:, 1])
    assert np.allclose(param, prior)        # no elements from every sample in this prior
    # the learned curve is the friction it was fitted to
    assert np.max(np.abs(tau - (0.5 * v + 0.3 * np.tanh(v / 0.05)))) < 0.1


def test_the_png_is_written(tmp_path):
    m, Q, T = _model()
    p = friction_curves(tmp_path / 'friction_curves.png', m, Q, T, names=['a', 'b'],
                        confidence=[0.5, 1.0])
    assert p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n' and p.stat().st_size > 10_000


def test_a_joint_with_an_element_from_every_sample_shows_both_curves(tmp_path):
    """The prior with the element and the parametric part alone are drawn apart."""
    from dgp_ros.gp.joint_element import JointElementMean, M_BASIS, VelocityBasis
    m, Q, T = _model()
    W = np.zeros((2, M_BASIS))
    W[1, :3] = [0.2, -0.1, 0.05]
    m.posterior_.mean = JointElementMean(m.mean_, VelocityBasis(np.ones(2)), W)
    v, tau, band, prior, param = _curves(m, Q, 1)
    V = np.zeros((v.size, 2))
    V[:, 1] = v
    assert np.allclose(param, m.mean_.base.force(V)[:, 1])
    assert np.allclose(prior, m.mean_.force(V)[:, 1]) and np.max(np.abs(prior - param)) > 0.01
    p = friction_curves(tmp_path / 'f.png', m, Q, T, element_scores=[None, 0.8])
    assert p.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
