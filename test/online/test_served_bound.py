"""
The served model holds a bounded number of samples however late its rebases come (``Served``).

Samples are appended to the served model between rebases; past ``rebase_after`` appends (the
window's size) the rest wait for the rebase (``blocked``), so a learner whose rebases fall
behind or fail for hours holds at most twice its window in the served model.
"""
import numpy as np

from dgp_ros.online.learner.health import LearnerHealth
from dgp_ros.online.learner.served import Served


class _Model:
    def __init__(self):
        self.n = 0

    def update(self, Q, T):
        self.n += len(Q)


class _Window:
    def __init__(self):
        self.seq = 0

    def learn(self, k):
        self.seq += k

    def run_of(self, lo, hi, gen):
        assert gen == 0 and hi == self.seq
        return np.zeros((hi - lo, 2)), np.zeros((hi - lo, 2))


def test_appends_stop_at_the_window_and_the_rebase_takes_the_rest():
    served, win, model, h = Served(), _Window(), _Model(), LearnerHealth()
    served.based(model, 0, 0)
    for _ in range(100):                        # rebases that never come
        win.learn(7)
        served.catch_up(win, h, rebase_after=200)
    assert served.appended <= 200 and model.n == served.appended and served.blocked
    assert served.unheld(win.seq) == 700 - served.appended
    served.based(_Model(), win.seq, 0)          # the rebase took them all
    win.learn(3)
    assert served.catch_up(win, h, rebase_after=200) == 3 and not served.blocked
