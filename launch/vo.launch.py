"""Launch ``vo_node`` (and, with ``rviz:=true``, RViz2 showing its outputs).

    ros2 launch epi_vo vo.launch.py
    ros2 launch epi_vo vo.launch.py namespace:=robot1 image_topic:=/front/image_raw \
        camera_info_topic:=/front/camera_info image_transport:=compressed use_sim_time:=true rviz:=true
    ros2 launch epi_vo vo.launch.py managed:=true   # then: ros2 lifecycle set /vo_node configure; ... activate

``managed:=true`` starts ``vo_lifecycle_node`` instead (same name, parameters and remappings, as a
launch_ros LifecycleNode so launch's lifecycle events apply): it starts unconfigured and does nothing
until a lifecycle manager or ``ros2 lifecycle set`` configures and activates it.

The node subscribes ``camera/image_raw`` (sensor_msgs/Image), ``camera/image_raw/compressed``
(sensor_msgs/CompressedImage) and ``camera/camera_info``, all relative to ``namespace``;
``image_topic`` / ``camera_info_topic`` remap them (the compressed topic follows image_transport's
convention, ``<image_topic>/compressed``). Parameters come from ``params_file``; ``image_transport`` and
``use_sim_time`` given here override the file. Outputs: ``vo/odometry``, ``vo/path``, ``vo/points``,
``vo/frame_status``, ``vo/debug_image`` (``publish_debug_image: true`` in the file), ``/diagnostics``, TF
odom -> base_link.
"""

# ruff takes `launch` for this repository's launch/ folder (first party); these are ROS 2's launch packages.
from launch import LaunchDescription  # noqa: I001
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import LifecycleNode, Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = "epi_vo"
BOOLEAN = ["true", "false"]

# The topics RViz2's config names (absolute, as RViz stores them), remapped into the launch namespace below.
RVIZ_TOPICS = ("vo/odometry", "vo/odometry/vo_units", "vo/path", "vo/points", "vo/debug_image")


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare(PACKAGE)
    namespace = LaunchConfiguration("namespace")
    params_file = LaunchConfiguration("params_file")
    image_topic = LaunchConfiguration("image_topic")
    camera_info_topic = LaunchConfiguration("camera_info_topic")
    image_transport = LaunchConfiguration("image_transport")
    use_sim_time = LaunchConfiguration("use_sim_time")
    log_level = LaunchConfiguration("log_level")
    rviz = LaunchConfiguration("rviz")
    rviz_config = LaunchConfiguration("rviz_config")
    rviz_fixed_frame = LaunchConfiguration("rviz_fixed_frame")
    managed = LaunchConfiguration("managed")

    arguments = [
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of vo_node (and of RViz2): its topics and service move under it"),
        DeclareLaunchArgument("params_file", default_value=PathJoinSubstitution([share, "config", "epi_vo.yaml"]),
                              description="ROS 2 parameter file for vo_node (`epi-vo params` writes the defaults)"),
        DeclareLaunchArgument("image_topic", default_value="camera/image_raw",
                              description="image topic to subscribe to (the compressed one: <image_topic>/compressed)"),
        DeclareLaunchArgument("camera_info_topic", default_value="camera/camera_info",
                              description="sensor_msgs/CameraInfo topic of that camera"),
        DeclareLaunchArgument("image_transport", default_value="auto", choices=["raw", "compressed", "auto"],
                              description="raw (Image), compressed (CompressedImage) or auto (both, the first to "
                                          "arrive is used); overrides the params file"),
        DeclareLaunchArgument("use_sim_time", default_value="false", choices=BOOLEAN,
                              description="use /clock (bag playback with --clock); overrides the params file"),
        DeclareLaunchArgument("log_level", default_value="info", choices=["debug", "info", "warn", "error", "fatal"],
                              description="log level of vo_node"),
        DeclareLaunchArgument("managed", default_value="false", choices=BOOLEAN,
                              description="start vo_lifecycle_node (a managed node: unconfigured until configured "
                                          "and activated through its lifecycle services) instead of vo_node"),
        DeclareLaunchArgument("rviz", default_value="false", choices=BOOLEAN,
                              description="also start RViz2 with the epi_vo display config"),
        DeclareLaunchArgument("rviz_config", default_value=PathJoinSubstitution([share, "config", "epi_vo.rviz"]),
                              description="RViz2 config file (used with rviz:=true)"),
        DeclareLaunchArgument("rviz_fixed_frame", default_value="odom",
                              description="RViz2's fixed frame: odom shows the outputs in metres; without metres "
                                          "(scale_source none, or not established yet) the path, points and "
                                          "vo/odometry/vo_units are in odom_vo_units, which no TF tree joins"),
    ]

    # The same node either way (name, parameters, remappings); managed:=true makes it a lifecycle node.
    vo_node_settings = {
        "package": PACKAGE,
        "name": "vo_node",
        "namespace": namespace,
        "output": "screen",
        "emulate_tty": True,
        "parameters": [
            params_file,
            {
                "image_transport": ParameterValue(image_transport, value_type=str),
                "use_sim_time": ParameterValue(use_sim_time, value_type=bool),
            },
        ],
        "remappings": [
            ("camera/image_raw", image_topic),
            ("camera/image_raw/compressed", [image_topic, "/compressed"]),
            ("camera/camera_info", camera_info_topic),
        ],
        "ros_arguments": ["--log-level", log_level],
    }
    vo_node = Node(executable="vo_node", condition=UnlessCondition(managed), **vo_node_settings)
    vo_lifecycle_node = LifecycleNode(executable="vo_lifecycle_node", condition=IfCondition(managed),
                                      **vo_node_settings)

    # RViz2 runs in the same namespace; its config names absolute /vo/... topics, remapped here to the
    # relative names, so they resolve to the namespace vo_node publishes in (/robot1/vo/odometry, ...).
    rviz_node = Node(
        package="rviz2",
        executable="rviz2",
        name="rviz2",
        namespace=namespace,
        output="screen",
        arguments=["-d", rviz_config, "-f", rviz_fixed_frame],
        parameters=[{"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
        remappings=[("/" + topic, topic) for topic in RVIZ_TOPICS],
        condition=IfCondition(rviz),
    )

    return LaunchDescription([*arguments, vo_node, vo_lifecycle_node, rviz_node])
