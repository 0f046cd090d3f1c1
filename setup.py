"""
ament_python setup for bcid_ros.

On a ROS 2 system rclpy and the message packages come from apt (see
package.xml), so ``install_requires`` names only the numerical libraries.
The pip path pins the PyPI ROS wheels in ``requirements.txt`` instead.
"""

from glob import glob

from setuptools import find_packages, setup

package_name = 'bcid_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'benchmarks']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools', 'numpy', 'scipy'],
    extras_require={
        'bags': ['mcap', 'mcap-ros2-support', 'rosbags'],
        'plots': ['matplotlib'],
    },
    zip_safe=True,
    maintainer='bcid_ros maintainers',
    maintainer_email='bcid@example.com',
    description='Online bias-compensated system identification for ROS 2.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'identifier_node = bcid_ros.entry_points:identifier_node',
            'identifier_lifecycle_node = bcid_ros.entry_points:identifier_lifecycle_node',
            'simulator_node = bcid_ros.entry_points:simulator_node',
            'adaptive_controller_node = bcid_ros.entry_points:adaptive_controller_node',
            'bcid = bcid_ros.entry_points:bcid',
        ],
    },
)
