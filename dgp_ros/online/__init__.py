"""
Online D-GP estimation: the one implementation behind the ROS node, bag replay and the demo.

No rclpy here (everything a node does can be done offline)::

    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    # EstimatorConfig: the same names as the node's parameters
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    e = est.process(stamp_s, names, velocity, effort)          # -> Estimate, or None if rejected
    est.diagnostics()                                          # dict: level, message, counters

Modules: ``config`` (parameters and their specs), ``estimator`` (the message path, with its
parts ``intake`` and ``clock``), ``learner`` (what is learned, composed of parts that own their
state: ``front``, ``window``, ``structure``, ``grounds``, ``served``, ``jobs``, ``absorb``,
``switch``, ``snapshot``, ``files``), ``process``/``child`` (the learner in a child process),
``health`` and ``report`` (counters and status); docs/ARCHITECTURE.md has the map.
"""
from dgp_ros.gp import KINDS as MODELS
from dgp_ros.gp import PASSIVITY_MODES

from .config import EstimatorConfig, PARAMS, ParamSpec, REFIT_MODES, SELECTION_POLICIES
from .estimator import Estimate, OnlineEstimator
from .health import ERROR, OK, REJECT_REASONS, WARN

__all__ = ['EstimatorConfig', 'OnlineEstimator', 'Estimate', 'PARAMS', 'ParamSpec', 'MODELS',
           'PASSIVITY_MODES', 'SELECTION_POLICIES', 'REFIT_MODES', 'REJECT_REASONS', 'OK',
           'WARN', 'ERROR']
