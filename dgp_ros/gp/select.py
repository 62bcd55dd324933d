"""
Which elements of the damping matrix each output keeps, chosen on held-out samples.

The marginal likelihood that learns the hyper-parameters cannot tell a coupling ``D_mn``
(``m != n``) the data support from one that only fits the path the data took: along one
trajectory the joint velocities move together (sums of sines, a repeated task), so an element
``x_n f_mn(x)`` of another joint's velocity explains what belongs to joint m and extrapolates
wildly once they move apart. On a real UR10 the Full-D-GP put -89 N m s/rad from wrist 2's
velocity onto the elbow and predicted 1525 N m on the unseen part of the log where the residual
stays within 29 N m. The aircraft needs its couplings (lift and drag depend on the angle of
attack, a velocity that crosses zero, at an airspeed that never does).

So with ``elements='auto'`` every output ``m`` (an independent GP) chooses between the prior
alone and the one structure with GP elements that suits the velocities (``_candidates``):

* ``'none'``: no GP element, the prior mean alone (the parametric part; the GP could not show
  that it adds anything);
* ``'own'``, where every velocity reverses (an arm): its own element ``(m, m)`` as a function
  of its own velocity alone (a friction curve; the other velocities' lengthscales pinned at
  ``hyper.PINNED_LOG_LS``): it cannot extrapolate along velocities it does not see;
* ``'all'``, where a velocity never nears zero: its own element and the couplings ``(m, n)`` of
  the model kind, each a function of every velocity (SE-ARD; for a Diag-D-GP its own element);
  and with ``reversing`` (a system that is not an arm: the paper's coupled D(qd) whose
  velocities reverse) also where every velocity reverses, beside ``'own'``, kept only where it
  beats the output's pick by :data:`REVERSING_MARGIN` both in the blocks and on the newest
  block predicted by a fit on the rows before it, hyper-parameters learned there too (a block
  neither they nor their hyper-parameters saw). On an arm the window is one path, repeated: its
  local dimension is 1.00-1.13 at every selection on the real Panda, the real UR10 and the
  simulated arms, and the couplings that path fakes pass both tests (the real UR10's forward
  block at 0.1-0.8 of the own element's error, 0.0162 -> 0.0204 held out),

by blocked cross-validation: the hyper-parameters of the GP choice are learned on all the rows,
then each of :data:`FOLDS` contiguous blocks of them (rows in time order, oldest first: a block
is a stretch of the motion) is predicted by the posterior of the others. The GP must cut the
held-out error of the prior alone by its margin (:data:`MARGINS`): the blocks lie on the path
the data took, so their error flatters every model that extrapolates. The chosen elements keep
those hyper-parameters; the others are switched off (``log sf2 = -inf``: they contribute
nothing, cost nothing and stay off until the next selection).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np
from scipy.linalg import cho_factor, cho_solve, LinAlgError

from ._chol import JITTER_STEPS
from .hyper import learn_hyper, persistent as hyper_persistent, PINNED_LOG_LS
from .kernels import Structure
from .posterior import Hyper

__all__ = ['select_elements', 'choice_summary', 'element_masks', 'row_choices', 'keeps_all',
           'CHOICES', 'FOLDS', 'MARGINS', 'MIN_TRAIN', 'MIN_HOLDOUT']

CHOICES = ('none', 'own', 'all')
#: contiguous blocks of the rows (in time order), each held out in turn
FOLDS = 4
#: at least this many samples per block, and this many to learn from; else no selection
MIN_HOLDOUT = 5
MIN_TRAIN = 15
#: a GP choice is taken over the prior alone where its held-out error is below (1 - margin)
#: times the prior's: an arm's friction curve must earn its place (its parametric prior is a
#: complete friction model); where a velocity never nears zero the prior cannot carry a force
#: at another velocity's zero at all (an A320's drag at zero angle of attack), and the GP is
#: dropped only where it does harm (held-out blocks on a trajectory that moves on to new
#: angles of attack flatter neither: 0.976 of the prior's error 5 s into a flight, and 42 s
#: of prior-only drag at 3 to 5 times the force's variance followed)
MARGINS = {'own': 0.2, 'all': -0.2}
#: where every velocity reverses (``reversing``), couplings are tried beside the own element and
#: kept only where they beat it by this margin both in the blocked cross-validation and on the
#: newest block predicted from a fit (hyper-parameters too) on the rows before it
REVERSING_MARGIN = 0.2


def element_masks(structure: Structure) -> dict:
    """Return the elements each choice keeps: ``choice -> (E,) bool``."""
    E = structure.E
    own = np.array([n is None or n == m for m, n in structure.elems], bool)
    return {'none': np.zeros(E, bool), 'own': own, 'all': np.ones(E, bool)}


def _pin(structure: Structure, log_ls: np.ndarray, mask: np.ndarray) -> None:
    """Pin every lengthscale of the elements in ``mask`` but their own velocity's, in place."""
    for e in np.flatnonzero(mask):
        m = structure.elems[e][0]
        keep = log_ls[e, m]
        log_ls[e] = PINNED_LOG_LS
        log_ls[e, m] = min(keep, PINNED_LOG_LS - 1.0)


def row_choices(structure: Structure, hp: Hyper) -> list:
    """Return the choice each output's switched-on elements amount to (``CHOICES``), per row."""
    masks = element_masks(structure)
    on = np.isfinite(np.asarray(hp.log_sf2, float))
    pinned = np.asarray(hp.log_ls, float) >= PINNED_LOG_LS - 1e-9
    out = []
    for rows in structure.rows:
        r = list(rows)
        if not on[r].any():
            out.append('none')
        elif on[r].all() and not pinned[r].any():
            out.append('all')
        elif np.array_equal(on[r], masks['own'][r]) and pinned[r].any():
            out.append('own')
        else:
            out.append('some')
    return out


def keeps_all(structure: Structure, X: np.ndarray) -> bool:
    """
    Tell whether every output tries only ``'all'`` on standardized inputs X (n, N).

    An ARD-GP, or an element whose feature stays away from zero in X (``hyper.persistent``: an
    aircraft's airspeed); else every velocity reverses.
    """
    return structure.kind == 'ard' or any(hyper_persistent(structure, X, e)
                                          for e in range(structure.E))


def _candidates(structure: Structure, X: np.ndarray, reversing: bool = False) -> tuple:
    """
    Return the choice with GP elements to try on standardized inputs X (n, N).

    Where every velocity reverses (an arm's joints), ``'own'``: an output restricted to its own
    velocity cannot extrapolate along the others. The couplings were tried there too: on the
    real arms' unseen parts every coupled output the cross-validation chose was worse than its
    parametric part (a Panda at 30 Hz, joint 6: 0.43 of the prior's error in cross-validation,
    1.46 against 0.98 held out; at 125 Hz joints 6 and 7; a UR10's wrist 3, 0.48 against
    0.074), because along one trajectory the velocities move together and what the couplings
    learn is the path. Where a velocity never comes near zero (an aircraft's airspeed,
    ``hyper.persistent``), ``'all'``: a force at another velocity's zero can only be carried by
    a coupling to it (the drag of an A320 at zero angle of attack), and an output restricted to
    its own velocity cannot be right there, however well it did on the data so far (its first
    80 samples: 0.043 against 0.049 with the couplings; the whole flight's drag 1.7x worse).
    ``reversing`` (not an arm): ``'own'`` and ``'all'`` (the synthetic coupled systems of
    ``bench/dgp_family.py``: 4 axes one step ahead 0.35 -> 4e-5 at worst).
    """
    if keeps_all(structure, X):
        return ('all',)
    if reversing and structure.E > structure.N:
        return ('own', 'all')
    return ('own',)


def _fold_error(structure: Structure, hp: Hyper, X: np.ndarray, Y: np.ndarray,
                folds: list) -> np.ndarray:
    """
    Mean squared error per output of the posterior mean on each block, learned on the rest.

    X, Y (n, N) standardized; folds: index arrays of the held-out blocks. Returns (N,), the
    mean over every held-out row (standardized units).
    """
    n = X.shape[0]
    err = np.zeros(structure.N)
    count = 0
    for test in folds:
        train = np.setdiff1d(np.arange(n), test)
        Xtr, Xte = X[train], X[test]
        count += len(test)
        for m in range(structure.N):
            K = structure.output_kernel(m, Xtr, Xtr, hp.log_ls, hp.log_sf2)
            if not np.any(K):
                err[m] += float(np.sum(Y[test, m] ** 2))
                continue
            sn2 = math.exp(hp.log_sn2[m])
            base = float(np.mean(np.diag(K))) + sn2
            c = None
            for rel in JITTER_STEPS:
                try:
                    c = cho_factor(K + (sn2 + rel * base) * np.eye(len(K)), lower=True)
                    break
                except LinAlgError:
                    continue
            if c is None:
                err[m] = np.inf
                continue
            pred = structure.output_kernel(m, Xte, Xtr, hp.log_ls, hp.log_sf2) @ \
                cho_solve(c, Y[train, m])
            err[m] += float(np.sum((pred - Y[test, m]) ** 2))
    return err / max(count, 1)


def _forward_error(structure: Structure, start: Hyper, Qd, resid, X, Y, test, **learn_kw):
    """
    Mean squared error per output on the newest block ``test`` of a fit on the rows before it.

    The hyper-parameters are learned afresh from ``start`` on those rows alone: a block that
    neither the posterior nor its hyper-parameters saw. Returns ((N,), evaluations).
    """
    train = np.arange(test[0])
    h, info = learn_hyper(structure, start, Qd[train], resid[train], warm=False, **learn_kw)
    return _fold_error(structure, h, X, Y, [test]), int(info.get('evaluations', 0))


def _couplings_earn(m: int, pick: str, err: dict, forward: dict) -> bool:
    """Whether output m's couplings beat its pick by the margin in both tests."""
    keep = 1.0 - REVERSING_MARGIN
    return (err['all'][m] < keep * err[pick][m]
            and forward['all'][m] < keep * forward[pick][m])


def select_elements(structure: Structure, hp: Hyper, Qd: np.ndarray, resid: np.ndarray,
                    fresh: Hyper, warm: bool = False, folds: int = FOLDS,
                    reversing: bool = False, keep_all: bool = False, **learn_kw):
    """
    Choose each output's elements by blocked cross-validation (module docstring).

    Parameters
    ----------
    structure : kernels.Structure
        The model's elements (kind and N).
    hp : Hyper
        Where to start (the last fit's hyper-parameters, or the initial ones); elements it has
        switched off start from ``fresh``.
    Qd, resid : (n, N)
        Velocities and residuals after the prior mean (model units), oldest first.
    fresh : Hyper
        Initial hyper-parameters (``hyper.initial_hyper``) for elements that were off.
    warm : bool
        ``hp`` is a previous optimum: refine it without restarts (``hyper.learn_hyper``), where
        a choice switches on no element that was off or pinned otherwise.
    folds : int
        Contiguous blocks of the rows, each held out in turn.
    reversing : bool
        Where every velocity reverses, try the couplings too, beside the own element, and keep
        them only where they beat it in the blocks and on the newest block predicted by a fit
        (hyper-parameters too) on the rows before it (``_couplings_earn``).
    keep_all : bool
        The prior carries the couplings of a persistent column (``gp.coupled``: an aircraft's
        airspeed): where ``'all'`` is the one choice, it is kept whatever the blocks say. The
        blocks of a coverage buffer lie where the others did not reach, and beside such a prior
        they judged the GP 1.5-2x worse 63 s into an approach where one step ahead it was 5-10x
        better (the online blend by earned gains weighs it where it is worse).
    learn_kw
        The other settings of ``hyper.learn_hyper`` (the model's).

    Returns
    -------
    (Hyper, dict) or None
        The hyper-parameters with the chosen elements on and ``info``: ``elements``
        (``choices`` per output, ``heldout``: choice -> (N,) MSE in standardized units),
        ``evaluations``. None when there are too few samples to hold blocks out.

    """
    n = Qd.shape[0]
    if n < folds * MIN_HOLDOUT or n - n // folds < MIN_TRAIN:
        return None
    blocks = np.array_split(np.arange(n), folds)
    X, Y = Qd / hp.sx, resid / hp.sy
    masks = element_masks(structure)
    start_on = np.isfinite(hp.log_sf2)
    start_pinned = (hp.log_ls >= PINNED_LOG_LS - 1e-9).any(axis=1)
    fitted, err, evals = {}, {'none': np.mean(Y ** 2, axis=0)}, 0
    cands = _candidates(structure, X, reversing)
    forward = {'none': np.mean(Y[blocks[-1]] ** 2, axis=0)}
    for choice in cands:
        mask = masks[choice]
        h = hp.copy()
        # elements that were off, or pinned where this choice is not (and the reverse), start
        # from the initial hyper-parameters: no warm refinement of another model's optimum
        new = mask & (~start_on | (start_pinned != (choice == 'own')))
        h.log_sf2[new], h.log_ls[new] = fresh.log_sf2[new], fresh.log_ls[new]
        h.log_sf2[~mask] = -np.inf
        if choice == 'own':
            _pin(structure, h.log_ls, mask)
        start = h.copy()
        h, info = learn_hyper(structure, h, Qd, resid, warm=warm and not new.any(),
                              **learn_kw)
        evals += int(info.get('evaluations', 0))
        fitted[choice] = h
        err[choice] = _fold_error(structure, h, X, Y, blocks)
        if len(cands) > 1:
            forward[choice], ev = _forward_error(structure, start, Qd, resid, X, Y,
                                                 blocks[-1], **learn_kw)
            evals += ev
    out = hp.copy()
    choices = []
    keep = keep_all and cands == ('all',)
    for m, rows in enumerate(structure.rows):
        pick = 'none'
        for choice in fitted:
            if choice == 'all' and len(cands) > 1:
                continue
            if err[choice][m] < (1.0 - MARGINS[choice]) * err[pick][m] or keep:
                pick = choice
        if 'all' in forward and _couplings_earn(m, pick, err, forward):
            pick = 'all'
        choices.append(pick)
        r = list(rows)
        if pick == 'none':
            out.log_sf2[r] = -np.inf
        else:
            h = fitted[pick]
            out.log_sf2[r], out.log_ls[r] = h.log_sf2[r], h.log_ls[r]
            out.log_sn2[m] = h.log_sn2[m]
    return out, {'elements': {'choices': choices,
                              'heldout': {c: e.tolist() for c, e in err.items()}},
                 'evaluations': evals}


def choice_summary(choices) -> Optional[str]:
    """Return 'own: 0 1, all: 2, none: 3' for per-output choices (None: none made)."""
    if not choices:
        return None
    parts = []
    for c in ('all', 'own', 'none', 'some'):
        idx = [str(i) for i, x in enumerate(choices) if x == c]
        if idx:
            parts.append(f'{c}: {" ".join(idx)}')
    return ', '.join(parts)
