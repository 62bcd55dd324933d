"""
Start sim_bridge and the D-GP estimator with the node's defaults.

Full ROS 2 install: ``ros2 launch dgp_ros demo.launch.py``.

Arguments: model (full|diag|ard) and passivity (none|paper|certified|projected), each the
node's default unless given (config/estimator.yaml, generated from the parameter table: one
set of defaults for the aircraft and the arms), real_time_factor, use_sim_time (the estimator
then follows sim_bridge's /clock).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

#: estimator parameters the launch arguments may set; empty: the node's default
OVERRIDES = ('model', 'passivity')


def _estimator(context, est_yaml):
    params = {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                             value_type=bool)}
    for name in OVERRIDES:
        value = LaunchConfiguration(name).perform(context)
        if value:
            params[name] = value
    return [Node(package='dgp_ros', executable='estimator', name='dgp_estimator',
                 output='screen', parameters=[est_yaml, params])]


def generate_launch_description():
    share = get_package_share_directory('dgp_ros')
    est_yaml = os.path.join(share, 'config', 'estimator.yaml')
    sim_yaml = os.path.join(share, 'config', 'sim_bridge.yaml')
    sim_params = [sim_yaml] if os.path.exists(sim_yaml) else []
    return LaunchDescription([
        DeclareLaunchArgument('model', default_value='', description="empty: the node's"),
        DeclareLaunchArgument('passivity', default_value='', description="empty: the node's"),
        DeclareLaunchArgument('real_time_factor', default_value='1.0'),
        DeclareLaunchArgument('use_sim_time', default_value='true'),
        Node(package='dgp_ros', executable='sim_bridge', name='sim_bridge', output='screen',
             parameters=sim_params + [{
                 'real_time_factor': ParameterValue(LaunchConfiguration('real_time_factor'),
                                                    value_type=float),
                 'publish_clock': True}]),
        OpaqueFunction(function=_estimator, args=[est_yaml]),
    ])
