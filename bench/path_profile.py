"""
A profile of the estimator node's message path by stage, in thread CPU (bench/arm_floor.py).

``install()`` wraps the functions of each stage of the node's path in the process it runs in
(``live_procs.py estimator`` with ``DGP_PATH_PROFILE=1``), whichever tree it is: the names of
both the object path (before issue 38) and the raw path are listed, the ones a tree lacks are
skipped. Each call's thread CPU is charged to its stage *exclusively* (a stage called inside
another is taken out of it); what the main thread spends outside every stage is the executor
(waiting, taking, dispatching). The profiler's own cost per wrapped call (two thread clock
reads, about 1 us each) is measured at start and taken out of the stage that pays it (the
caller's). ``report(main_thread_s, received, threads)`` returns the stages' CPU per message
received, with the snapshot receiver's thread and the middleware's threads beside them.
"""
from __future__ import annotations

import importlib
import threading
import time
from typing import Dict, List

#: (stage, [(module, qualified name)]) in the order of the path
STAGES = [
    ('take', [('dgp_ros.nodes.executor', 'WaitSetExecutor._take_batch'),
              ('dgp_ros.nodes.executor', 'WaitSetExecutor._take_one'),
              ('dgp_ros.nodes.estimator', 'EstimatorNode._take_waiting')]),
    ('check outputs', [('dgp_ros.nodes.estimator', 'EstimatorNode._update_outputs'),
                       ('dgp_ros.nodes.answers', 'MessagePath.update_outputs')]),
    ('convert', [('dgp_ros.msgs.sample', 'joint_state_sample'),
                 ('dgp_ros.msgs.cdr', 'JointStateReader.read')]),
    ('validate', [('dgp_ros.online.path.estimator', 'OnlineEstimator._accept'),
                  ('dgp_ros.online.path.intake', 'Intake.check_batch'),
                  ('dgp_ros.online.path.health', 'Health.count_batch')]),
    ('hand over to the learner', [('dgp_ros.online.process.proxy', 'LearnerProcess.learn'),
                                  ('dgp_ros.online.process.proxy', 'LearnerProcess.learn_many'),
                                  ('dgp_ros.online.path.clock', 'LearningClock.time'),
                                  ('dgp_ros.online.path.clock', 'LearningClock.times')]),
    ('predict', [('dgp_ros.online.learner.plan', 'AnswerPlan.answers'),
                 ('dgp_ros.online.path.gate', '_prior')]),
    ('project (passivity)', [('dgp_ros.gp.certified', 'CertifiedPolicy.finalize'),
                             ('dgp_ros.gp.policy', 'PassivityPolicy._project'),
                             ('dgp_ros.gp.psd', 'psd_clip')]),
    ('gate', [('dgp_ros.online.path.gate', 'answer'),
              ('dgp_ros.online.path.gate', '_gate'),
              ('dgp_ros.online.path.gate', '_bound')]),
    ('answers (objects / arrays)', [
        ('dgp_ros.online.path.estimator', 'OnlineEstimator._answer'),
        ('dgp_ros.online.path.estimator', 'OnlineEstimator._array_answers'),
        ('dgp_ros.online.path.arrays', 'answers_of')]),
    ('build the outputs', [('dgp_ros.nodes.estimator', 'EstimatorNode._publish'),
                           ('dgp_ros.nodes.answers', 'MessagePath._publish'),
                           ('dgp_ros.nodes.outputs', 'JointOutput.publish'),
                           ('dgp_ros.msgs.cdr', 'JointStateWriter.write')]),
    ('publish (serialize, DDS write)', [('rclpy.publisher', 'Publisher.publish')]),
    ('callback, the rest', [('dgp_ros.nodes.estimator', 'EstimatorNode._on_states'),
                            ('dgp_ros.nodes.answers', 'MessagePath.answer'),
                            ('dgp_ros.online.path.estimator', 'OnlineEstimator.process_batch'),
                            ('dgp_ros.online.path.arrays', 'ArrayPath.process_arrays')]),
]
RECEIVER = ('dgp_ros.online.process.proxy', 'LearnerProcess._receive')


class _Profiler:
    def __init__(self):
        self.ns: Dict[str, int] = {s: 0 for s, _ in STAGES}
        self.calls: Dict[str, int] = {s: 0 for s, _ in STAGES}
        self.local = threading.local()
        self.main = threading.get_ident()
        self.receiver_tid = None
        self.overhead_ns = 0.0

    def wrap(self, stage: str, fn):
        prof = self
        clock = time.thread_time_ns

        def wrapper(*args, **kw):
            if threading.get_ident() != prof.main:
                return fn(*args, **kw)
            st = prof.local.__dict__.setdefault('stack', [])
            t0 = clock()
            st.append(0)                        # CPU of the stages called inside this one
            try:
                return fn(*args, **kw)
            finally:
                t1 = clock()
                inner = st.pop()
                dt = t1 - t0
                prof.ns[stage] += dt - inner
                prof.calls[stage] += 1
                if st:
                    # the caller's exclusive time: this call and what measuring it cost
                    st[-1] += dt + prof.overhead_ns
        wrapper.__wrapped__ = fn
        return wrapper


_PROF = None


def _resolve(module: str, qual: str):
    try:
        mod = importlib.import_module(module)
    except ImportError:
        return None
    owner, _, name = qual.rpartition('.')
    obj = getattr(mod, owner, None) if owner else mod
    if obj is None or not hasattr(obj, name):
        return None
    return obj, name


def install() -> None:
    """Wrap every stage's functions (call before the node is made)."""
    global _PROF
    prof = _PROF = _Profiler()
    seen = set()
    for stage, names in STAGES:
        for module, qual in names:
            found = _resolve(module, qual)
            if found is None:
                continue
            obj, name = found
            fn = obj.__dict__.get(name) if isinstance(obj, type) else getattr(obj, name)
            if fn is None or id(fn) in seen:
                continue
            seen.add(id(fn))
            w = prof.wrap(stage, fn.__func__ if isinstance(fn, staticmethod) else fn)
            setattr(obj, name, staticmethod(w) if isinstance(fn, staticmethod) else w)
            # functions imported by name elsewhere (``from .answer import answer``)
            if not isinstance(obj, type):
                for mod in list(_importers(module, name, fn)):
                    setattr(mod, name, w)
    found = _resolve(*RECEIVER)
    if found is not None:
        obj, name = found
        fn = getattr(obj, name)

        def receive(self, *args, **kw):
            prof.receiver_tid = (prof.receiver_tid or []) + [threading.get_native_id()]
            return fn(self, *args, **kw)
        setattr(obj, name, receive)
    _calibrate(prof)


def _importers(module: str, name: str, fn):
    import sys
    for m in list(sys.modules.values()):
        if m is None or getattr(m, '__name__', '') == module:
            continue
        if getattr(m, name, None) is fn and getattr(m, '__name__', '').startswith('dgp_ros'):
            yield m


def _calibrate(prof: _Profiler) -> None:
    """Measure what one wrapped call costs its caller (thread CPU, ns)."""
    stage = STAGES[0][0]
    noop = prof.wrap(stage, lambda: None)
    outer = prof.wrap(stage, lambda: [noop() for _ in range(2000)])
    best = None
    for _ in range(5):
        t0 = time.thread_time_ns()
        for _ in range(2000):
            (lambda: None)()
        bare = time.thread_time_ns() - t0
        t0 = time.thread_time_ns()
        outer()
        wrapped = time.thread_time_ns() - t0
        per = max(0.0, (wrapped - bare) / 2000)
        best = per if best is None else min(best, per)
    prof.overhead_ns = best
    prof.ns = {s: 0 for s, _ in STAGES}
    prof.calls = {s: 0 for s, _ in STAGES}


def _thread_cpu(tids) -> float:
    from cpu_watch import proc_stat
    return sum(st[2] for st in (proc_stat(f'/proc/self/task/{t}/stat') for t in tids or ()) if st)


def report(main_thread_s: float, received: int, threads: Dict[str, float]) -> dict:
    """
    Return {'stages': [(stage, us per message, calls)], ...} since ``install``.

    ``main_thread_s``: the main thread's CPU over the stream; ``threads``: CPU seconds by
    thread name (``live_procs.thread_cpu``), for the middleware's threads.
    """
    prof = _PROF
    if prof is None or not received:
        return {}
    per = 1e-3 / received
    rows: List[tuple] = [(s, prof.ns[s] * per, prof.calls[s]) for s, _ in STAGES]
    staged = sum(prof.ns.values()) * 1e-9
    rows.append(('executor (wait, dispatch)', max(0.0, main_thread_s - staged) * 1e6 / received,
                 0))
    receiver = _thread_cpu(prof.receiver_tid)
    dds = sum(v for k, v in threads.items() if k.startswith('dds.'))
    return {'stages': rows, 'receiver_us': receiver * 1e6 / received,
            'dds_us': dds * 1e6 / received, 'overhead_ns_per_call': prof.overhead_ns,
            'received': received}
