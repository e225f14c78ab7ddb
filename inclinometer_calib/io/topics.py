"""The graph's topic names and message types — one place, ROS-free (the nodes, the launcher,
offline reprocessing and the tests agree on them)."""

TOPIC_IMU = "/probe/imu"
TOPIC_MAG = "/probe/mag"
TOPIC_TEMPERATURE = "/probe/temperature"
TOPIC_REFERENCE = "/probe/reference"
TOPIC_DEPTH = "/probe/depth"
TOPIC_SERIAL = "/probe/serial"  # the probe's serial number, latched (transient local), once per run
TOPIC_IMU_CORRECTED = "/probe/imu_corrected"
TOPIC_MAG_CORRECTED = "/probe/mag_corrected"
TOPIC_COEFFICIENTS = "/calibration/coefficients"
TOPIC_STATUS = "/calibration/status"
TOPIC_STATION = "/survey/station"
TOPIC_DIAGNOSTICS = "/diagnostics"
TOPIC_CLOCK = "/clock"  # the probe's log time (stamp:=log); the other nodes run on it (use_sim_time)
#: Each node's place in the sample stream (StreamProgress, transient local): the replay's flow
#: control and the run's accounting.
TOPIC_PROGRESS = "/graph/progress"

IMU_TYPE = "sensor_msgs/msg/Imu"
MAG_TYPE = "sensor_msgs/msg/MagneticField"
TEMPERATURE_TYPE = "sensor_msgs/msg/Temperature"
REFERENCE_TYPE = "geometry_msgs/msg/Vector3Stamped"
#: The probe's measured depth, m (no header: it holds from when it arrives, in the order of the
#: samples around it; published where it changes, before the samples at the new depth).
DEPTH_TYPE = "std_msgs/msg/Float64"
#: The probe's serial number (its identity in the fleet registry and in every record and station).
SERIAL_TYPE = "std_msgs/msg/String"
STATION_TYPE = "inclinometer_calib/msg/SurveyStation"
COEFFICIENTS_TYPE = "inclinometer_calib/msg/CalibrationCoefficients"
PROGRESS_TYPE = "inclinometer_calib/msg/StreamProgress"

#: What the probe publishes: the inputs of the calibration and correction (and of a replay).
PROBE_TOPICS = {TOPIC_IMU: IMU_TYPE, TOPIC_MAG: MAG_TYPE, TOPIC_TEMPERATURE: TEMPERATURE_TYPE,
                TOPIC_REFERENCE: REFERENCE_TYPE, TOPIC_DEPTH: DEPTH_TYPE, TOPIC_SERIAL: SERIAL_TYPE}
#: What the rest of a live graph publishes (a recorded run holds them): a replay or a
#: reprocessing makes them anew, so meeting them in a bag is expected, not a problem.
GRAPH_OUTPUTS = {TOPIC_COEFFICIENTS, TOPIC_STATUS, TOPIC_STATION, TOPIC_DIAGNOSTICS, TOPIC_CLOCK, TOPIC_PROGRESS,
                 TOPIC_IMU_CORRECTED, TOPIC_MAG_CORRECTED, "/rosout", "/parameter_events"}
