"""Pure numpy/scipy Dissipative Gaussian Processes (no ROS import anywhere in this package).

Models (DESIGN "Core API"): ``FullDGP``, ``DiagDGP``, ``ArdGP`` with fit / predict /
damping_matrix / certificate / update / save / load. See ``models`` for units and shapes and
``passivity`` / ``verify`` for the passivity guarantees (docs/PASSIVITY.md).
"""
from .kernels import se_ard, se_bound
from .models import (FORMAT_VERSION, ArdGP, DiagDGP, FullDGP, load_model, make_model,
                     prior_mean_diag)
from .passivity import Certificate, copositivity_margin, project_passive

__all__ = ['ArdGP', 'DiagDGP', 'FullDGP', 'make_model', 'load_model', 'prior_mean_diag',
           'Certificate', 'copositivity_margin', 'project_passive', 'se_ard', 'se_bound',
           'FORMAT_VERSION']
