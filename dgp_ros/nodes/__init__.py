"""
The ROS processes of the package: every module here runs an rclpy node (docs/ARCHITECTURE.md).

- ``estimator``: the ``dgp_estimator`` node (console script ``estimator``), a thin wrapper
  around :class:`dgp_ros.online.OnlineEstimator`;
- ``arm_sim``: the ``arm_sim`` node (``dgp-arm-sim``), a simulated arm's raw ``/joint_states``;
- ``runtime``: what every node process shares (``--help``, parameters, a clean exit);
- ``executor``: the wait-set executor the nodes spin by default.

Nothing is imported here: importing a node module imports rclpy, importing the package does not.
"""
