"""
Dissipative Gaussian Processes in pure numpy/scipy (no ROS import anywhere in this package).

Estimators (scikit-learn shape): ``FullDGP``, ``DiagDGP``, ``ArdGP`` with fit / predict /
damping_matrix / certificate / recertify / update / save / load.

Pieces, one module each: ``kernels`` (the SE kernel, element structure), ``means`` (passive prior
means), ``posterior`` (exact inference), ``hyper`` (hyper-parameter learning), ``passivity`` (the
registry of passivity modes and their policies; ``certified`` and ``verify`` for the structural
proof), ``persistence`` (model files), ``models`` (the estimators; ``fitted``: their fitted
attributes), ``joint_element`` (the per-joint element of D learned from every sample: a
reduced-rank GP on each joint's velocity), ``coupled`` (the couplings of a velocity that never
nears zero, an aircraft's airspeed, in the prior mean).
"""
from . import coupled, joint_element, transmission  # noqa: F401 - register their prior means
from .kernels import KINDS, se_ard, se_bound
from .means import prior_mean_diag, PRIORS
from .models import ArdGP, DiagDGP, FullDGP, load_model, make_model, model_class
from .passivity import (copositivity_margin, modes_for, PASSIVITY_MODES, POLICIES,
                        policy_class)
from .persistence import FORMAT_VERSION
from .policy import Certificate, GUARANTEES, passive_tolerance, project_passive

__all__ = ['ArdGP', 'DiagDGP', 'FullDGP', 'make_model', 'model_class', 'load_model',
           'prior_mean_diag', 'Certificate', 'copositivity_margin', 'project_passive',
           'passive_tolerance', 'se_ard', 'se_bound', 'FORMAT_VERSION', 'KINDS', 'PRIORS',
           'PASSIVITY_MODES', 'POLICIES', 'modes_for', 'policy_class', 'GUARANTEES']
