"""
rosbag2 tools in three layers.

- pure (``rosbags`` only, no rclpy, no DDS): :mod:`dgp_ros.bags.io` (open, read, write, message
  types and the check that guards their import) and :mod:`dgp_ros.bags.joint_states`
  (JointState streams). This package re-exports only these, so ``import dgp_ros.bags`` never
  loads rclpy.
- :mod:`dgp_ros.bags.ros`: the rclpy :class:`~dgp_ros.bags.ros.Recorder` and
  :class:`~dgp_ros.bags.ros.Player`.
- :mod:`dgp_ros.bags.cli`: the ``dgp-record`` and ``dgp-play`` commands.
"""
from dgp_ros.bags.io import (ALLOWED_PACKAGES, bag_summary, BagError, BagWriter,
                             check_message_type, installed_definition, iter_bag,
                             message_definition, normalize_type, open_bag, playable_topics,
                             storage_plugin, STORAGES, typestore)
from dgp_ros.bags.joint_states import (iter_joint_states, JOINT_STATE, joint_state_topic,
                                       write_joint_state_bag)

__all__ = ['ALLOWED_PACKAGES', 'JOINT_STATE', 'STORAGES', 'BagError', 'BagWriter', 'bag_summary',
           'check_message_type', 'installed_definition', 'iter_bag', 'iter_joint_states',
           'joint_state_topic', 'message_definition', 'normalize_type', 'open_bag',
           'playable_topics', 'storage_plugin', 'typestore', 'write_joint_state_bag']
