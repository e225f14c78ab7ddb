"""The graph's topic names and message types — one place, ROS-free (the nodes, the launcher,
offline reprocessing and the tests agree on them)."""
import math


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


def station_dict(msg) -> dict:
    """A ``SurveyStation`` message as a plain dict (Python numbers, lists): one conversion for a
    bag's messages (``rosbags``, :func:`read_bag`) and live ones (``rclpy``, the wits and live
    nodes).  A station recorded before the stations had one north (no ``azimuth_true_deg``) is put
    along its positions' north (:func:`_one_north`)."""
    d = {k: getattr(msg, k) for k in (
        "station_id", "drift_deg", "azimuth_deg", "toolface_deg", "gravity_toolface_deg",
        "magnetic_toolface_deg",
        "total_gravity_mps2", "total_field_nt", "dip_deg", "delta_g_mps2", "delta_b_nt",
        "delta_dip_deg", "status", "azimuth_undefined", "interference_suspected",
        "coefficients_id", "reference_drift_deg", "reference_azimuth_deg",
        "reference_toolface_deg", "samples_averaged", "duration_s", "temperature_c",
        "moved_during_capture", "model_misfit", "model_diagnosis")}
    # depth and trajectory (NaN in a bag recorded before they existed)
    for k in ("measured_depth_m", "tvd_m", "north_m", "east_m", "dls_deg_per_30m",
              "azimuth_magnetic_deg", "azimuth_grid_deg", "azimuth_true_deg", "axial_field_nt"):
        d[k] = getattr(msg, k, float("nan"))
    # the azimuth's north and method ("" in a bag recorded before they existed)
    for k in ("azimuth_reference", "azimuth_method", "probe_serial", "uncorrected_reason"):
        d[k] = getattr(msg, k, "")
    # the rest of the message, so that the dict has every field (the live view shows them all)
    for k, default in (("toolface_type", ""), ("azimuth_sigma_deg", float("nan")), ("axial_degenerate", False),
                       ("is_static", True), ("gravity_out_of_tolerance", False)):
        d[k] = getattr(msg, k, default)
    # raw means and the position's covariance (NaN in a bag recorded before they existed)
    for k, n in (("raw_gravity_mps2", 3), ("raw_field_nt", 3), ("position_covariance_ned_m2", 9)):
        d[k] = [float(x) for x in getattr(msg, k, [float("nan")] * n)]
    d["warnings"] = list(msg.warnings)
    d["stamp"] = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    d = {k: (v.item() if hasattr(v, "item") else v) for k, v in d.items()}
    if not hasattr(msg, "azimuth_true_deg"):
        _one_north(d)
    return d


def _one_north(d: dict) -> None:
    """A station dict of a bag recorded before the stations had one north, put along it (in place).
    Then ``azimuth_deg`` and ``reference_azimuth_deg`` were true (``azimuth_reference`` "true", or
    empty in older bags) while ``north_m``/``east_m`` were along grid north when the site had a grid
    (``azimuth_grid_deg`` finite): such a station becomes a grid one (its true azimuth in
    ``azimuth_true_deg``, its reference azimuth minus the convergence) — what its positions are."""
    grid, az = d["azimuth_grid_deg"], d["azimuth_deg"]
    if not (math.isfinite(grid) and math.isfinite(az)):
        if d["azimuth_reference"] == "true":
            d["azimuth_true_deg"] = az
        return
    d["azimuth_true_deg"] = az
    convergence = az - grid
    d["azimuth_deg"], d["azimuth_reference"] = grid, "grid"
    if math.isfinite(d["reference_azimuth_deg"]):
        d["reference_azimuth_deg"] = (d["reference_azimuth_deg"] - convergence) % 360.0
