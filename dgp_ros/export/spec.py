"""
What a frozen model answers, as plain numbers: the constants a generated header bakes in.

The export evaluates exactly what the frozen node serves (docs/CONTRACTS.md, "dgp_ros.export"):
the model file read by ``load_model``, its certificate proven as the node proves it when it
loads a file (:func:`prove_as_node`: never taken from the file), the weights after that proof
(a repair may change them), the policy's answer (correction weight, eigenvalue floor,
projection), the earned gains' blend (``gp.blend``) and the node's output gate
(``online/path/gate.py``: fallback, bounds). :func:`model_spec` reads all of it into a
:class:`Spec` of numpy arrays and small records, or raises :class:`ExportError` naming why the
model cannot be carried and what to do.

Units: model units throughout (velocities as the model was fitted, forces in N m or N);
``X`` and the lengthscales are standardized (``x = qd / sx``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import List, Optional

import numpy as np

from dgp_ros.gp.blend import Grounds
from dgp_ros.gp.certified import CertifiedPolicy
from dgp_ros.gp.coupled import CoupledMean, MAX_PAIRED
from dgp_ros.gp.joint_element import JointElementMean
from dgp_ros.gp.means import BasisFrictionMean, FrictionMean, ViscousMean
from dgp_ros.gp.passivity import NonePolicy, PaperPolicy, policy_class, ProjectedPolicy
from dgp_ros.gp.persistence import rebuild_correction, SavedCorrection
from dgp_ros.gp.transmission import EPS as TRANSMISSION_EPS, TransmissionMean

from .errors import ExportError

__all__ = ['ExportError', 'Spec', 'Element', 'model_spec', 'prove_as_node', 'BOUND_FACTOR',
           'psi_terms', 'psi_values']

#: the output gate's factor on the largest learned force (``online.path.gate.BOUND_FACTOR``; the
#: export does not import the online layer: test/export checks that the two agree)
BOUND_FACTOR = 1.5


@dataclass
class Element:
    """
    One damping-matrix element ``D[m, n]`` of the GP correction.

    il2 : (N,) inverse squared lengthscales (standardized units); v : (n,) its weight per
    training sample, ``sf2 * x_n,j * weights_j,m``, so that the element's correction at a query
    ``x`` is ``sum_j exp(-0.5 sum_d (x_d - X_jd)^2 il2_d) v_j``.
    """

    m: int
    n: int
    il2: np.ndarray
    v: np.ndarray


@dataclass
class Spec:
    """
    The numbers of one frozen model (module docstring); every array in model units.

    prior : dict with ``coef`` (N, 1 + K + S), ``eps`` (N, K + 1) and ``vs`` (N, S): the
    damping prior ``m_d(|qd|)`` (``gp.means``; viscous: K = S = 0), ``element`` where joints
    carry a per-joint element (``gp.joint_element``) and ``coupled`` where the prior carries the
    couplings of persistent columns (``gp.coupled``; its base's ``m_d`` then; ``_prior``).
    weight : ('one',) | ('scale', s) | ('domain', s, olo, ilo - olo, ohi, ohi - ihi): the policy's
    correction weight. clip_delta : the eigenvalue floor's width, or None. project : the policy
    projects every answer onto ``qd . tau >= 0`` (``w_inv``: the projection's weights).
    grounds : (w, a) or None; per_joint : the congruence blend (guarantee ``psd``).
    gate : the output gate of the frozen node (``limit``, ``box_lo``, ``box_hi``, ``gain``,
    ``passive``). correction : None or a dict (``offsets``, ``basis`` and its constants).
    """

    N: int
    n: int
    kind: str
    passivity: str
    names: List[str]
    sx: np.ndarray
    sy: np.ndarray
    X: np.ndarray
    elements: List[Element]
    prior: dict
    weight: tuple
    clip_delta: Optional[float]
    project: bool
    w_inv: np.ndarray
    grounds: Optional[tuple]
    per_joint: bool
    gate: dict
    correction: Optional[dict]
    guarantee: str
    method: str
    proof: str
    info: dict = field(default_factory=dict)


def prove_as_node(model) -> str:
    """
    Prove a loaded model's certificate as the frozen node does when it loads a file.

    The same steps as ``dgp_ros.online.jobs.worker.prove(model, model.passivity)`` (called by
    ``Learner.adopt``): nothing for a mode that does not certify; a stale certificate (a domain
    proof read from a file) re-proven by ``recertify()``, which may repair the weights. Returns
    '' when the certificate holds, else why (the model then answers with every estimate
    projected, as the node's does).
    """
    if not policy_class(model.passivity).certifies:
        return ''
    cert = model.certificate()
    if cert.stale:
        cert = model.recertify()
    if cert.certified:
        return ''
    return f'certificate does not hold (margin {cert.margin:.3g}, {cert.method})'


def _prior(mean, N: int) -> dict:
    """
    Return the prior's damping ``m_d`` in the general form of ``friction_means._friction_diag``.

    A prior with per-joint elements (``gp.joint_element.JointElementMean``) is its base's, with
    ``element``: the joints that carry one, their weights (n, M), velocity scales and sign
    smoothings (n,), added and floored at 0 as the mean does. A prior with the couplings of
    persistent columns (``gp.coupled.CoupledMean``) is its base's too, with ``coupled``
    (:func:`_coupled`); so is one with coupled transmissions (``gp.transmission``), whose
    ``coupled`` has no column and its ``motors`` (a, b, s, Coulomb, viscous) at ``eps``.
    """
    if isinstance(mean, JointElementMean):
        out = _prior(mean.base, N)
        j = np.asarray(mean.active, int)
        b = mean.basis
        lo, hi = (np.full(b.N, -np.inf), np.full(b.N, np.inf)) if mean.span is None else \
            mean.span
        out['element'] = {'joints': j, 'W': np.asarray(mean.W, float)[j],
                          'vc': np.asarray(b.vc, float)[j], 'eps': np.asarray(b.eps, float)[j],
                          'lo': np.asarray(lo, float)[j], 'hi': np.asarray(hi, float)[j]}
        return out
    if isinstance(mean, CoupledMean):
        out = _prior(mean.base, N)
        out['coupled'] = _coupled(mean)
        return out
    if isinstance(mean, TransmissionMean):
        # a non-diagonal prior in the coupled form: no persistent column, a motor per pair
        out = _prior(mean.base, N)
        # (``psd``: the diagonal plus a PSD part, gains and blend by congruence)
        out['coupled'] = {'box': None, 'columns': [], 'eps': float(TRANSMISSION_EPS),
                          'psd': True,
                          'motors': [(a, b, s, float(c[0]), float(c[1]))
                                     for (a, b, s), c in zip(mean.pairs, mean.coef)]}
        return out
    if isinstance(mean, ViscousMean):
        return {'coef': np.asarray(mean.m_d, float).reshape(N, 1), 'eps': np.zeros((N, 1)),
                'vs': np.zeros((N, 0)), 'K': 0}
    if isinstance(mean, FrictionMean):
        S = 1 if mean.stribeck else 0
        eps = np.asarray(mean.eps, float)
        return {'coef': np.asarray(mean.coef, float)[:, :2 + S], 'eps': np.stack([eps, eps], 1),
                'vs': np.asarray(mean.v_s, float).reshape(N, 1)[:, :S], 'K': 1}
    if isinstance(mean, BasisFrictionMean):
        eps = np.append(mean.eps, mean.eps_s)
        K, S = mean.eps.size, mean.vs.size
        out = {'coef': np.asarray(mean.coef, float), 'eps': np.tile(eps, (N, 1)),
               'vs': np.tile(np.asarray(mean.vs, float), (N, 1)), 'K': K, 'S': S}
        if mean.coef_neg is not None:       # its own coefficients for v < 0
            out['coef_neg'] = np.asarray(mean.coef_neg, float)
        return out
    raise ExportError(f'the prior {type(mean).__name__} has no C++ form (viscous, friction, '
                      'frozen friction, coupled and transmission priors do): refit with one of '
                      'these priors')


def psi_terms(n: int, paired: bool) -> List[tuple]:
    """
    Return the features of one persistent column, in ``CouplingBasis.psi``'s order.

    n : how many other velocities; paired : with the pair features. Each term is ('one',),
    ('x', k), ('a', k), ('x2', k), ('x3', k) (``x_k``, ``|x_k|``, ``x_k^2``, ``x_k^3``) or
    ('xx', k, m), ('xa', k, m), ('ax', k, m) (``x_k x_m``, ``x_k |x_m|``, ``|x_k| x_m``).
    """
    out = [('one',)] + [(f, k) for f in ('x', 'a', 'x2', 'x3') for k in range(n)]
    if paired:
        for k in range(n):
            for m in range(k + 1, n):
                out += [('xx', k, m), ('xa', k, m), ('ax', k, m)]
    return out


def psi_values(terms: List[tuple], X: np.ndarray) -> np.ndarray:
    """Evaluate ``terms`` (:func:`psi_terms`) at clipped other velocities X (k, n): (k, T)."""
    A = np.abs(X)
    val = {'x': lambda k: X[:, k], 'a': lambda k: A[:, k], 'x2': lambda k: X[:, k] * X[:, k],
           'x3': lambda k: X[:, k] * X[:, k] * X[:, k],
           'xx': lambda k, m: X[:, k] * X[:, m], 'xa': lambda k, m: X[:, k] * A[:, m],
           'ax': lambda k, m: A[:, k] * X[:, m]}
    return np.stack([np.ones(X.shape[0]) if t[0] == 'one' else val[t[0]](*t[1:])
                     for t in terms], axis=1)


def _coupled(mean) -> dict:
    """
    Return the couplings of a coupled prior (``gp.coupled.CoupledMean``) as plain numbers.

    ``box``: (lo, hi) (N,) each, the other velocities' clipping, or None; ``columns``: per
    persistent column ``p``, its reference speed ``vref``, its ``others`` (the velocities its
    features are taken of, in order), ``terms`` (:func:`psi_terms`) and weights ``W`` (N, T).
    The terms are checked against ``CouplingBasis.psi`` at random velocities (equal bit for
    bit): a basis whose features changed is refused rather than exported wrong.
    """
    b = mean.basis
    W = np.asarray(mean.W, float)
    box = None if b.box is None else (np.asarray(b.box[0], float), np.asarray(b.box[1], float))
    rng = np.random.default_rng(0)
    Q = rng.normal(0.0, 1.0, (64, b.N)) * rng.choice([1e-3, 1.0, 1e3], (64, 1))
    cols = []
    for c, (p, sl) in enumerate(zip(b.cols, b.slices())):
        o = list(b.others[c])
        terms = psi_terms(len(o), len(o) <= MAX_PAIRED)
        X = Q[:, o] if box is None else np.clip(Q[:, o], box[0][o], box[1][o])
        if len(terms) != b.sizes[c] or not np.array_equal(psi_values(terms, X), b.psi(Q, c)):
            raise ExportError("the coupled prior's features are not the ones the export "
                              'knows (gp.coupled.CouplingBasis.psi changed): update '
                              'dgp_ros.export.spec.psi_terms')
        cols.append({'p': int(p), 'vref': float(b.vref[c]), 'others': o, 'terms': terms,
                     'W': W[:, sl].copy()})
    return {'box': box, 'columns': cols}


def _weight(pol) -> tuple:
    """Return the policy's correction weight as a record (``PassivityPolicy.weight``)."""
    if isinstance(pol, CertifiedPolicy):
        if pol.blend_on and pol.domain is not None and not (pol.cert is not None and
                                                            pol.cert.stale):
            (ilo, ihi), (olo, ohi) = pol.domain
            return ('domain', float(pol.scale), np.asarray(olo, float),
                    np.maximum(ilo - olo, 1e-300), np.asarray(ohi, float),
                    np.maximum(ohi - ihi, 1e-300))
        return ('one',) if pol.scale == 1.0 else ('scale', float(pol.scale))
    if isinstance(pol, PaperPolicy):
        return ('scale', float(pol.scale))
    if isinstance(pol, (NonePolicy, ProjectedPolicy)):
        return ('one',)
    raise ExportError(f'the passivity policy {type(pol).__name__} has no C++ form')


def _elements(post) -> List[Element]:
    """Every element that is switched on, with its per-sample weights (class ``Element``)."""
    s, hp = post.structure, post.hyper
    out = []
    for e, (m, n) in enumerate(s.elems):
        sf2 = math.exp(hp.log_sf2[e]) if np.isfinite(hp.log_sf2[e]) else 0.0
        if sf2 == 0.0:
            continue                          # switched off: contributes nothing
        ls = np.exp(np.asarray(hp.log_ls[e], float))
        v = sf2 * post.X[:, n] * post.weights[:, m]
        out.append(Element(int(m), int(n), ls ** -2.0, v))
    return out


def model_spec(model, names: Optional[List[str]] = None, proof: str = '') -> Spec:
    """
    Read a loaded, proven model into a :class:`Spec` (module docstring).

    ``names``: the joint names the header reports (default: the correction's URDF joints, else
    ``joint_1..N``); ``proof``: what :func:`prove_as_node` returned. Raises ExportError for a
    model the header cannot carry.
    """
    post = model.posterior_
    s = post.structure
    if not s.has_damping:
        raise ExportError('an ARD-GP model has no damping matrix and no passive structure '
                          'to carry (its answers are not D(qd) qd): refit with model=full '
                          'or model=diag')
    N, pol = post.N, model.policy_
    if any(n is None for _, n in s.elems):
        raise ExportError('the model has elements without a damping column: not a D-GP')
    corr = _correction(model, N)
    names = list(names) if names else (list(corr['joints']) if corr and corr.get('joints')
                                       else [f'joint_{j + 1}' for j in range(N)])
    if len(names) != N:
        raise ExportError(f'{len(names)} joint names given for a model of {N} joints')
    cert = pol.cert
    clip = isinstance(pol, CertifiedPolicy) and pol.clip
    g = Grounds.of(getattr(model, 'grounds_', None), N)
    X, T = model.X_train_, model.Y_train_
    record = getattr(model, 'grounds_', None) or {}
    gain = np.clip(np.asarray(record.get('prior_gain', np.ones(N)), float), 0.0, 1.0)
    gate = {'limit': BOUND_FACTOR * np.maximum(np.abs(T).max(axis=0), 1e-12),
            'box_lo': X.min(axis=0), 'box_hi': X.max(axis=0), 'gain': gain,
            'passive': model.passivity != 'none'}
    return Spec(
        N=N, n=post.n, kind=s.kind, passivity=model.passivity, names=names,
        sx=np.asarray(post.hyper.sx, float), sy=np.asarray(post.hyper.sy, float),
        X=np.asarray(post.X, float), elements=_elements(post), prior=_prior(post.mean, N),
        weight=_weight(pol), clip_delta=pol._delta(post) if clip else None,
        project=isinstance(pol, (CertifiedPolicy, ProjectedPolicy)),
        w_inv=np.ones(N) if pol.options.projection_weights is None
        else np.asarray(pol.options.projection_weights, float),
        grounds=None if g is None else (g.w.copy(), g.a.copy()),
        per_joint=g is not None and Grounds.per_joint(cert.guarantee), gate=gate,
        correction=corr, guarantee=cert.guarantee, method=cert.method, proof=proof)


def _correction(model, N: int) -> Optional[dict]:
    """Return the correction's constants (offsets, basis) or None; ExportError if impossible."""
    corr = getattr(model, 'correction_', None)
    if corr is None:
        return None
    if isinstance(corr, SavedCorrection):
        import dgp_ros.dynamics  # noqa: F401 - registers the 'conservative' kind it owns
        corr = model.correction_ = rebuild_correction(corr.record)
    record = corr.to_dict() if hasattr(corr, 'to_dict') else None
    kind = (record or {}).get('kind', 'conservative')
    if kind != 'conservative' or not hasattr(corr, 'basis'):
        raise ExportError(f'the model carries a {kind!r} correction, rebuilt by a Python '
                          'plugin the header cannot reproduce: export the damping force '
                          'alone (export_cpp(..., correction=False), dgp-export '
                          '--no-correction) and add that correction in your controller')
    out = {'offsets': np.asarray(corr.offsets, float).reshape(N), 'basis': None}
    if not corr.needs_position:
        return out
    basis, theta = corr.basis, np.asarray(corr.theta, float)
    if basis.kind == 'potential':
        out.update(basis='potential', terms=list(basis.terms), theta=theta)
    elif basis.kind == 'regressor':
        from .kinematics import chain_of
        out.update(basis='regressor', chain=chain_of(basis), theta=theta,
                   joints=list(basis.joints))
    else:
        raise ExportError(f'the correction basis {basis.kind!r} has no C++ form: export '
                          'with --no-correction and add it in your controller')
    return out
