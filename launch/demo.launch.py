"""
Start sim_bridge and the D-GP estimator.

Full ROS 2 install: ``ros2 launch dgp_ros demo.launch.py``.

Arguments: model (full|diag|ard), passivity (none|paper|certified|projected), real_time_factor,
use_sim_time (the estimator then follows sim_bridge's /clock).
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
    sim_yaml = os.path.join(share, 'config', 'sim_bridge.yaml')
    use_sim_time = LaunchConfiguration('use_sim_time')
    sim_params = [sim_yaml] if os.path.exists(sim_yaml) else []
    return LaunchDescription([
        DeclareLaunchArgument('model', default_value='full'),
        DeclareLaunchArgument('passivity', default_value='projected'),
        DeclareLaunchArgument('real_time_factor', default_value='1.0'),
        DeclareLaunchArgument('use_sim_time', default_value='true'),
        Node(package='dgp_ros', executable='sim_bridge', name='sim_bridge', output='screen',
             parameters=sim_params + [{
                 'real_time_factor': ParameterValue(LaunchConfiguration('real_time_factor'),
                                                    value_type=float),
                 'publish_clock': True}]),
        Node(package='dgp_ros', executable='estimator', name='dgp_estimator', output='screen',
             parameters=[est_yaml, {
                 'model': LaunchConfiguration('model'),
                 'passivity': LaunchConfiguration('passivity'),
                 'prior': 'viscous', 'bias': False,      # the aircraft (defaults are for arms)
                 'use_sim_time': ParameterValue(use_sim_time, value_type=bool)}]),
    ])
