"""
Launch the adaptive loop: ``ros2 launch bcid_ros adaptive_loop.launch.py``.

The plant (``simulator_node`` in plant mode), the identifier (``cl_bcls``)
and the adaptive controller, all three from the installed
``config/adaptive_loop.yaml``, in one namespace (argument ``namespace``,
default none): the file names the identifier and the controller topic
relatively, so the loop closes inside the namespace. ``bcid demo --scenario
adaptive_loop`` runs the same three nodes with live output and a figure.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    """Return the launch description: the argument and the three nodes."""
    params_file = os.path.join(get_package_share_directory('bcid_ros'), 'config',
                               'adaptive_loop.yaml')
    namespace = LaunchConfiguration('namespace')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the loop\'s three nodes'),
        Node(package='bcid_ros', executable='simulator_node', name='bcid_simulator',
             namespace=namespace, parameters=[params_file], output='screen'),
        Node(package='bcid_ros', executable='identifier_node', name='bcid_identifier',
             namespace=namespace, parameters=[params_file], output='screen'),
        Node(package='bcid_ros', executable='adaptive_controller_node', name='bcid_controller',
             namespace=namespace, parameters=[params_file], output='screen'),
    ])
