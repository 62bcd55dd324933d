"""
Online D-GP estimation: the one implementation behind the ROS node, bag replay and the demo.

No rclpy here (everything a node does can be done offline)::

    from dgp_ros.online import EstimatorConfig, OnlineEstimator
    # EstimatorConfig: the same names as the node's parameters
    est = OnlineEstimator(EstimatorConfig(refit_mode='sync'))
    e = est.process(stamp_s, names, velocity, effort)          # -> Estimate, or None if rejected
    est.diagnostics()                                          # dict: level, message, counters

Rooms, by who runs the code (docs/ARCHITECTURE.md has the map), each importing only those before
it: ``config`` (the parameter table) and ``memtrace``; ``jobs`` (what replaces the served model:
``refits``, ``rebase``, ``switch``, ``worker``); ``learner`` (the learner's state and its steps:
``learner``, ``sampling``, ``window``, ``selection``, ``prior``, ``grounds``, ``skill``,
``served``, ``snapshot``, ``plan``, ``files``, ``parts``, ``health``, ``report``); ``process`` (the
learner in a child process: ``proxy`` in the node, ``child`` in the learner process, ``ring`` and
``commands`` between them); ``path`` (the node's thread, never waits: ``estimator``, ``intake``,
``clock``, ``gate``, ``arrays``, ``stream_part``, ``health``).
"""
from dgp_ros.gp import KINDS as MODELS
from dgp_ros.gp import PASSIVITY_MODES

from .config import EstimatorConfig, PARAMS, ParamSpec, REFIT_MODES, SELECTION_POLICIES
from .path.estimator import Estimate, OnlineEstimator
from .path.health import ERROR, OK, REJECT_REASONS, WARN

__all__ = ['EstimatorConfig', 'OnlineEstimator', 'Estimate', 'PARAMS', 'ParamSpec', 'MODELS',
           'PASSIVITY_MODES', 'SELECTION_POLICIES', 'REFIT_MODES', 'REJECT_REASONS', 'OK',
           'WARN', 'ERROR']
