"""
``sensor_msgs/JointState`` in and out, without rclpy: the room the nodes, bags and tools share.

* :mod:`.sample`: the one converter of a message object (rclpy's or rosbags') into a
  :class:`JointStateSample` (``joint_state_sample``), so a message gives the same numbers
  whichever path it took;
* :mod:`.cdr`: the codec of its serialized bytes (``JointStateReader`` decodes a batch into
  arrays, ``JointStateWriter`` encodes answers), checked against rclpy's serialization.
"""
from .sample import joint_state_sample, JointStateSample, stamp_seconds

__all__ = ['JointStateSample', 'joint_state_sample', 'stamp_seconds']
