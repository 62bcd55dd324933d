"""
The check of a model's constructor arguments (scikit-learn: ``__init__`` stores, ``fit`` checks).

Every failed check is a ValueError that names the argument and what it must be.
"""
from __future__ import annotations

import numpy as np

from ._validation import as_box
from .means import PriorMean, PRIORS
from .passivity import check_mode
from .policy import PolicyOptions


def check_params(model, N: int):
    """
    Validate a model's constructor arguments for N velocities; return its policy options.

    ``model``: a ``models._DGP`` (its constructor arguments as attributes). ValueError naming
    the first bad argument.
    """
    check_mode(model.passivity, model._kind)
    w = model.window
    if w is not None and (isinstance(w, bool) or int(w) != w or w < 1):
        raise ValueError(f'window must be a positive integer or None, got {w!r}')
    for name, low in (('n_restarts', 0), ('max_opt_samples', 1), ('max_boxes', 1)):
        v = getattr(model, name)
        if isinstance(v, bool) or int(v) != v or v < low:
            raise ValueError(f'{name} must be an integer >= {low}, got {v!r}')
    nf = model.noise_floor
    if nf is not None and not (isinstance(nf, (int, float)) and 0 < nf <= 1.0):
        raise ValueError(f'noise_floor must be in (0, 1] or None, got {nf!r}')
    if not (model.domain_margin >= 0 and model.blend_width > 0):
        raise ValueError('domain_margin must be >= 0 and blend_width > 0')
    if not isinstance(model.prior, PriorMean) and model.prior not in PRIORS:
        raise ValueError(f"prior must be one of {', '.join(PRIORS)}, got {model.prior!r}")
    if model.elements not in ('all', 'auto'):
        raise ValueError(f"elements must be 'all' or 'auto', got {model.elements!r}")
    pw = model.projection_weights
    if pw is not None:
        pw = np.asarray(pw, float)
        if pw.shape != (N,) or np.any(~np.isfinite(pw)) or np.any(pw <= 0):
            raise ValueError(f'projection_weights must be {N} positive finite numbers')
    od = model.operating_domain
    od = None if od is None else as_box(od, N, 'operating_domain')
    return PolicyOptions(float(model.domain_margin), float(model.blend_width),
                         int(model.max_boxes), od, pw)
