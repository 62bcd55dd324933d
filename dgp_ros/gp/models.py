"""
Full-D-GP, Diag-D-GP and ARD-GP: thin estimators in the scikit-learn shape.

``__init__`` only stores its arguments; ``fit`` validates them and the data, then learns: the
prior mean (``means``), the hyper-parameters (``hyper``), the exact posterior (``posterior``) and
the passivity guarantee (the policy of ``passivity``, from the registry in ``passivity``).
``get_params``/``set_params`` read and write the constructor arguments by name.

Units and shapes: ``Qd`` (n, N) generalized velocities and ``Tau`` (n, N) damping forces in any
consistent units; every public method takes and returns model units.
"""
from __future__ import annotations

import copy
import inspect
import time
from typing import Optional

import numpy as np

from ._params import check_params
from ._validation import as_matrix, as_pair, in_chunks
from .blend import Grounds
from .fitted import Fitted
from .hyper import (apply_fixed_noise, hyper_from_params, initial_hyper, learn_hyper,
                    MIN_NOISE_VAR, scales)
from .kernels import KINDS, Structure
from .means import make_mean
from .passivity import policy_class
from .persistence import read_model, rebuild_correction, save_model
from .policy import Certificate, PolicyOptions
from .posterior import Posterior
from .select import keeps_all, select_elements

__all__ = ['ArdGP', 'DiagDGP', 'FullDGP', 'make_model', 'model_class', 'load_model']


#: query rows per chunk times training samples: bounds the (rows, n) kernel temporaries of a
#: large batch (10^6 queries at n = 500 took 24 GB at once) to about 64 MB each
CHUNK_ELEMENTS = 8_000_000
#: ``fit``'s ``hyper_rows`` are used from this many rows (else the training rows)
MIN_HYPER_ROWS = 50


class _DGP(Fitted):
    """
    Shared estimator; subclasses only set ``_kind``.

    Parameters
    ----------
    passivity : str
        A mode of ``passivity.PASSIVITY_MODES`` ('none' | 'paper' | 'certified' | 'projected';
        docs/PASSIVITY.md says what each proves). Default 'certified' (ArdGP: 'none', it has no
        damping matrix to certify).
    noise : float or (N,) array or None
        Fixed noise standard deviation per output, force units; None = learn it.
    noise_floor : float or None
        Least noise variance the fit may learn, in units of the residual's variance (None:
        ``hyper.MIN_NOISE_VAR``, 1e-6). Forces that depend on more than ``qd`` (hidden states),
        seen along a densely sampled path, drive the likelihood to near-zero noise and
        lengthscales too short to predict the next sample; a floor keeps them smooth.
    window : int or None
        Keep at most this many samples; ``update`` drops the oldest beyond it.
    n_restarts : int
        Extra random restarts of the hyper-parameter optimizer.
    max_opt_samples : int
        Hyper-parameters are optimized on at most this many samples (random subset).
    domain_margin, blend_width : float
        'certified': the verified box is the data box grown by ``domain_margin`` of its range per
        side; the correction blends to the prior mean over a further ``blend_width``.
    max_boxes : int
        Branch-and-bound budget of the 'certified' domain proof.
    projection_weights : (N,) array or None
        Diagonal of ``W^-1`` of the 'projected' mode (default ones: Euclidean, model units).
    hyperparams : dict or None
        ``hyperparams_`` of an earlier fit to start from (or keep, with ``fit(optimize=False)``).
    random_state : int
        Seed for subsets and restarts (fits are deterministic).
    operating_domain : ((N,), (N,)) or None
        'certified': a declared operating box ``(lo, hi)``, model units; the proof then covers
        its hull with the data box, so the correction is kept where no sample was seen yet.
    prior : str
        Prior mean of the damping: 'viscous' (constant diagonal, the paper's) | 'friction'
        (Coulomb + viscous) | 'friction+stribeck'; see ``means``.
    bias : bool
        Learn a per-joint constant bias with the prior (``bias_``; not part of the damping force).
    warm_start : bool
        ``fit(optimize=True)`` refines the hyper-parameters it starts from (the last fit's, or
        ``hyperparams``) without random restarts: the online estimator's re-learning.
    elements : 'all' | 'auto'
        Every element the kind has (the paper's), or per output none / its diagonal / also its
        couplings, chosen at each optimizing fit on the newest rows held out (``select``).
    couplings : 'evidence' | 'persistent'
        With ``elements='auto'``, where the couplings are tried: for every output, kept where
        the held-out blocks and the newest block predicted from the rows before it (with
        hyper-parameters learned on those rows) show them (a system whose velocities move
        apart: the paper's), or only beside a velocity that never nears zero (an arm, whose
        window is one path and whose couplings are what the path fakes).

    Fitted attributes: ``posterior_``, ``policy_``, ``mean_`` (the prior), ``hyperparams_``,
    ``bias_``, ``n_samples_``, ``X_train_``, ``Y_train_``, ``mean_diag_``, ``fit_info_``.

    """

    _kind = ''

    def __init__(self, passivity: str = 'certified', noise=None, window: Optional[int] = None,
                 n_restarts: int = 2, max_opt_samples: int = 300, domain_margin: float = 0.1,
                 blend_width: float = 0.1, max_boxes: int = 50000, projection_weights=None,
                 hyperparams: Optional[dict] = None, random_state: int = 0,
                 operating_domain=None, prior: str = 'viscous', bias: bool = False,
                 warm_start: bool = False, noise_floor: Optional[float] = None,
                 elements: str = 'all', couplings: str = 'evidence'):
        self.passivity = passivity
        self.noise = noise
        self.noise_floor = noise_floor
        self.window = window
        self.n_restarts = n_restarts
        self.max_opt_samples = max_opt_samples
        self.domain_margin = domain_margin
        self.blend_width = blend_width
        self.max_boxes = max_boxes
        self.projection_weights = projection_weights
        self.hyperparams = hyperparams
        self.random_state = random_state
        self.operating_domain = operating_domain
        self.prior = prior
        self.bias = bias
        self.warm_start = warm_start
        self.elements = elements
        self.couplings = couplings

    # ------------------------------------------------------------------ parameters
    @classmethod
    def _param_names(cls):
        sig = inspect.signature(_DGP.__init__)
        return [p for p in sig.parameters if p != 'self']

    def get_params(self, deep: bool = True) -> dict:
        """Return the constructor arguments, by name (scikit-learn convention)."""
        return {k: getattr(self, k) for k in self._param_names()}

    def set_params(self, **params) -> '_DGP':
        """Set constructor arguments; they take effect at the next ``fit``. Returns self."""
        unknown = set(params) - set(self._param_names())
        if unknown:
            raise ValueError(f'unknown parameter(s): {sorted(unknown)}')
        for k, v in params.items():
            setattr(self, k, v)
        return self

    def _check_params(self, N: int) -> PolicyOptions:
        """Validate the constructor arguments for N velocities; the policy options."""
        return check_params(self, N)

    # ------------------------------------------------------------------ fitting
    def fit(self, Qd, Tau, optimize: bool = True, prove: bool = True,
            hyper_rows=None) -> '_DGP':
        """
        Fit to samples Qd, Tau (n, N) (rows oldest first for ``elements='auto'``); return self.

        optimize=True: the prior mean, the standardization and the kernel hyper-parameters are
        (re)estimated (log marginal likelihood, analytic gradients, L-BFGS-B with restarts),
        starting from the last fit's (or ``hyperparams``) kernel parameters when there are any.
        optimize=False: keeps everything the model has (from an earlier fit or ``hyperparams``);
        a model without any estimates prior and scales from the data and keeps the default
        kernel.
        prove=False: a certifying mode establishes only its cheap certificates (the global bound,
        the eigenvalue floor); a domain proof is left pending (``certificate().stale``, every
        answer projected meanwhile) for ``recertify``: the online learner's rebases do this, so
        that no proof holds up learning.
        hyper_rows: (Qd, Tau) to learn the hyper-parameters and the elements on instead of the
        training rows (from ``MIN_HYPER_ROWS``; where ``_hyper_rows`` says): the online
        learner's samples spread evenly over the run; the posterior stays on ``Qd, Tau``.
        """
        t0 = time.perf_counter()
        Qd, Tau = as_pair(Qd, Tau)
        N = Qd.shape[1]
        options = self._check_params(N)
        structure = Structure.of(self._kind, N)
        if self.window is not None and Qd.shape[0] > self.window:
            Qd, Tau = Qd[-int(self.window):], Tau[-int(self.window):]
        start = self._start_hyper(structure)
        if start is not None and start[0].sx.size != N:
            if not optimize:
                raise ValueError(f'the kept hyper-parameters are for N = {start[0].sx.size}, '
                                 f'data has N = {N}')
            start = None
        info = {}
        if optimize or start is None:
            mean = make_mean(self.prior, self._kind, bool(self.bias)).fit(Qd, Tau)
            resid = Tau - mean(Qd)
            if start is not None:
                hp = start[0].copy()
                hp.sx, hp.sy = scales(Qd, resid, Tau)
                apply_fixed_noise(hp, self.noise)
            else:
                hp = initial_hyper(structure, Qd, resid, Tau, self.noise)
            if optimize:
                H = self._hyper_rows(structure, hp, Qd, Tau, hyper_rows)
                hp, info = self._learn(structure, hp, H[0], H[1] - mean(H[0]), H[1],
                                       not mean.is_diagonal,
                                       start is not None)
        else:
            hp, mean = start
        policy = policy_class(self.passivity)(options)
        post = Posterior(structure, hp, mean, Qd, Tau,
                         None if self.window is None else int(self.window),
                         keep_rkhs=policy.needs_rkhs)
        self.posterior_ = policy.enforce(post) if prove else policy.defer(post)
        self.policy_ = policy
        self.fit_info_ = dict(info, fit_seconds=time.perf_counter() - t0)
        return self

    def _hyper_rows(self, structure, hp, Qd, Tau, hyper_rows) -> tuple:
        """
        Return the rows to learn the hyper-parameters and elements on: (Qd, Tau) or hyper_rows.

        ``hyper_rows`` serve where the couplings are judged on evidence (``couplings``) and no
        velocity of the training rows stays away from zero: the paper's coupled systems, whose
        velocities reverse (``bench/dgp_family.py``: 7 axes one step ahead 0.158 -> 5.5e-5, 3
        axes in the box 6.4e-3 -> 3.5e-4). Beside an airspeed the aircraft's operating point
        drifts along its approach, and hyper-parameters of the whole run flew worse (3 of the
        first 9 flights of ``bench/a320_family.py`` newly failing).
        """
        if hyper_rows is None or self.couplings != 'evidence':
            return Qd, Tau
        Qh, Th = as_pair(*hyper_rows)
        if (Qh.shape[0] < min(Qd.shape[0], MIN_HYPER_ROWS) or Qh.shape[1] != Qd.shape[1]
                or keeps_all(structure, Qd / hp.sx)):
            return Qd, Tau
        return Qh, Th

    def _learn(self, structure, hp, Qd, resid, Tau, coupled: bool, started: bool):
        """
        Learn the hyper-parameters (and with ``elements='auto'`` the elements): (hp, info).

        ``coupled``: the prior carries the couplings of a persistent column (``gp.coupled``).
        """
        kw = {'fix_noise': self.noise is not None, 'n_restarts': int(self.n_restarts),
              'max_samples': int(self.max_opt_samples), 'random_state': int(self.random_state),
              'noise_floor': float(self.noise_floor or MIN_NOISE_VAR)}
        warm = bool(self.warm_start) and started     # refine the last optimum, no restarts
        if self.elements == 'auto':
            fresh = initial_hyper(structure, Qd, resid, Tau, self.noise)
            picked = select_elements(structure, hp, Qd, resid, fresh, warm,
                                     reversing=self.couplings == 'evidence', keep_all=coupled,
                                     **kw)
            if picked is not None:
                return picked
        return learn_hyper(structure, hp, Qd, resid, warm=warm, **kw)

    def _start_hyper(self, structure):
        """(Hyper, mean) to start from: the last fit's, else the ``hyperparams`` argument."""
        if getattr(self, 'posterior_', None) is not None:
            p = self.posterior_
            if p.structure.kind == structure.kind:
                return p.hyper.copy(), p.mean
        if self.hyperparams is None:
            return None
        return hyper_from_params(self.hyperparams, self._kind)

    def _restore(self, post: Posterior, meta: dict, arrays: dict, cert: dict) -> None:
        """
        Install a loaded posterior and policy state (``persistence``).

        The certificate is re-derived, never taken from the file.
        """
        policy = policy_class(self.passivity)(self._check_params(post.N))
        policy.load_state(meta, arrays, post)
        saved = Certificate.from_dict(cert) if cert else None
        policy.restore_certificate(post, saved)
        self.posterior_ = post
        self.policy_ = policy
        self.fit_info_ = {}

    # ------------------------------------------------------------------ online update
    def update(self, qd, tau) -> '_DGP':
        """
        Append samples without a refit: O(n^2) per sample and output.

        qd, tau: (N,) or (k, N).

        Hyper-parameters, standardization and prior stay as fitted; beyond ``window`` the oldest
        sample is dropped. The passivity policy re-checks cheaply; a structural certificate that
        no longer holds becomes stale (see ``certificate``). Returns self.
        """
        p = self._check_fitted()
        Q, T = as_pair(np.atleast_2d(qd) if np.ndim(qd) < 2 else qd,
                       np.atleast_2d(tau) if np.ndim(tau) < 2 else tau, p.N)
        p.update(Q, T)
        self.policy_.after_update(p, Q)
        return self

    def remean(self, mean) -> '_DGP':
        """
        Take another prior mean (a ``PriorMean``) without a refit: O(n^2) per output.

        Kernel, standardization and data stay; the weights become the posterior's with that
        mean (``Posterior.remean``). A structural certificate becomes stale, as after
        ``update``. Returns self.
        """
        p = self._check_fitted()
        p.remean(mean)
        self.policy_.after_update(p, np.zeros((0, p.N)))
        return self

    # ------------------------------------------------------------------ prediction
    def predict(self, Qs, return_var: bool = False, q=None):
        """
        Damping force at Qs (k, N) (or (N,)): (k, N) [and the posterior variance (k, N)].

        Passive as the policy guarantees (``passivity``); the variance is the GP posterior
        variance (noise-free), force units squared. The bias is not included (``bias_``).
        ``q`` (poses, k x N) is accepted for models whose damping depends on the pose; D here
        depends on the velocity only, so it is not used.
        """
        tau, var, _ = self._answers(Qs, return_var, False)
        return (tau, var) if return_var else tau

    def predict_residual(self, q=None, qd=None) -> np.ndarray:
        """
        Everything learned to explain the residual at (q, qd) (k, N) each: (k, N) N m.

        The damping force ``predict(qd)`` plus the learned conservative correction of the
        rigid-body model ``dV/dq(q)`` and the offsets (``correction_``, set by the online
        learner; none for a model fitted directly). ``q`` is needed when the correction uses it.
        A loaded model's correction needs its owner imported (``dgp_ros.dynamics``; else
        ValueError saying so: ``persistence``).
        """
        if qd is None:
            raise ValueError('predict_residual needs qd (velocities, k x N)')
        tau = np.atleast_2d(self.predict(qd))
        corr = getattr(self, 'correction_', None)
        if corr is None:
            return tau
        return tau + corr(None if q is None else as_matrix(q, 'q', tau.shape[1]))

    def damping_matrix(self, Qs) -> np.ndarray:
        """Posterior damping matrix D(q), (k, N, N), with ``predict(q) = D(q) q``."""
        if not self._check_fitted().structure.has_damping:
            raise NotImplementedError('ArdGP models the force directly and has no damping matrix')
        return self._answers(Qs, False, True, tau_from_predict=False)[2]

    def predict_with_damping(self, Qs, return_var: bool = True, return_damping: bool = True):
        """
        Predict with variance and damping matrix in one pass.

        ``predict(Qs, return_var=True)`` and ``damping_matrix(Qs)`` in one pass (the element
        kernels are built once): (tau, var, D); D None for ArdGP or without ``return_damping``,
        var None without ``return_var`` (the online estimator skips what nobody subscribes to:
        together they are about 60 % of a 7-joint answer).
        """
        return self._answers(Qs, return_var, return_damping)

    def _answers(self, Qs, want_var: bool, want_D: bool, tau_from_predict: bool = True) -> tuple:
        """
        Return (tau, var or None, D or None) at Qs, through the policy, in row chunks.

        D is built when asked for or when the policy or the grounds' per-joint blend needs it; tau
        comes from the posterior's prediction (bit-identical to ``predict``) unless D is at hand
        and that does not matter. A model carrying its learner's gains (``grounds_``) blends by
        them (``blend``).
        """
        p = self._check_fitted()
        Q = as_matrix(Qs, 'Qs', p.N)
        pol = self.policy_
        g = Grounds.of(getattr(self, 'grounds_', None), p.N) if p.structure.has_damping else None
        guarantee = pol.cert.guarantee if g is not None else ''
        need_D = p.structure.has_damping and (want_D or pol.needs_damping or (
            g is not None and g.per_joint(guarantee)))

        def part(Qc):
            Kel = p.element_kernels(Qc)
            w = pol.weight(Qc)
            D = p.damping(Qc, w, Kel) if need_D else None
            if D is not None and not want_var and (pol.needs_damping or not tau_from_predict):
                tau, var = np.einsum('kij,kj->ki', D, Qc), None
            else:
                tau, var = p.predict(Qc, w, want_var, Kel)
            tau, D = pol.finalize(p, Qc, tau, D)
            if g is not None:
                tau, D = g.apply(p.mean, Qc, tau, D, guarantee)
            return tau, var, D if want_D else None
        return in_chunks(Q, p.n, part, CHUNK_ELEMENTS)

    def snapshot(self, variance: bool = True) -> '_DGP':
        """
        Return a predict-only copy, compact to send to another process.

        Same parameters, prior, weights, scales and passivity state (the certificate is the
        one proven here, not re-derived); the Cholesky factors only with ``variance`` (else
        the variance it predicts is NaN). ``update`` raises on it; ``save`` refactorizes.
        """
        p = self._check_fitted()
        snap = copy.copy(self)
        snap.posterior_ = p.frozen(variance)
        snap.policy_ = copy.deepcopy(self.policy_)
        return snap

    # ------------------------------------------------------------------ passivity
    def certificate(self) -> Certificate:
        """Return the certificate as it is now: a record, not a computation (``recertify``)."""
        self._check_fitted()
        return self.policy_.cert

    @property
    def certificate_stale(self) -> bool:
        return bool(self.certificate().stale)

    def recertify(self, full: bool = False) -> Certificate:
        """
        Re-prove a stale structural certificate for the current weights.

        It takes milliseconds to seconds of branch-and-bound; the online estimator runs it in its
        refit worker. A no-op when nothing is stale. ``full``: unless the certificate holds, the
        proof a fit makes, from scratch, also after a failed one (a model that stops learning).
        """
        p = self._check_fitted()
        if full:
            self.posterior_ = self.policy_.reprove(p)
            return self.policy_.cert
        return self.policy_.recertify(p)

    # ------------------------------------------------------------------ persistence
    def save(self, path) -> None:
        """Write the model to ``path`` atomically (``persistence``: npz + JSON header)."""
        self._check_fitted()
        save_model(self, path)

    @classmethod
    def load(cls, path):
        """Read a model written by ``save``; ValueError for anything else (``persistence``)."""
        model = load_model(path)
        if cls is not _DGP and not isinstance(model, cls):
            raise ValueError(f'{path}: holds a {type(model).__name__}, not a {cls.__name__}')
        return model


class FullDGP(_DGP):
    """Full-D-GP: every element ``d_mn(q)`` of the damping matrix an independent SE-ARD GP."""

    _kind = 'full'


class DiagDGP(_DGP):
    """Diag-D-GP: diagonal damping matrix, ``d_n(q)`` independent SE-ARD GPs."""

    _kind = 'diag'


class ArdGP(_DGP):
    """Baseline: an independent SE-ARD GP per output on ``q`` (constant prior mean)."""

    _kind = 'ard'

    def __init__(self, passivity: str = 'none', **kw):
        super().__init__(passivity=passivity, **kw)


_KINDS = {'full': FullDGP, 'diag': DiagDGP, 'ard': ArdGP}
assert tuple(_KINDS) == KINDS


def model_class(kind: str):
    """Return the estimator class of a model kind; ValueError naming the choices."""
    if kind not in _KINDS:
        raise ValueError(f"unknown model kind {kind!r}: expected one of {', '.join(KINDS)}")
    return _KINDS[kind]


def make_model(kind: str, **kw) -> _DGP:
    """Construct a model by name: 'full' | 'diag' | 'ard'."""
    return model_class(kind)(**kw)


def load_model(path) -> _DGP:
    """
    Load any model written by ``save``; ValueError with a reason for anything else.

    ``persistence.read_model`` validates the file and restores the posterior; the estimator is
    built here, and its policy re-derives the certificate (never taken from the file).
    """
    f = read_model(path)
    try:
        model = model_class(f.kind)(**f.params)
        model._restore(f.posterior, f.policy, f.policy_arrays, f.certificate)
        if f.correction is not None:
            # rebuilt by the layer that owns its kind (the robot front end: a URDF needs
            # pinocchio), through the registry it fills (``persistence``)
            model.correction_ = rebuild_correction(f.correction)
        model.grounds_ = None if f.grounds is None else dict(f.grounds)
        if model.posterior_.structure.has_damping:
            Grounds.of(model.grounds_, model.N)     # a malformed record fails here, not later
    except Exception as exc:      # a crafted header: wrong names, types or policy state
        raise ValueError(f'{path}: malformed model file ({type(exc).__name__}: {exc})') \
            from None
    return model
