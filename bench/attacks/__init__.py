"""
The attack surfaces of ``bench/hostile.py``, one module each.

``messages`` (class 1: messages through ``OnlineEstimator.process``), ``params`` (class 2:
parameter sets), ``files`` (class 3: model files), ``bags`` (class 4: bags naming types that
are not allowed) and, live over DDS, the ``estimator`` node process (``node``: the process and a
client of it; ``live``: what is thrown at it). ``base`` is what they share (the sandbox, the
good stream, the tally of one class), ``report`` the section they fill.
"""
