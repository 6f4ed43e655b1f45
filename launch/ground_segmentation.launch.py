# SPDX-License-Identifier: Apache-2.0
"""Launch the ground segmentation node (and optionally RViz).

    ros2 launch gp_ground_segmentation ground_segmentation.launch.py points:=/velodyne_points
    ros2 launch gp_ground_segmentation ground_segmentation.launch.py \
        points:=/ouster/points namespace:=seg use_sim_time:=true rviz:=true

Arguments: points (input PointCloud2 topic), params_file (default: the installed
config/params.yaml), namespace, use_sim_time, rviz and rviz_config. The outputs are 'ground' and
'obstacles' in the node's namespace (/ground, /obstacles without one).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'gp_ground_segmentation'


def generate_launch_description():
    share = FindPackageShare(PACKAGE)
    arguments = [
        DeclareLaunchArgument('points', default_value='/velodyne_points',
                              description='input sensor_msgs/PointCloud2 topic, in the sensor '
                              'frame (or set the sensor_* pose parameters)'),
        DeclareLaunchArgument('params_file',
                              default_value=PathJoinSubstitution([share, 'config',
                                                                  'params.yaml']),
                              description='ROS 2 parameter file of the node'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its output topics'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='use /clock (e.g. from gp-ground-seg play --clock)'),
        DeclareLaunchArgument('rviz', default_value='false', description='also start RViz'),
        DeclareLaunchArgument('rviz_config',
                              default_value=PathJoinSubstitution([share, 'config',
                                                                  'ground_segmentation.rviz']),
                              description='RViz configuration file'),
    ]
    node = Node(
        package=PACKAGE, executable='ground_segmentation_node', name='ground_segmentation',
        namespace=LaunchConfiguration('namespace'), output='screen',
        parameters=[LaunchConfiguration('params_file'),
                    {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                                    value_type=bool)}],
        remappings=[('points', LaunchConfiguration('points'))])
    rviz = Node(
        package='rviz2', executable='rviz2', output='screen',
        arguments=['-d', LaunchConfiguration('rviz_config')],
        parameters=[{'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                                    value_type=bool)}],
        condition=IfCondition(LaunchConfiguration('rviz')))
    return LaunchDescription(arguments + [node, rviz])
