"""
What every attack class of ``bench/hostile.py`` shares.

The sandbox (a private directory with decoys, fingerprinted before and after), the good stream
(smooth 3-joint velocities, a passive damping force plus noise), the checks of one answer
(``est_ok``) and the tally of one class (``Tally``, ``feed``: one message through
``OnlineEstimator.process``, counted and checked).
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import os
import shutil
import stat
import tempfile
from typing import List

import numpy as np

#: the joints of the good stream
NAMES = ['a', 'b', 'c']
EPS = np.finfo(float).eps


# ----------------------------------------------------------------------------- environment
def proc_status(key: str, pid='self') -> float:
    """Read a ``/proc/<pid>/status`` field in MiB (VmRSS, VmHWM); NaN if unreadable."""
    try:
        with open(f'/proc/{pid}/status') as f:
            for line in f:
                if line.startswith(key + ':'):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


# ----------------------------------------------------------------------------- sandbox
class Sandbox:
    """A private directory with decoys, and a snapshot of what is on disk."""

    def __init__(self):
        self.root = tempfile.mkdtemp(prefix='dgp_hostile_')
        self.decoys = os.path.join(self.root, 'decoys')
        self.outside = os.path.join(self.root, 'outside')
        self.files = os.path.join(self.root, 'files')     # hostile model files (inputs)
        self.models = os.path.join(self.root, 'models')   # the estimators' own model files
        self.scratch = os.path.join(self.root, 'scratch')  # copies used as model_path
        self.bags = os.path.join(self.root, 'bags')
        self.logs = os.path.join(self.root, 'logs')
        for d in (self.decoys, self.outside, self.files, self.models, self.scratch, self.bags,
                  self.logs):
            os.makedirs(d)
        with open(os.path.join(self.outside, 'secret.txt'), 'w') as f:
            f.write("not the estimator's file\n")
        with open(os.path.join(self.decoys, 'notes.txt'), 'w') as f:
            f.write("a user's text file\n")
        with open(os.path.join(self.decoys, 'notes.npz'), 'w') as f:
            f.write('a text file named like a model\n')
        np.savez(os.path.join(self.decoys, 'user_arrays.npz'), x=np.arange(5.0))
        os.makedirs(os.path.join(self.decoys, 'dir.npz'))
        os.mkfifo(os.path.join(self.decoys, 'fifo.npz'))
        os.symlink(os.path.join(self.outside, 'secret.txt'),
                   os.path.join(self.decoys, 'link.npz'))
        os.symlink('/dev/zero', os.path.join(self.decoys, 'zero.npz'))

    def decoy(self, name: str) -> str:
        return os.path.join(self.decoys, name)

    def snapshot(self) -> dict:
        """
        Fingerprint the sandbox.

        {path: (kind, ino, size, mtime_ns, sha256)} of the sandbox's inputs and decoys (not
        the models/scratch/logs directories, which the estimator may write), plus devices.
        """
        out = {}
        for top in (self.decoys, self.outside, self.files, self.bags):
            for dp, dns, fns in os.walk(top):
                for n in dns + fns:
                    p = os.path.join(dp, n)
                    out[p] = fingerprint(p)
        for p in ('/dev/full', '/dev/zero', '/dev/null'):
            out[p] = fingerprint(p)
        return out

    def cleanup(self):
        shutil.rmtree(self.root, ignore_errors=True)


def fingerprint(p: str):
    try:
        st = os.lstat(p)
    except OSError:
        return ('missing',)
    kind = stat.S_IFMT(st.st_mode)
    digest = ''
    if stat.S_ISREG(st.st_mode) and st.st_size < (64 << 20):
        h = hashlib.sha256()
        with open(p, 'rb') as f:
            for chunk in iter(lambda: f.read(1 << 20), b''):
                h.update(chunk)
        digest = h.hexdigest()
    return (kind, st.st_ino, st.st_size, st.st_mtime_ns, st.st_rdev, digest)


def touched(before: dict, after: dict) -> List[str]:
    return sorted(p for p in set(before) | set(after) if before.get(p) != after.get(p))


# ----------------------------------------------------------------------------- data
def truth(q):
    return np.array([2.0, 1.0, 0.5]) * q + 0.3 * np.tanh(np.asarray(q) / 0.1)


class Good:
    """The good stream: smooth 3-joint velocities, passive damping force plus noise."""

    def __init__(self, t0=0.0, dt=0.01, seed=0):
        self.t, self.dt = float(t0), float(dt)
        self.rng = np.random.default_rng(seed)

    def q(self, t):
        return np.array([np.sin(t), np.cos(0.7 * t), 0.5 * np.sin(0.3 * t + 1.0)])

    def next(self):  # noqa: A003 (a method: it shadows nothing)
        t = self.t
        self.t += self.dt
        q = self.q(t)
        return t, q, truth(q) + 0.01 * self.rng.normal(size=3)


def est_ok(e, passivity: str):
    """(finite, passive, strictly_non_negative, D consistent) of one Estimate."""
    arrs = [e.tau_hat, e.stddev, e.qd] + ([e.D] if e.D is not None else [])
    finite = all(np.all(np.isfinite(a)) for a in arrs) and math.isfinite(e.power)
    if not finite:
        return False, True, True, True
    p = float(e.qd @ e.tau_hat)
    tol = 8.0 * EPS * float(np.abs(e.qd) @ np.abs(e.tau_hat))
    passive = passivity == 'none' or (p >= -tol and e.power >= 0.0)
    consistent = True
    if e.D is not None:
        consistent = bool(np.allclose(e.D @ e.qd, e.tau_hat, rtol=1e-6,
                                      atol=1e-9 * (1 + np.abs(e.tau_hat).max())))
    return True, passive, p >= 0.0, consistent


@dataclasses.dataclass
class Tally:
    """One attack class against one estimator: counts and the checks."""

    name: str
    sent: int = 0
    answered: int = 0
    rejected: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    nonfinite: int = 0
    nonpassive: int = 0
    strict_negative: int = 0        # qd . tau_hat < 0 within rounding (reported as power 0)
    d_inconsistent: int = 0         # published D with D qd != tau_hat
    exceptions: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    untruthful: int = 0             # counters disagree with what happened to the message
    unexpected: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    seconds: float = 0.0
    refits: int = 0                 # refit / recertify jobs started during the class
    notes: List[str] = dataclasses.field(default_factory=list)

    def reasons(self) -> str:
        return ', '.join(f'{k} {v}' for k, v in sorted(self.rejected.items())) or '-'

    def failed(self) -> bool:
        return bool(self.nonfinite or self.nonpassive or sum(self.exceptions.values()) or
                    self.untruthful)


def feed(est, T: Tally, stamp, names, v, e, expect=None):
    """
    One message through ``est.process``; checks and counts (see Tally).

    ``expect``: None (either), 'answer', or a collection of acceptable rejection reasons.
    """
    h, lh = est.health, est.learner.health
    rej0 = dict(h.rejected)
    rec0 = h.messages_received
    ref0 = lh.refits_started + lh.recertifications
    T.sent += 1
    try:
        out = est.process(stamp, names, v, e)
    except Exception as exc:  # noqa: BLE001 - counted: process() must never raise
        T.exceptions[type(exc).__name__] += 1
        return None
    T.refits += lh.refits_started + lh.recertifications - ref0
    diff = {k: n - rej0[k] for k, n in h.rejected.items() if n != rej0[k]}
    ok = h.messages_received == rec0 + 1
    if out is None:
        ok = ok and len(diff) == 1 and sum(diff.values()) == 1
        reason = next(iter(diff), '(no reason counted)')
        T.rejected[reason] += 1
        if expect is not None and (expect == 'answer' or reason not in expect):
            T.unexpected[f'rejected {reason}'] += 1
    else:
        ok = ok and not diff
        T.answered += 1
        fin, pas, strict, cons = est_ok(out, est.config.passivity)
        T.nonfinite += not fin
        T.nonpassive += not pas
        T.strict_negative += fin and not strict
        T.d_inconsistent += not cons
        if expect is not None and expect != 'answer':
            T.unexpected['answered'] += 1
    T.untruthful += not ok
    return out


def short(v) -> str:
    if isinstance(v, str) and len(v) > 20:
        return f"'{v[:3]}...' ({len(v)} chars)"
    if isinstance(v, (list, tuple)) and len(v) > 4:
        return f'[{short(v[0])}, ...] ({len(v)} entries)'
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return repr(v)
