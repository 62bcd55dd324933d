"""
Start the D-GP estimator for a robot that already runs robot_state_publisher.

Full ROS 2 install: ``ros2 launch dgp_ros robot.launch.py [joint_states:=/joint_states]
[model_path:=$HOME/.ros/friction.npz] [learning:=false]``: ``learning:=false`` with a
``model_path`` serves that model frozen (commission, then deploy: the README).

The estimator subscribes to the robot's joint states (raw ``sensor_msgs/JointState`` with
position, velocity and measured effort), takes the URDF from ``/robot_description`` (transient
local, as ros2_control's controller manager does) and subtracts the rigid-body torque with
pinocchio before learning the friction, on the URDF's movable joints (to select fewer, or another
order, set the ``joints`` parameter in a copy of ``config/estimator.yaml``). Every other parameter
keeps the defaults of ``config/estimator.yaml``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description():
    share = get_package_share_directory('dgp_ros')
    est_yaml = os.path.join(share, 'config', 'estimator.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('joint_states', default_value='/joint_states',
                              description="the robot driver's JointState topic"),
        DeclareLaunchArgument('model_path', default_value='',
                              description='model file (.npz): loaded at start, saved on exit'),
        DeclareLaunchArgument('learning', default_value='true',
                              description='false: serve only the model of model_path'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
        Node(package='dgp_ros', executable='estimator', name='dgp_estimator', output='screen',
             remappings=[('generalized_state', LaunchConfiguration('joint_states'))],
             parameters=[est_yaml, {
                 'inverse_dynamics': 'urdf',         # the URDF comes from /robot_description
                 'model_path': LaunchConfiguration('model_path'),
                 'learning': ParameterValue(LaunchConfiguration('learning'), value_type=bool),
                 'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                                value_type=bool)}]),
    ])
