"""
Launch the demo pair, simulator and identifier: ``ros2 launch bcid_ros demo.launch.py``.

Arguments: ``scenario`` (a file of the installed ``config/``, default
``ding_miso``) and ``namespace`` (default: none). The simulator publishes
the scenario's samples and its truth; the identifier estimates from them.
``bcid demo`` runs the same two nodes with live output and a figure.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def nodes(context):
    """Return the simulator and the identifier, both configured by the scenario's file."""
    share = get_package_share_directory('bcid_ros')
    scenario = LaunchConfiguration('scenario').perform(context)
    params_file = os.path.join(share, 'config', f'{scenario}.yaml')
    namespace = LaunchConfiguration('namespace')
    return [
        Node(package='bcid_ros', executable='simulator_node', name='bcid_simulator',
             namespace=namespace, parameters=[params_file], output='screen'),
        Node(package='bcid_ros', executable='identifier_node', name='bcid_identifier',
             namespace=namespace, parameters=[params_file], output='screen'),
    ]


def generate_launch_description():
    """Return the launch description: the arguments and the two nodes."""
    return LaunchDescription([
        DeclareLaunchArgument('scenario', default_value='ding_miso',
                              description='config/<scenario>.yaml: ding_miso, '
                              'ding_miso_nonstationary, ikenoue_colored, ikenoue_white_input, '
                              'ikeda_closed_loop or joints'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of both nodes and their topics'),
        OpaqueFunction(function=nodes),
    ])
