"""
Generated C++ of frozen models against Python and the frozen node (issue 43).

The models, each trained once per session on short data: a Full-D arm model (7 joints, the
eigenvalue floor ``psd-clip``, earned gains below 1: the per-joint blend), a Diag arm model with
a URDF regressor correction and offsets (the Panda's kinematics), an A320 model (3 velocities,
a domain proof: the C2 blend), a Diag arm model with per-joint elements in its prior, and two
models of an aircraft-like stream whose prior carries the couplings of the airspeed's column
(``gp.coupled``: one with a zero base, one with a friction base and earned gains: the blend
joint by joint toward the coupled prior, then projected). Each header is compiled with the
system compiler
(``-std=c++17 -Wall -Wextra -Werror -O2``; skipped with the reason where there is none) and
evaluated on random velocities inside the data and 10-30x outside, against
``load_model(M)`` proven as the node proves it (``predict``, ``damping_matrix``,
``predict_residual``) and against the frozen node's published answers
(``OnlineEstimator(learning=False, model_path=M)``): relative error below 1e-9, no negative
power (within rounding where the blend toward a coupled prior is projected, as in Python).
The coupled models are also compared where the prior's raw power is negative (its projection
acts). Refusals, the tool's exit status, the example program and the exp are tested too.
"""
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

from dgp_ros.export import export_cpp, ExportError, header_spec, write_header
from dgp_ros.export.toolchain import compile_program, driver, evaluate, find_compiler

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(
    os.path.abspath(__file__)))), 'bench'))
from cpp_export import node_answers, rel, velocities  # noqa: E402,I100

CXX = find_compiler()
needs_cxx = pytest.mark.skipif(CXX is None, reason='no C++ compiler (g++, clang++, c++ or CXX)')
EXAMPLE = os.path.join(os.path.dirname(__file__), '..', '..', 'examples', 'cpp',
                       'friction_along_log.cpp')
TOL = 1e-9


def _arm_data(n=80, N=7, coupling=1.0, seed=0):
    rng = np.random.default_rng(seed)
    Qd = rng.normal(0.0, 0.6, (n, N))
    Tau = (0.3 * Qd + 0.3 * np.tanh(Qd / 0.05) + coupling * np.roll(Qd, 1, axis=1)
           * np.sin(3.0 * Qd) + 0.02 * rng.normal(size=(n, N)))
    return Qd, Tau


def _grounds(N, seed):
    rng = np.random.default_rng(seed)
    return {'model_weight': rng.uniform(0.2, 1.0, N).tolist(),
            'prior_gain': rng.uniform(0.5, 1.0, N).tolist(), 'confidence': [1.0] * N}


def _train(directory):
    """Train the three models (module docstring) into ``directory``; their files by name."""
    from dgp_ros.dynamics import example_robot_urdf, UrdfInverseDynamics
    from dgp_ros.dynamics.conservative import Correction, RegressorBasis
    from dgp_ros.gp import DiagDGP, FullDGP
    from sim_bridge import SimConfig, simulate_approach
    d = pathlib.Path(directory)
    out = {}
    m = FullDGP(prior='friction', n_restarts=0, max_opt_samples=80).fit(*_arm_data())
    assert m.certificate().method == 'psd-clip'
    m.grounds_ = _grounds(7, 1)
    out['full_arm'] = str(d / 'full_arm.npz')
    m.save(out['full_arm'])
    m = DiagDGP(prior='friction+stribeck', n_restarts=0).fit(*_arm_data(coupling=0.2, seed=1))
    names = [f'panda_joint{j}' for j in range(1, 8)]
    with open(example_robot_urdf('panda'), encoding='utf-8') as f:
        urdf = f.read()
    basis = RegressorBasis(UrdfInverseDynamics(urdf=urdf, joints=names), 'test', urdf)
    theta = np.random.default_rng(2).normal(0.0, 0.3, basis.C)
    m.correction_ = Correction(basis, theta, np.linspace(-0.5, 0.7, 7))
    m.grounds_ = _grounds(7, 3)
    out['diag_arm'] = str(d / 'diag_arm.npz')
    m.save(out['diag_arm'])
    f = simulate_approach(SimConfig())
    idx = np.arange(0, 900, 15)
    m = FullDGP(prior='viscous', n_restarts=0).fit(f['q'][idx], f['tau'][idx])
    out['a320'] = str(d / 'a320.npz')
    m.save(out['a320'])
    m = DiagDGP(prior=_element_prior(), n_restarts=0).fit(*_arm_data(coupling=0.1, seed=4))
    m.grounds_ = _grounds(7, 5)
    out['element_arm'] = str(d / 'element_arm.npz')
    m.save(out['element_arm'])
    m = DiagDGP(prior=_element_prior(asymmetric=True), n_restarts=0).fit(
        *_arm_data(coupling=0.1, seed=9))
    out['asym_arm'] = str(d / 'asym_arm.npz')
    m.save(out['asym_arm'])
    m = _coupled_model(friction=False)
    out['coupled'] = str(d / 'coupled.npz')
    m.save(out['coupled'])
    m = _coupled_model(friction=True)
    m.grounds_ = _grounds(3, 7)
    out['coupled_gains'] = str(d / 'coupled_gains.npz')
    m.save(out['coupled_gains'])
    m = _transmission_model()
    m.grounds_ = _grounds(7, 11)
    out['transmission'] = str(d / 'transmission.npz')
    m.save(out['transmission'])
    return out


def _transmission_model():
    """
    Return a Full-D-GP of an arm whose prior carries two coupled transmissions.

    ``gp.transmission``: a motor on joints 5 + 6 and one on 2 - 3, over a friction prior with
    elements; the data carry both motors, which the GP partly corrects.
    """
    from dgp_ros.gp import make_model
    from dgp_ros.gp.transmission import motor_columns, TransmissionMean
    Qd, Tau = _arm_data(n=90, coupling=0.1, seed=12)
    for a, b, s, c in ((5, 6, 1, (0.6, 0.3)), (2, 3, -1, (0.2, 0.1))):
        f = motor_columns(Qd[:, a] + s * Qd[:, b]) @ np.array(c)
        Tau[:, a] += f
        Tau[:, b] += s * f
    prior = TransmissionMean(_element_prior(seed=13), [(5, 6, 1), (2, 3, -1)],
                             [[0.5, 0.2], [0.25, 0.0]])
    return make_model('full', prior=prior, bias=False, passivity='certified').fit(Qd, Tau)


def _aircraft(t):
    """Velocities [alpha, beta, airspeed] and forces of an aircraft-like stream (test/gp)."""
    a = 0.05 + 0.07 * np.sin(0.5 * t + 1.0)
    b = 0.03 * np.sin(0.7 * t)
    V = 90.0 + 6.0 * np.sin(0.3 * t)
    qS = 0.5 * 1.225 * V * V * 122.6
    drag = qS * (0.03 + 0.6 * a * a + 0.4 * b * b + 0.05 * a)
    side = qS * (-0.8 * b + 0.1 * a * b)
    lift = qS * (0.4 + 5.0 * a - 2.0 * a ** 3 + 0.3 * np.abs(b))
    return np.stack([a, b, V], axis=1), np.stack([drag, -side, lift], axis=1)


def _coupled_model(friction, n=150, seed=8):
    """
    Return a certified Full-D-GP of ``_aircraft`` whose prior carries the airspeed's couplings.

    The couplings' weights are fitted to the stream by least squares and clipped to its box
    (``gp.coupled``); the base is zero (the force is the couplings alone) or, with
    ``friction``, a friction prior of random coefficients the GP corrects.
    """
    from dgp_ros.dynamics.parametric import EPS_S, F, FRICTION_EPS, STRIBECK_VS
    from dgp_ros.gp import make_model
    from dgp_ros.gp.coupled import CoupledMean, CouplingBasis
    from dgp_ros.gp.means import BasisFrictionMean
    Q, T = _aircraft(np.linspace(0.0, 12.0, n))
    basis = CouplingBasis(3, [2], [Q[0, 2]])
    W = np.linalg.lstsq(basis.columns(Q), T, rcond=None)[0].T
    base = BasisFrictionMean(np.zeros((3, 1)), (), 0.01, ())
    if friction:
        coef = np.abs(np.random.default_rng(seed).normal(0.0, 1e3, (3, F)))
        base = BasisFrictionMean(coef, FRICTION_EPS, EPS_S, STRIBECK_VS)
    prior = CoupledMean(base, basis.boxed(Q.min(axis=0), Q.max(axis=0)), W)
    return make_model('full', prior=prior, bias=False, passivity='certified').fit(Q, T)


def _element_prior(N=7, seed=6, asymmetric=False):
    """
    Return a frozen friction prior with elements on joints 0, 2 and 5 (gp.joint_element).

    Each element was learned on velocities within +-0.3..1 (its span).

    asymmetric: its base has coefficients of its own for v < 0 (``coef_neg``).
    """
    from dgp_ros.dynamics.parametric import EPS_S, F, FRICTION_EPS, STRIBECK_VS
    from dgp_ros.gp.joint_element import JointElementMean, M_BASIS, VelocityBasis
    from dgp_ros.gp.means import BasisFrictionMean
    rng = np.random.default_rng(seed)
    neg = np.abs(rng.normal(0.0, 0.4, (N, F))) if asymmetric else None
    base = BasisFrictionMean(np.abs(rng.normal(0.0, 0.2, (N, F))), FRICTION_EPS, EPS_S,
                             STRIBECK_VS, coef_neg=neg)
    W = np.zeros((N, M_BASIS))
    W[[0, 2, 5]] = rng.normal(0.0, 0.3, (3, M_BASIS)) / np.arange(1, M_BASIS + 1)
    # the velocities the elements were learned on: the header clips into them as Python does
    span = (-rng.uniform(0.3, 1.0, N), rng.uniform(0.3, 1.0, N))
    return JointElementMean(base, VelocityBasis(rng.uniform(0.5, 2.0, N)), W, span=span)


@pytest.fixture(scope='module')
def models(session_once):
    """Return the three models' files by name, trained once per session (conftest)."""
    return session_once('export_models', _train)


def _compile(specs, directory):
    """Write each spec's header into ``directory`` and compile its driver; {name: exe}."""
    out = {}
    for name, spec in specs.items():
        d = os.path.join(directory, name)
        os.makedirs(d, exist_ok=True)
        hdr = os.path.join(d, 'model.hpp')
        write_header(spec, hdr)
        out[name] = driver(hdr, d, CXX)
    return out


@pytest.fixture(scope='module')
def built(models, session_once, tmp_path_factory):
    """
    Return {name: (spec, proven model, driver executable, workdir, file)}.

    The drivers are compiled once per session; the workdir (the driver's input and output
    files) is this worker's own.
    """
    if CXX is None:
        pytest.skip('no C++ compiler (g++, clang++, c++ or CXX)')
    proven = {name: header_spec(path) for name, path in models.items()}
    exes = session_once('export_drivers',
                        lambda d: _compile({k: v[0] for k, v in proven.items()}, d))
    return {name: proven[name] + (exes[name], str(tmp_path_factory.mktemp(f'cpp_{name}')),
                                  path) for name, path in models.items()}


def _velocities(model, k, seed, far):
    return velocities(model.X_train_, k, far, np.random.default_rng(seed))


def _node_answers(spec, path, Qd):
    """Return the frozen node's published (tau_hat, D) at each velocity (in line, no DDS)."""
    tau, D, guarantee = node_answers(spec, path, Qd)
    assert guarantee == spec.guarantee
    return tau, D


def test_guarantees_as_proven(built):
    assert built['full_arm'][0].guarantee == 'psd' and built['full_arm'][0].clip_delta
    assert built['full_arm'][0].per_joint and built['full_arm'][0].grounds is not None
    assert built['diag_arm'][0].correction['basis'] == 'regressor'
    assert built['a320'][0].guarantee == 'passive-on-domain'
    assert built['a320'][0].weight[0] == 'domain'
    assert list(built['element_arm'][0].prior['element']['joints']) == [0, 2, 5]
    assert 'coef_neg' in built['asym_arm'][0].prior
    assert 'coef_neg' not in built['element_arm'][0].prior
    for name in ('coupled', 'coupled_gains'):
        spec = built[name][0]
        assert spec.guarantee == 'passive-on-domain' and spec.weight[0] == 'domain'
        assert [c['p'] for c in spec.prior['coupled']['columns']] == [2]
    assert built['coupled_gains'][0].grounds is not None
    assert 'coupled' not in built['a320'][0].prior
    motors = built['transmission'][0].prior['coupled']['motors']
    assert [m[:3] for m in motors] == [(5, 6, 1), (2, 3, -1)]
    assert list(built['transmission'][0].prior['element']['joints']) == [0, 2, 5]
    # diagonal plus PSD: its gains and blend are the congruence (coupled_cpp), under 'psd'
    spec = built['transmission'][0]
    assert spec.prior['coupled']['psd'] and spec.guarantee == 'psd' and spec.per_joint


@pytest.mark.parametrize('name', ['full_arm', 'diag_arm', 'a320', 'element_arm', 'asym_arm',
                                  'coupled', 'coupled_gains', 'transmission'])
@pytest.mark.parametrize('far', [False, True], ids=['inside', 'outside'])
def test_equals_python_and_frozen_node(built, name, far):
    spec, model, exe, d, path = built[name]
    Qd = _velocities(model, 1000, 7 + far, far)
    Q = np.random.default_rng(5).uniform(-np.pi, np.pi, Qd.shape)
    out = evaluate(exe, Q, Qd, d)
    assert rel(out['model_damping'], model.predict(Qd)) < TOL
    assert rel(out['model_damping_matrix'], model.damping_matrix(Qd)) < TOL
    assert rel(out['model_residual'], model.predict_residual(q=Q, qd=Qd)) < TOL
    tau, D = _node_answers(spec, path, Qd[:300])
    assert rel(out['damping'][:300], tau) < TOL
    assert rel(out['damping_matrix'][:300], D) < TOL
    assert rel(out['friction'], out['damping'] + out['correction']) < 1e-15
    for key in ('damping', 'model_damping', 'friction'):
        if key == 'friction' and spec.correction is not None:
            continue                     # the correction is conservative, not dissipative
        _assert_passive(spec, Qd, out[key], key)
    if far:
        assert np.any(np.abs(out['damping'] - out['model_damping']) > 0), 'gate never acted'


def _assert_passive(spec, Qd, tau, key):
    """
    Assert ``qd . tau >= 0`` at every velocity.

    Where a coupled prior is projected an answer lies on ``qd . tau = 0``, and the sign of its
    computed power depends on the order of the sum (numpy's einsum gave -4e-18 relative where
    the header's joint-after-joint sum gives 0): its power is summed as the header sums it.
    """
    if 'coupled' in spec.prior:
        power = Qd[:, 0] * tau[:, 0]
        for i in range(1, spec.N):
            power = power + Qd[:, i] * tau[:, i]
    else:
        power = np.einsum('ij,ij->i', Qd, tau)
    assert int((power < 0.0).sum()) == 0, key


def _wind(k, seed):
    """Return k velocities of the coupled models where the prior's raw power is often < 0."""
    rng = np.random.default_rng(seed)
    Q = rng.standard_normal((k, 3)) * np.array([0.1, 0.05, 10.0]) * \
        rng.choice([1.0, 30.0], (k, 1))
    Q[:, 2] += 90.0 * rng.choice([1.0, -1.0, 0.0], k)
    return Q * rng.choice([1e-4, 1e-2, 1.0, 3.0], (k, 1))     # |qd| < max_abs_velocity


@pytest.mark.parametrize('name', ['coupled', 'coupled_gains'])
def test_coupled_prior_where_it_is_projected(built, name):
    # tailwind, reversed flow, hovering: the couplings' raw power is negative at many of these
    # velocities, so the prior's projection (and the blend's) acts, as it does in Python
    spec, model, exe, d, path = built[name]
    Qd = _wind(1000, 21)
    raw = np.einsum('ij,ij->i', Qd, model.mean_.raw_force(Qd))
    assert np.mean(raw < 0) > 0.1
    out = evaluate(exe, Qd, Qd, d)
    assert rel(out['model_damping'], model.predict(Qd)) < TOL
    assert rel(out['model_damping_matrix'], model.damping_matrix(Qd)) < TOL
    tau, D = _node_answers(spec, path, Qd[:300])
    assert rel(out['damping'][:300], tau) < TOL
    assert rel(out['damping_matrix'][:300], D) < TOL
    for key in ('damping', 'model_damping'):
        _assert_passive(spec, Qd, out[key], key)
    assert np.any(np.abs(out['damping'] - out['model_damping']) > 0), 'gate never acted'


def test_coupled_features_are_checked(built, monkeypatch):
    """A basis whose features the export does not know is refused, not exported wrong."""
    from dgp_ros.export import model_spec, spec as S
    model = built['coupled'][1]
    known = S.psi_terms
    monkeypatch.setattr(S, 'psi_terms', lambda n, paired: known(n, paired)[::-1])
    with pytest.raises(ExportError, match='psi_terms'):
        model_spec(model)


def test_correction_matches_the_regressor(built):
    spec, model, exe, d, _ = built['diag_arm']
    Q = np.random.default_rng(9).uniform(-np.pi, np.pi, (200, 7))
    out = evaluate(exe, Q, np.zeros_like(Q), d)
    assert rel(out['conservative'], model.correction_.conservative(Q)) < TOL
    assert rel(out['correction'], model.correction_(Q)) < TOL


def test_a_changed_constant_is_seen(built, tmp_path):
    """Show that the comparison can fail: one weight changed by 1e-6 shows."""
    spec, model, _, _, _ = built['diag_arm']
    spec.elements[0].v = spec.elements[0].v * (1.0 + 1e-6)
    try:
        hdr = str(tmp_path / 'bad.hpp')
        write_header(spec, hdr)
        exe = driver(hdr, str(tmp_path), CXX)
    finally:
        spec.elements[0].v = spec.elements[0].v / (1.0 + 1e-6)
    Qd = _velocities(model, 200, 3, False)
    out = evaluate(exe, Qd, Qd, str(tmp_path))
    assert rel(out['model_damping'], model.predict(Qd)) > 1e-8


@needs_cxx
@pytest.mark.parametrize('elements', [0, 3])
def test_fewer_elements_than_a_vector_holds(tmp_path, elements):
    # an arm whose joints keep their own friction curve or none (gp.select): the kernel sums
    # one element at a time, or nothing at all, and answers as Python does
    from dgp_ros.gp import FullDGP
    from dgp_ros.gp.select import row_choices
    Qd, Tau = _arm_data(n=120, coupling=0.0, seed=4)
    if elements == 0:
        Tau = 0.3 * Qd + 0.3 * np.tanh(Qd / 0.05)              # the prior is the whole law
    else:
        Tau[:, :3] += 0.5 * np.sin(4.0 * Qd[:, :3]) * Qd[:, :3]
    m = FullDGP(prior='friction', elements='auto', couplings='persistent',
                n_restarts=0).fit(Qd, Tau)
    own = sum(c == 'own' for c in row_choices(m.posterior_.structure, m.posterior_.hyper))
    assert own == elements
    spec, model = header_spec(m)
    assert len(spec.elements) == elements
    hdr = str(tmp_path / 'few.hpp')
    write_header(spec, hdr)
    exe = driver(hdr, str(tmp_path), CXX)
    Qs = _velocities(model, 300, 17, False)
    out = evaluate(exe, Qs, Qs, str(tmp_path))
    assert rel(out['model_damping'], model.predict(Qs)) < TOL
    assert rel(out['model_damping_matrix'], model.damping_matrix(Qs)) < TOL


def _cpu_has(flag):
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as f:
            return any(line.startswith('flags') and flag in line.split() for line in f)
    except OSError:
        return False


@pytest.mark.parametrize('variant', ['scalar', 'no-dispatch', 'avx', 'avx512', 'clang++'])
def test_other_builds(built, tmp_path, variant):
    """
    Every build gives the same answers.

    The scalar fallback (no vector extensions), the -O2 build's own 2 lanes without the choice
    at run time (an x86 -O2 build takes the processor's AVX2 or AVX-512 lanes where it has
    them), the vector widths of AVX (4 lanes) and AVX-512 (8), and clang++.
    """
    spec, model, _, _, path = built['full_arm']
    cxx, flags = CXX, ('-O2', '-DDGP_EXPORT_SCALAR')
    if variant == 'no-dispatch':
        flags = ('-O2', '-DDGP_EXPORT_NO_DISPATCH')
    if variant.startswith('avx'):
        if not _cpu_has('avx512f' if variant == 'avx512' else 'avx'):
            pytest.skip(f'this CPU has no {variant.upper()}')
        flags = ('-O2', '-mavx512f' if variant == 'avx512' else '-mavx')
    if variant == 'clang++':
        cxx, flags = find_compiler(('clang++',)) if 'clang' not in CXX else CXX, ('-O2',)
        if cxx is None or 'clang' not in os.path.basename(cxx):
            pytest.skip('clang++ not installed')
    hdr = str(tmp_path / 'm.hpp')
    write_header(spec, hdr)
    exe = driver(hdr, str(tmp_path), cxx, flags=flags)
    Qd = _velocities(model, 300, 11, False)
    out = evaluate(exe, Qd, Qd, str(tmp_path))
    assert rel(out['model_damping'], model.predict(Qd)) < TOL


@needs_cxx
def test_exp_is_within_a_few_ulps(tmp_path):
    from dgp_ros.export import cpp_runtime as R
    src = ('#include <cmath>\n#include <cstdint>\n#include <cstring>\n#include <cstdio>\n'
           + R.EXP.substitute() + r"""
int main() {
  double worst = 0.0;
  for (int i = 0; i <= 2000000; ++i) {
    double x = -600.0 * i / 2000000.0, y = x;
    exp_floor<double, std::uint64_t>(y, 0.0);
    const double r = std::fabs(y - std::exp(x)) / std::exp(x);
    worst = r > worst ? r : worst;
  }
  double z = -600.5;
  exp_floor<double, std::uint64_t>(z, 0.0);
  std::printf("%.3e %g\n", worst, z);
}
""")
    exe = compile_program(src, str(tmp_path / 'exp'), CXX)
    worst, below = subprocess.run([exe], capture_output=True, text=True, check=True).stdout.split()
    assert float(worst) < 2e-15 and float(below) == 0.0


@needs_cxx
def test_example_program_times_a_logged_trajectory(built, tmp_path):
    spec, model, _, _, path = built['diag_arm']
    export_cpp(path, tmp_path / 'friction_model.hpp')
    exe = compile_program(open(EXAMPLE, encoding='utf-8').read(), str(tmp_path / 'example'),
                          CXX, include=(str(tmp_path),))
    Qd = _velocities(model, 300, 13, False)
    Q = np.random.default_rng(3).uniform(-1.0, 1.0, Qd.shape)
    np.savetxt(tmp_path / 'log.csv', np.hstack([Q, Qd]), delimiter=',', header='q, qd')
    r = subprocess.run([exe, str(tmp_path / 'log.csv'), str(tmp_path / 'out.csv')],
                       capture_output=True, text=True, check=True)
    assert 'us per call' in r.stdout
    got = np.loadtxt(tmp_path / 'out.csv', delimiter=',')
    assert rel(got, model.predict_residual(q=Q, qd=Qd)) < TOL  # inside: the gate is silent


def test_refusals(models, tmp_path):
    from dgp_ros.dynamics.conservative import Correction
    from dgp_ros.gp import ArdGP, load_model
    from dgp_ros.gp.persistence import SavedCorrection
    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    ard = ArdGP(n_restarts=0).fit(*_arm_data(n=30, N=2))
    with pytest.raises(ExportError, match='ARD'):
        export_cpp(ard)
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    with pytest.raises(ExportError, match='still learning'):
        export_cpp(est)
    est.close()
    m = load_model(models['a320'])
    m.correction_ = SavedCorrection({'kind': 'my_plugin', 'params': [1.0]})
    with pytest.raises(ExportError, match='my_plugin.*--no-correction'):
        export_cpp(m)
    assert 'namespace dgp_model' in export_cpp(m, correction=False)
    m.correction_ = Correction(None, np.zeros(0), np.ones(3))
    with pytest.raises(ExportError, match='2 joint names'):
        export_cpp(m, names=['a', 'b'])
    with pytest.raises(ExportError, match='not a model file'):
        export_cpp(str(tmp_path / 'missing.npz'))


def test_non_revolute_joint_refused():
    from dgp_ros.dynamics import UrdfInverseDynamics
    from dgp_ros.dynamics.conservative import RegressorBasis
    from dgp_ros.export.kinematics import chain_of
    link = '<link name="{0}"><inertial><mass value="1"/><origin xyz="0 0 0.1"/>' \
           '<inertia ixx="0.1" iyy="0.1" izz="0.1" ixy="0" ixz="0" iyz="0"/></inertial></link>'
    urdf = ('<robot name="r">' + link.format('base') + link.format('l1') + link.format('l2') +
            '<joint name="j1" type="revolute"><parent link="base"/><child link="l1"/>'
            '<axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
            '<joint name="j2" type="prismatic"><parent link="l1"/><child link="l2"/>'
            '<axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
            '</robot>')
    basis = RegressorBasis(UrdfInverseDynamics(urdf=urdf), 'test', urdf)
    with pytest.raises(ExportError, match="'j2' is a JointModelP.*revolute"):
        chain_of(basis)


def test_gate_factor_is_the_nodes():
    from dgp_ros.export.spec import BOUND_FACTOR
    from dgp_ros.online.path import gate as answer
    assert BOUND_FACTOR == answer.BOUND_FACTOR


def test_console_tool(models, tmp_path):
    from dgp_ros.apps.export import main
    assert main([models['diag_arm'], '--cpp', str(tmp_path / 'a.hpp')]) == 0
    text = (tmp_path / 'a.hpp').read_text()
    assert 'panda_joint7' in text and 'Guarantee: psd' in text
    assert main([str(tmp_path / 'none.npz'), '--cpp', str(tmp_path / 'b.hpp')]) == 2
    assert main([models['a320'], '--cpp', str(tmp_path / 'c.hpp'), '--joints', 'x,y']) == 2
    with pytest.raises(SystemExit) as e:
        main(['--help'])
    assert e.value.code == 0


HOSTILE = ['a\n#include <cstdlib>\nint evil = (std::abort(), 0);\n//', 'q"uote\\', 'gelenk_ä\t?']


def test_text_from_users_and_files_never_reaches_the_compiler_as_code(models, tmp_path):
    """Joint names, a source path and a namespace: escaped, sanitized or refused."""
    if CXX is None:
        pytest.skip('no C++ compiler (g++, clang++, c++ or CXX)')
    from dgp_ros.export.literals import comment, string
    for bad in ('é', '1ns', 'a b', 'a\nb', ''):
        with pytest.raises(ExportError, match='not a C\\+\\+ identifier'):
            export_cpp(models['a320'], namespace=bad)
    odd = tmp_path / 'model\nint evil = 1;\\'
    odd.mkdir()
    src = odd / 'm.npz'
    src.write_bytes(pathlib.Path(models['a320']).read_bytes())
    hdr = str(tmp_path / 'h.hpp')
    text = export_cpp(str(src), hdr, names=HOSTILE)
    assert 'int evil' not in text.replace(string(HOSTILE[0]), '').replace(comment(str(src)), '')
    assert '\n#include <cstdlib>' not in text
    prog = ('#include "%s"\n#include <cstdio>\nint main() {\n'
            '  for (auto s : dgp_model::joint_names) std::printf("%%s|", s);\n  return 0;\n}\n'
            % hdr)
    exe = compile_program(prog, str(tmp_path / 'names'), CXX)
    out = subprocess.run([exe], capture_output=True, timeout=30).stdout
    assert out == ''.join(n + '|' for n in HOSTILE).encode('utf-8')
