"""Session-wide test isolation.

DDS: every test session gets a random ROS_DOMAIN_ID and localhost-only discovery, set before any
rclpy context exists, so parallel sessions on one machine (or CI next to a developer) never see
each other's nodes. Child processes inherit the environment.
"""
import os
import random

os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
os.environ.setdefault('MPLBACKEND', 'Agg')
# one BLAS thread: see dgp_ros/__init__.py (oversubscribed OpenBLAS is 100x slower here)
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')
