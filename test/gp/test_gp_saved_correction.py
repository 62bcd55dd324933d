"""
A saved model's correction is rebuilt by the layer that owns it: ``dgp_ros.gp`` imports no other.

``dgp_ros.dynamics`` registers the 'conservative' kind with ``gp.persistence`` when imported,
and dgp_ros declares it as an entry point (``setup.py``, group ``dgp_ros.corrections``). A fresh
interpreter that imports only ``dgp_ros.gp`` loads such a model without importing the owner
(its damping force needs no correction), keeps the correction's record (saved back unchanged),
and ``predict_residual`` finds the owner through the entry point and answers as the model that
was saved. A kind nobody declares says what to install or import. Files written before the
record carried its kind still load.
"""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from dgp_ros.dynamics.conservative import Correction, PotentialBasis
from dgp_ros.gp import FullDGP, load_model
from dgp_ros.gp.persistence import rebuild_correction, SavedCorrection

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

#: run in a fresh interpreter: only dgp_ros.gp imported when the model is loaded
FRESH = r"""
import json, sys
import numpy as np
from dgp_ros.gp import load_model
path, data, again = sys.argv[1:4]
d = np.load(data)
m = load_model(path)
out = {'dynamics_loaded': any(k.startswith('dgp_ros.dynamics') for k in sys.modules),
       'predict': np.abs(m.predict(d['V']) - d['tau']).max(),
       'kept': type(m.correction_).__name__}
m.save(again)                          # the record goes back unchanged
out['residual'] = np.abs(m.predict_residual(q=d['Q'], qd=d['V']) - d['res']).max()
out['dynamics_after'] = 'dgp_ros.dynamics.conservative' in sys.modules
print(json.dumps(out))
"""


@pytest.fixture(scope='module')
def saved(tmp_path_factory):
    """Save a fitted Full-D-GP with a conservative correction (a trigonometric potential)."""
    rng = np.random.default_rng(0)
    V = rng.uniform(-1, 1, (80, 2))
    Q = rng.uniform(-2, 2, (80, 2))
    m = FullDGP(passivity='projected', prior='viscous').fit(V, 0.8 * V + 0.05 * rng.normal(
        size=V.shape))
    basis = PotentialBasis(2)
    m.correction_ = Correction(basis, rng.normal(size=basis.C), np.array([0.3, -0.1]))
    d = tmp_path_factory.mktemp('saved')
    path = d / 'm.npz'
    m.save(path)
    Vt, Qt = V[::7], Q[::7]
    np.savez(d / 'data.npz', V=Vt, Q=Qt, tau=m.predict(Vt), res=m.predict_residual(q=Qt, qd=Vt))
    return m, path, d


def test_a_fresh_interpreter_with_only_gp_loads_and_evaluates_it(saved):
    m, path, d = saved
    again = d / 'again.npz'
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get('PYTHONPATH', ''))
    p = subprocess.run([sys.executable, '-c', FRESH, str(path), str(d / 'data.npz'), str(again)],
                       capture_output=True, text=True, timeout=120, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    assert out['dynamics_loaded'] is False          # gp imported no other layer
    assert out['predict'] == 0.0 and out['kept'] == 'SavedCorrection'
    assert out['residual'] == 0.0                   # rebuilt through the entry point
    assert out['dynamics_after'] is True
    m2 = load_model(again)
    assert isinstance(m2.correction_, Correction)
    assert m2.correction_.to_dict() == m.correction_.to_dict()


def test_loaded_here_the_correction_is_rebuilt_by_its_owner(saved):
    m, path, d = saved
    data = np.load(d / 'data.npz')
    m2 = load_model(path)
    assert isinstance(m2.correction_, Correction) and isinstance(m2.correction_.basis,
                                                                 PotentialBasis)
    np.testing.assert_array_equal(m2.predict_residual(q=data['Q'], qd=data['V']), data['res'])


def test_records_without_a_kind_are_the_conservative_correction():
    rec = {'basis': None, 'theta': [], 'offsets': [1.0, 2.0]}      # as files wrote it before
    c = rebuild_correction(rec)
    assert isinstance(c, Correction)
    np.testing.assert_array_equal(c(None), [[1.0, 2.0]])
    assert c.to_dict()['kind'] == 'conservative'
    unknown = rebuild_correction({'kind': 'someone-elses', 'x': 1})
    assert isinstance(unknown, SavedCorrection)
    assert unknown.to_dict() == {'kind': 'someone-elses', 'x': 1}
    with pytest.raises(ValueError, match="'someone-elses' correction.*dgp_ros.corrections"):
        unknown(None)
