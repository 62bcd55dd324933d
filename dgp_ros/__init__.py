"""
dgp_ros: Dissipative Gaussian Processes for passive online damping identification.

BLAS threads: the dense problems here are small (n <= a few thousand) and the estimator shares the
machine with a simulator and DDS. A multi-threaded OpenBLAS then spins against the other processes
(measured on a loaded 2-core machine: a 200 x 200 Cholesky took 378 ms with 2 threads, 0.4 ms with
1). So one BLAS thread is the default when ``dgp_ros`` is imported before numpy; set
``OPENBLAS_NUM_THREADS`` (or ``OMP_NUM_THREADS``) yourself to override.
"""
import os as _os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    _os.environ.setdefault(_var, '1')

__version__ = '0.1.0'
