# SPDX-License-Identifier: Apache-2.0
"""Launch the ground segmentation node, plain or managed (lifecycle), and optionally RViz.

    ros2 launch gp_ground_segmentation ground_segmentation.launch.py points:=/velodyne_points
    ros2 launch gp_ground_segmentation ground_segmentation.launch.py \
        points:=/ouster/points namespace:=seg use_sim_time:=true rviz:=true
    ros2 launch gp_ground_segmentation ground_segmentation.launch.py lifecycle:=true \
        autostart:=false   # a managed node, left unconfigured for Nav2's lifecycle manager

Arguments: points (input PointCloud2 topic), params_file (default: the installed
config/params.yaml), namespace, use_sim_time, lifecycle (true: the managed node
ground_segmentation_lifecycle_node instead of ground_segmentation_node), autostart (with
lifecycle:=true: configure it, then activate it once inactive; false leaves it unconfigured),
rviz and rviz_config. The outputs are 'ground', 'obstacles', 'labeled' and 'ground_surface' in
the node's namespace (/ground, /obstacles, ... without one).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.conditions import IfCondition, UnlessCondition
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import LifecycleNode, Node
from launch_ros.descriptions import ParameterValue
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from launch_ros.substitutions import FindPackageShare
from lifecycle_msgs.msg import Transition

PACKAGE = 'gp_ground_segmentation'
NODE_NAME = 'ground_segmentation'


def _arguments(share):
    return [
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
        DeclareLaunchArgument('lifecycle', default_value='false',
                              description='true: start the managed (lifecycle) node'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='with lifecycle:=true: configure and activate it '
                              '(false: leave it unconfigured for a lifecycle manager)'),
        DeclareLaunchArgument('rviz', default_value='false', description='also start RViz'),
        DeclareLaunchArgument('rviz_config',
                              default_value=PathJoinSubstitution([share, 'config',
                                                                  'ground_segmentation.rviz']),
                              description='RViz configuration file'),
    ]


def _transition(node, transition_id, **kwargs):
    """The event that asks the lifecycle ``node`` for a transition."""
    return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(node),
                                       transition_id=transition_id), **kwargs)


def generate_launch_description():
    share = FindPackageShare(PACKAGE)
    lifecycle = LaunchConfiguration('lifecycle')
    sim_time = {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                               value_type=bool)}
    common = dict(package=PACKAGE, name=NODE_NAME, namespace=LaunchConfiguration('namespace'),
                  output='screen', parameters=[LaunchConfiguration('params_file'), sim_time],
                  remappings=[('points', LaunchConfiguration('points'))])
    node = Node(executable='ground_segmentation_node', condition=UnlessCondition(lifecycle),
                **common)
    managed = LifecycleNode(executable='ground_segmentation_lifecycle_node',
                            condition=IfCondition(lifecycle), **common)
    autostart = IfCondition(PythonExpression([
        "'", lifecycle, "'.lower() == 'true' and '", LaunchConfiguration('autostart'),
        "'.lower() == 'true'"]))
    configure = _transition(managed, Transition.TRANSITION_CONFIGURE, condition=autostart)
    # activate at the end of a configure (not after a deactivate, which also ends inactive)
    activate = RegisterEventHandler(OnStateTransition(
        target_lifecycle_node=managed, start_state='configuring', goal_state='inactive',
        entities=[_transition(managed, Transition.TRANSITION_ACTIVATE)]), condition=autostart)
    rviz = Node(
        package='rviz2', executable='rviz2', output='screen',
        arguments=['-d', LaunchConfiguration('rviz_config')], parameters=[sim_time],
        condition=IfCondition(LaunchConfiguration('rviz')))
    return LaunchDescription(_arguments(share) + [node, managed, activate, configure, rviz])
