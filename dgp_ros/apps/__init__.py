"""
The console tools of the package and their reports (docs/ARCHITECTURE.md).

- ``demo`` (``dgp-demo``) and ``robot_demo`` (``dgp-demo --robot``): start the nodes as child
  processes over real DDS, listen, and report (``robot_report``: the robot demo's scoring);
- ``replay`` (``dgp-replay``) and ``replay_report``: a bag through the online estimator,
  offline, and the files it writes;
- ``children``: starting, isolating and stopping the demos' child processes.

The nodes these tools start live in :mod:`dgp_ros.nodes`; nothing is imported here.
"""
