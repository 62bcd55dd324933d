"""
Estimator parameters: one table of specs (name, default, range, description).

The same table serves the ROS node (parameter declarations with ``ParameterDescriptor`` ranges,
``--help``), ``dgp-replay --set`` and the YAML defaults file (a test keeps them in sync), so a
parameter is described and bounded in exactly one place. Every range is finite: a value a peer
sets at run time can neither overflow a timer nor allocate without bound.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
import os
from typing import List

from dgp_ros.gp import KINDS, PASSIVITY_MODES, PRIORS
from dgp_ros.gp.passivity import check_mode, describe_modes
from dgp_ros.params import check_spec, ParamSpec

__all__ = ['ParamSpec', 'PARAMS', 'EstimatorConfig', 'SELECTION_POLICIES', 'REFIT_MODES',
           'MODEL_SUFFIX']

SELECTION_POLICIES = ('all', 'novelty')
REFIT_MODES = ('process', 'async', 'sync')
MODEL_SUFFIX = '.npz'


PARAMS = {p.name: p for p in (
    ParamSpec('model', 'str', 'full', 'damping model: Full-D-GP, Diag-D-GP or the ARD-GP baseline',
              choices=KINDS),
    ParamSpec('passivity', 'str', 'certified', describe_modes(), choices=PASSIVITY_MODES),
    ParamSpec('elements', 'str', 'auto', 'which elements of D each joint keeps: auto (at each '
              'hyper-parameter refit, by 4-fold blocked cross-validation over the buffer: each '
              'contiguous quarter predicted by the rest; none, the parametric part alone; its '
              'diagonal element; or also its couplings to the other joints, only where they '
              'predict better; on an arm only beside a velocity that never nears zero) or all '
              "(every element of the model kind: the paper's Full-D-GP)", choices=('auto', 'all')),
    ParamSpec('prior', 'str', 'auto', 'prior mean of the damping: auto (the structure is chosen '
              'from the data by cross-validation: friction family, offsets, the conservative '
              'correction of the rigid-body model; fitted on the whole history), or fixed: '
              'constant viscous diagonal (the paper), Coulomb + viscous, + Stribeck (fitted on '
              'the buffer)', choices=('auto',) + tuple(PRIORS)),
    ParamSpec('history_elements', 'bool', True, 'prior auto, on an arm (inverse_dynamics set) '
              'only: each joint may carry an element of D learned from every sample (a '
              'reduced-rank GP on its velocity, in the long history), kept where it predicts '
              'the newest blocks better than the parametric part and two halves of the run '
              'learn it alike; false: the parametric part alone'),
    ParamSpec('bias', 'bool', False, 'fixed prior only: learn a per-joint constant bias with the '
              'prior (reported apart from the damping force); auto decides itself'),
    ParamSpec('noise_floor', 'float', 1e-5, 'least noise variance the hyper-parameter fit may '
              "learn, in units of the residual's variance: a stream's consecutive samples, and "
              'forces that depend on states the model does not see, drive the likelihood to '
              'near-zero noise and lengthscales too short to predict the next sample',
              low=1e-9, high=1.0),
    ParamSpec('buffer_size', 'int', 200, 'samples kept in the GP (its window)', low=2, high=5000),
    ParamSpec('min_samples', 'int', 20, 'prior-mean estimate until this many samples are '
              'buffered', low=1, high=5000),
    ParamSpec('refit_period_s', 'float', 10.0, 'message-stamp seconds between refits; 0 = first '
              'fit and on request only', low=0.0, high=86400.0),
    ParamSpec('optimize_every_n_refits', 'int', 5, 'hyper-parameters re-learned every n-th '
              'refit, and when a sample the model answered badly lies beyond the velocities '
              'they were learned on (0 = first fit only; so with refit_period_s 0)',
              low=0, high=1000),
    ParamSpec('buffer_policy', 'str', 'coverage', 'which sample a full buffer replaces: '
              'coverage (one of the two closest in velocity: the buffer keeps the motion that was '
              'visited) or recency (the oldest)', choices=('coverage', 'recency')),
    ParamSpec('selection', 'str', 'novelty', 'sample selection: all, or skip near-duplicates of '
              'buffered samples', choices=SELECTION_POLICIES),
    ParamSpec('selection_min_distance', 'float', 0.05, 'novelty threshold, in robust scales of '
              'the buffered velocities', low=0.0, high=100.0),
    ParamSpec('selection_scale', 'float[]', [], 'per-joint novelty scale, velocity units '
              '([] = robust scale of the buffer)', low=1e-12, high=1e12, max_len=64),
    ParamSpec('min_sample_interval_s', 'float', 0.01, 'learn at most one sample per this much '
              'stamp time (0 = every sample); every message still gets an estimate',
              low=0.0, high=60.0),
    ParamSpec('joints', 'str[]', [], 'joint names to select and order ([] = message order)',
              max_len=64),
    ParamSpec('max_joints', 'int', 16, 'messages with more joints than this are rejected',
              low=1, high=64),
    ParamSpec('model_path', 'str', '', f'model file ({MODEL_SUFFIX}): loaded at start, saved on '
              'refit, shutdown and ~/save_model; only a dgp_ros model file is overwritten',
              max_len=4096),
    ParamSpec('learning', 'bool', True, 'learn from the stream; false: serve only the current '
              'or loaded model (nothing learned, no refits, ~/friction_residual still '
              'published); switching it off proves the model once with the full proof and saves '
              'it to model_path; switching it on resumes learning'),
    ParamSpec('refit_mode', 'str', 'process', 'where the learner runs: process (a child '
              'process at lower priority; answers never wait for learning), async (this '
              'process, refits in a background thread) or sync (in line: replay, tests)',
              choices=REFIT_MODES),
    ParamSpec('max_abs_velocity', 'float', 1.0e4, '|velocity| above this: message rejected '
              '(out_of_range)', low=1e-9, high=1e6),
    ParamSpec('max_abs_effort', 'float', 1.0e8, '|effort| above this: message rejected '
              '(out_of_range)', low=1e-9, high=1e12),
    ParamSpec('effort_scale', 'float[]', [], 'joint torque per unit of the published effort '
              '(N m per unit: for a motor current, torque constant x gear ratio), one per joint '
              'or one for all; a negative entry flips a sign convention ([] = the effort is '
              'joint torque in N m); a change resets the learner', low=-1e6, high=1e6,
              max_len=64),
    ParamSpec('inverse_dynamics', 'str', '', 'rigid-body model subtracted from the effort before '
              "learning: '' (the effort already is the damping force), 'urdf' (pinocchio, from "
              "robot_description or urdf_file) or 'python:<module>:<function>' "
              '(f(q, qd, qdd) -> tau_rb); start-up only', max_len=4096, read_only=True),
    ParamSpec('robot_description', 'str', '', 'URDF text for inverse_dynamics=urdf (the ROS '
              'convention; wins over urdf_file; with neither, the node takes it from the '
              '/robot_description topic); start-up only', max_len=50_000_000,
              read_only=True),
    ParamSpec('urdf_file', 'str', '', 'URDF path for inverse_dynamics=urdf; start-up only',
              max_len=4096, read_only=True),
    ParamSpec('accel_half_window_s', 'float', 0.05, 'half window of the centred acceleration '
              'filter (s): learning trails the stream by this much; answers are immediate (20 ms '
              'turned torque-sensor noise into target noise through M(q) on a real Panda)',
              low=0.002, high=0.2),
    ParamSpec('negative_power_warn_fraction', 'float', 0.1, 'WARN when more than this fraction '
              'of the recent learned samples has qd . target < 0 (the data are not damping)',
              low=0.0, high=1.0),
    ParamSpec('operating_domain', 'float[]', [], 'certified: declared operating box '
              "[lo_1..lo_N, hi_1..hi_N] in the joints' units, proven with the data box "
              '([] = data box only)', low=-1e12, high=1e12, max_len=128),
)}


@dataclass
class EstimatorConfig:
    """
    Parameters of the online estimator; the node's ROS parameters have the same names.

    Defaults, ranges and descriptions: ``PARAMS`` (printed by ``estimator --help``).
    """

    model: str = PARAMS['model'].default
    passivity: str = PARAMS['passivity'].default
    elements: str = PARAMS['elements'].default
    prior: str = PARAMS['prior'].default
    history_elements: bool = PARAMS['history_elements'].default
    bias: bool = PARAMS['bias'].default
    noise_floor: float = PARAMS['noise_floor'].default
    buffer_size: int = PARAMS['buffer_size'].default
    min_samples: int = PARAMS['min_samples'].default
    refit_period_s: float = PARAMS['refit_period_s'].default
    optimize_every_n_refits: int = PARAMS['optimize_every_n_refits'].default
    buffer_policy: str = PARAMS['buffer_policy'].default
    selection: str = PARAMS['selection'].default
    selection_min_distance: float = PARAMS['selection_min_distance'].default
    selection_scale: List[float] = field(default_factory=list)
    min_sample_interval_s: float = PARAMS['min_sample_interval_s'].default
    joints: List[str] = field(default_factory=list)
    max_joints: int = PARAMS['max_joints'].default
    model_path: str = PARAMS['model_path'].default
    learning: bool = PARAMS['learning'].default
    refit_mode: str = PARAMS['refit_mode'].default
    max_abs_velocity: float = PARAMS['max_abs_velocity'].default
    max_abs_effort: float = PARAMS['max_abs_effort'].default
    effort_scale: List[float] = field(default_factory=list)
    inverse_dynamics: str = PARAMS['inverse_dynamics'].default
    robot_description: str = PARAMS['robot_description'].default
    urdf_file: str = PARAMS['urdf_file'].default
    accel_half_window_s: float = PARAMS['accel_half_window_s'].default
    negative_power_warn_fraction: float = PARAMS['negative_power_warn_fraction'].default
    operating_domain: List[float] = field(default_factory=list)

    # ------------------------------------------------------------------ validation
    def validate(self) -> 'EstimatorConfig':
        """Raise ValueError naming the bad field and why; return self."""
        for spec in PARAMS.values():
            check_spec(spec, getattr(self, spec.name))
        check_mode(self.passivity, self.model)
        if self.min_samples > self.buffer_size:
            raise ValueError(f'min_samples={self.min_samples}: must be <= buffer_size '
                             f'({self.buffer_size}), else the model is never trained')
        if len(set(self.joints)) != len(self.joints):
            raise ValueError(f'joints={self.joints!r}: names must be unique')
        if len(self.joints) > self.max_joints:
            raise ValueError(f'joints: {len(self.joints)} names, more than max_joints '
                             f'({self.max_joints})')
        if self.joints and self.selection_scale and \
                len(self.selection_scale) != len(self.joints):
            raise ValueError(f'selection_scale={self.selection_scale!r}: needs one entry per '
                             f'joint ({len(self.joints)})')
        if any(x == 0.0 for x in self.effort_scale):
            raise ValueError(f'effort_scale={self.effort_scale!r}: a zero would erase the '
                             'effort (torque per effort unit, e.g. 12.0 for a current)')
        if self.joints and len(self.effort_scale) not in (0, 1, len(self.joints)):
            raise ValueError(f'effort_scale={self.effort_scale!r}: needs one entry, or one per '
                             f'joint ({len(self.joints)})')
        od = self.operating_domain
        if od:
            if len(od) % 2:
                raise ValueError(f'operating_domain={od!r}: needs an even length: N lower '
                                 'bounds, then N upper')
            k = len(od) // 2
            if any(hi <= lo for lo, hi in zip(od[:k], od[k:])):
                raise ValueError(f'operating_domain={od!r}: every lower bound must be below '
                                 'its upper bound')
            if self.joints and k != len(self.joints):
                raise ValueError(f'operating_domain={od!r}: needs 2 x {len(self.joints)} entries '
                                 '(one lower and one upper bound per joint)')
        if self.model_path:
            check_model_path(self.model_path)
        spec = self.inverse_dynamics
        if spec and spec != 'urdf' and not (spec.startswith('python:') and
                                            len(spec.split(':')) == 3 and all(spec.split(':'))):
            raise ValueError(f"inverse_dynamics={spec!r}: must be '', 'urdf' or "
                             "'python:<module>:<function>'")
        if spec == 'urdf' and not self.robot_description and self.urdf_file and \
                not os.path.isfile(self.urdf_file):
            raise ValueError(f'urdf_file={self.urdf_file!r}: no such file')
        return self

    @property
    def awaits_urdf(self) -> bool:
        """
        Tell whether the robot model is still to come.

        ``inverse_dynamics=urdf`` with neither ``robot_description`` nor ``urdf_file``: the node
        takes the URDF from the ``/robot_description`` topic (as ros2_control does); until then
        nothing is learned.
        """
        return self.inverse_dynamics == 'urdf' and not (self.robot_description
                                                        or self.urdf_file)

    def check_dimension(self, N: int) -> None:
        """
        Raise ValueError when a per-joint parameter does not fit N joints.

        An estimator is sized by the joint count its first message fixes (the learner's
        buffers, its process' ring, the answers): ``joints`` of another count at run time is
        refused with the reason, never half applied.
        """
        if self.joints and len(self.joints) != N:
            raise ValueError(f'joints: {len(self.joints)} names, but this estimator serves {N} '
                             'joints since its first message; restart the node (with -p '
                             'joints:=...) to serve another number of joints')
        if self.operating_domain and len(self.operating_domain) != 2 * N:
            raise ValueError(f'operating_domain has {len(self.operating_domain)} entries, the '
                             f'{N} joints need {2 * N}')
        if self.selection_scale and len(self.selection_scale) != N:
            raise ValueError(f'selection_scale has {len(self.selection_scale)} entries, the '
                             f'{N} joints need {N}')
        if len(self.effort_scale) not in (0, 1, N):
            raise ValueError(f'effort_scale has {len(self.effort_scale)} entries, the {N} '
                             f'joints need 1 or {N}')

    @classmethod
    def from_dict(cls, d: dict) -> 'EstimatorConfig':
        """Build from a dict (e.g. ROS parameters); unknown keys raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f'unknown estimator parameter(s): {", ".join(sorted(unknown))} '
                             f'(known: {", ".join(sorted(names))})')
        kw = dict(d)
        for k in ('joints', 'selection_scale', 'effort_scale', 'operating_domain'):
            if k in kw and kw[k] is not None and not isinstance(kw[k], (str, bytes)):
                try:
                    kw[k] = list(kw[k])
                except TypeError:
                    pass
        return cls(**kw)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def model_kwargs(self) -> dict:
        """
        Return the GP's constructor arguments for this configuration.

        Passivity, prior, noise floor, no window: the learner appends each new sample to the
        model and rebases it on the buffer every so often (``jobs.rebase``); the buffer holds the
        window.
        """
        kw = {'passivity': self.passivity, 'window': None, 'noise_floor': self.noise_floor,
              'elements': self.elements,
              'prior': 'viscous' if self.prior == 'auto' else self.prior,
              'bias': bool(self.bias) and self.prior != 'auto',
              # an arm's window is one path (its velocities move together): couplings there
              # are what the path fakes, tried only beside a velocity that never nears zero
              'couplings': 'persistent' if self.inverse_dynamics else 'evidence'}
        if self.operating_domain and self.passivity == 'certified':
            k = len(self.operating_domain) // 2
            kw['operating_domain'] = (list(self.operating_domain[:k]),
                                      list(self.operating_domain[k:]))
        return kw


#: parameters of the ROS node that are not estimator parameters (same table format)
NODE_PARAMS = {p.name: p for p in (
    ParamSpec('diagnostics_period_s', 'float', 1.0, 'period of /diagnostics (node clock, s)',
              low=0.01, high=3600.0),
    ParamSpec('queue_depth', 'int', 1000, 'depth of the generalized_state subscription queue '
              '(best effort: what does not fit is dropped and counted)', low=1, high=100000),
)}


def defaults_yaml() -> str:
    """
    Return the text of ``config/estimator.yaml``.

    ``config/estimator.yaml``: every parameter with its default, range and description
    (generated from ``PARAMS``; a test keeps the file equal to this text).
    """
    import textwrap
    lines = ['# Parameters of the dgp_estimator node (dgp_ros/nodes/estimator.py), generated from',
             '# dgp_ros.online.config.PARAMS; regenerate with',
             '#   python -c "import dgp_ros.online.config as c; '
             'print(c.defaults_yaml(), end=\'\')"'
             ' > config/estimator.yaml',
             '# Use: estimator --ros-args --params-file config/estimator.yaml',
             'dgp_estimator:', '  ros__parameters:']
    for spec in list(PARAMS.values()) + list(NODE_PARAMS.values()):
        rng = spec.range_text()
        doc = f'{spec.name}: {spec.description}' + (f' ({rng})' if rng else '')
        lines += textwrap.wrap(doc, 99, initial_indent='    # ', subsequent_indent='    #   ')
        if spec.type.endswith('[]') and not spec.default:
            # an empty YAML list has no type for the ROS parser: set it only when needed
            lines.append(f'    # {spec.name}: []')
        else:
            lines.append(f'    {spec.name}: {_yaml_scalar(spec.default)}')
    return '\n'.join(lines) + '\n'


def _yaml_scalar(value) -> str:
    """
    Return ``value`` as a YAML scalar that YAML 1.1 parsers read back with its type.

    A float in exponent form gets a decimal point (``1.0e-05``): to YAML 1.1 (PyYAML, the ROS
    parameter file parser) ``1e-05`` is a string.
    """
    import json
    if isinstance(value, list):
        return '[' + ', '.join(_yaml_scalar(v) for v in value) + ']'
    text = json.dumps(value)
    if isinstance(value, float) and 'e' in text:
        mantissa, exponent = text.split('e')
        if '.' not in mantissa:
            mantissa += '.0'
        text = f'{mantissa}e{exponent}'
    return text


def check_model_path(path: str) -> None:
    """
    Raise ValueError unless ``path`` may be read and written as the estimator's model file.

    Allowed: a path ending in ``.npz`` in an existing directory that either does not exist yet or
    is a regular file holding a dgp_ros model (never a directory, device, FIFO, a symlink, or
    another file, which a save would overwrite).
    """
    from dgp_ros.gp.persistence import is_model_file
    if '\0' in path:
        raise ValueError('model_path: contains a NUL byte')
    if not path.endswith(MODEL_SUFFIX):
        raise ValueError(f'model_path={path!r}: must end in {MODEL_SUFFIX}')
    d = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(d):
        raise ValueError(f'model_path={path!r}: directory {d} does not exist')
    if os.path.lexists(path):
        if os.path.islink(path):
            raise ValueError(f'model_path={path!r}: is a symbolic link; give the real path')
        if not os.path.isfile(path):
            raise ValueError(f'model_path={path!r}: exists and is not a regular file')
        if not is_model_file(path):
            raise ValueError(f'model_path={path!r}: exists and is not a dgp_ros model file; '
                             f'refusing to overwrite it')
