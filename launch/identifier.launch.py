"""
Launch one identifier: ``ros2 launch bcid_ros identifier.launch.py``.

The launch arguments are

- ``params_file``: the parameter file (default: the installed
  ``config/ding_miso.yaml``; the identifier's parameters sit under ``/**:``,
  so the file applies under any namespace);
- ``namespace``: the robot's namespace (default: none), e.g. ``robot1``: the
  node is then ``/robot1/bcid_identifier``, reads ``/robot1/samples`` and
  publishes ``/robot1/bcid_identifier/parameters``;
- ``managed``: ``true`` starts ``identifier_lifecycle_node`` instead (it waits
  for configure and activate).

Example: ``ros2 launch bcid_ros identifier.launch.py namespace:=robot1
params_file:=/path/to/arm.yaml``.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node


def generate_launch_description():
    """Return the launch description: the arguments and one identifier."""
    share = get_package_share_directory('bcid_ros')
    params_file = LaunchConfiguration('params_file')
    namespace = LaunchConfiguration('namespace')
    managed = LaunchConfiguration('managed')
    return LaunchDescription([
        DeclareLaunchArgument(
            'params_file', default_value=os.path.join(share, 'config', 'ding_miso.yaml'),
            description='parameter file (the identifier under /**:)'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the identifier and its topics'),
        DeclareLaunchArgument('managed', default_value='false',
                              description='true: the lifecycle form, identifier_lifecycle_node'),
        Node(package='bcid_ros', executable='identifier_node', name='bcid_identifier',
             namespace=namespace, parameters=[params_file], output='screen',
             condition=UnlessCondition(managed)),
        LifecycleNode(package='bcid_ros', executable='identifier_lifecycle_node',
                      name='bcid_identifier', namespace=namespace, parameters=[params_file],
                      output='screen', condition=IfCondition(managed)),
    ])
