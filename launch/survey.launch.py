"""Calibration + survey graph for a real ROS 2 install (``ros2 launch inclinometer_calib survey.launch.py``).

Equivalent of ``inclinometer-calib-launch`` (inclinometer_calib/apps/launcher.py, used where ``launch``
and ``launch_ros`` are not available, e.g. PyPI wheels): probe, calibration, correction and recorder
with the package's config/<node>.yaml, the run's outputs in ``out``, and the whole launch shut down
when the probe finishes.  The probe publishes ``/clock`` (its log time); calibration and correction
run on it (``use_sim_time``).  Unlike the launcher, nothing here restarts a node that dies, reserves
a ROS_DOMAIN_ID, or turns failures into an exit status.  The launcher additionally prints the summary; here run
``python -c "from inclinometer_calib.apps.launcher import summarize_run; summarize_run('<out>')"``.

Arguments: out (output directory), source (simulate|csv|mcap), input (file for csv/mcap),
speed, survey (stand_grid|well_path|none), seed, record (true|false).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler, TimerAction
from launch.conditions import IfCondition
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory("inclinometer_calib"), "config")
    out = LaunchConfiguration("out")
    record = LaunchConfiguration("record")
    consumers = PythonExpression(["3 if '", record, "'.lower() == 'true' else 2"])
    reference_readers = PythonExpression(["2 if '", record, "'.lower() == 'true' else 1"])
    station_readers = PythonExpression(["'/survey/station=1' if '", record, "'.lower() == 'true' else '/survey/station=0'"])

    probe = Node(
        package="inclinometer_calib", executable="probe", name="probe", output="screen",
        parameters=[os.path.join(config, "probe.yaml"), {
            "source": LaunchConfiguration("source"),
            "path": LaunchConfiguration("input"),
            "speed": LaunchConfiguration("speed"),
            "survey": LaunchConfiguration("survey"),
            "seed": LaunchConfiguration("seed"),
            "on_end": "stop",
            "wait_for_subscribers": consumers,
            "wait_for_reference_subscribers": reference_readers,
            # the recorder, before the first station (=0: nothing to wait for without one)
            "wait_for_topic_subscribers": [station_readers],
            "truth_file": PathJoinSubstitution([out, "truth.json"]),
        }],
    )
    calibration = Node(
        package="inclinometer_calib", executable="calibration", name="calibration", output="screen",
        parameters=[os.path.join(config, "calibration.yaml"),
                    {"output": PathJoinSubstitution([out, "coeffs.yaml"]), "use_sim_time": True,
                     "model.effects": LaunchConfiguration("model_effects")}],
    )
    correction = Node(
        package="inclinometer_calib", executable="correction", name="correction", output="screen",
        parameters=[os.path.join(config, "correction.yaml"), {
            "use_sim_time": True,  # the probe's /clock (stamp:=log): one time base for all stamps
            "fallback_coeffs_file": PathJoinSubstitution([out, "coeffs.yaml"]),
            "state_file": PathJoinSubstitution([out, "correction_state.json"]),
        }],
    )
    recorder = Node(
        package="inclinometer_calib", executable="recorder", name="recorder", output="screen",
        parameters=[{"output": PathJoinSubstitution([out, "survey.mcap"])}],
        condition=IfCondition(record),
    )
    return LaunchDescription([
        DeclareLaunchArgument("out", default_value="run", description="output directory (must exist)"),
        DeclareLaunchArgument("source", default_value="simulate", description="simulate | csv | mcap"),
        DeclareLaunchArgument("input", default_value="", description="input file for csv / mcap"),
        DeclareLaunchArgument("speed", default_value="1.0", description="playback speed factor"),
        DeclareLaunchArgument("survey", default_value="well_path", description="stand_grid | well_path | none"),
        DeclareLaunchArgument("seed", default_value="7", description="simulator seed"),
        DeclareLaunchArgument("record", default_value="true", description="record survey.mcap"),
        DeclareLaunchArgument("model_effects", default_value="",
                              description="effects the calibration node fits beyond the paper's model, "
                                          "e.g. temperature_bias:mag"),
        calibration, correction, recorder, probe,
        # the probe ends the run (on_end:=stop); give the others time to close the last station
        RegisterEventHandler(OnProcessExit(
            target_action=probe,
            on_exit=[TimerAction(period=3.0, actions=[EmitEvent(event=Shutdown(reason="probe finished"))])],
        )),
    ])
