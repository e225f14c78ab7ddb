"""``live`` node: the survey live in Foxglove, over the Foxglove SDK's WebSocket server.

Subscribes ``/survey/station`` (reliable), ``/diagnostics`` and ``/calibration/status`` and sends
the channels of :data:`liveview.CHANNELS` (the payloads are built by :mod:`liveview`, ROS-free):
the latest station as JSON (every field, NaN as null), the residual series and the station table
of the survey so far, the trajectory as a ``foxglove.SceneUpdate`` in ``survey_ned`` with its
frame (``foxglove.FrameTransforms``), diagnostics and calibration status as JSON, and the
stations' warnings as ``foxglove.Log``.  Open ``ws://HOST:PORT`` in Foxglove (Open connection →
Foxglove WebSocket) with ``config/foxglove_layout.json``.

Parameters: ``host`` (127.0.0.1: loopback only; 0.0.0.0 serves the rig network), ``port`` (0: a
free port the system picks; the URL is logged either way), ``max_stations`` kept for the series,
table and trajectory, ``message_backlog`` (messages buffered per client), ``republish_s`` (the
period the series, table, trajectory and frame are sent again, for clients that connected since).

A slow client never holds up the executor: ``Channel.log`` hands the message to the SDK, whose
server (its own threads, in Rust) queues it per client, at most ``message_backlog`` messages; when
a client's queue is full its oldest data message is dropped (and a client whose control queue
fills is disconnected).  The callbacks here only convert and hand over.
"""
from __future__ import annotations

import json
import math
import sys

import foxglove
from diagnostic_msgs.msg import DiagnosticArray
from foxglove.channels import FrameTransformsChannel, LogChannel, SceneUpdateChannel
from rclpy.node import Node

from ..io.surveystation import from_msg as station_dict
from ..rig import liveview as lv
from . import common as c
from inclinometer_calib.msg import CalibrationStatus, SurveyStation


def _fields_of(type_name: str) -> dict:
    """Fields of a nested ROS message type named as rclpy names it (``pkg/Name`` or ``pkg/msg/Name``)."""
    import importlib

    pkg, _, name = type_name.replace("/msg/", "/").partition("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name).get_fields_and_field_types()


def _json_channel(ctx, topic: str, schema: dict):
    data = json.dumps(schema).encode()
    return foxglove.Channel(topic, message_encoding="json", context=ctx,
                            schema=foxglove.Schema(name=lv.CHANNELS[topic], encoding="jsonschema", data=data))


def _series_schema() -> dict:
    number = {"type": "array", "items": {"type": ["number", "null"]}}
    integer = {"type": "array", "items": {"type": "integer"}}
    return {"type": "object", "title": lv.CHANNELS[lv.TOPIC_RESIDUALS],
            "properties": {"station_id": integer, "status": integer, "stamp_s": number, "measured_depth_m": number,
                           **{k: number for k in lv.SERIES}}}


def _table_schema() -> dict:
    return {"type": "object", "title": lv.CHANNELS[lv.TOPIC_TABLE],
            "properties": {"rows": {"type": "array", "items": {"type": "object"}}}}


class LiveNode(Node):
    def __init__(self, **kwargs):
        super().__init__("live", **kwargs)
        p = c.Params(self)
        self.host = p.declare("host", "127.0.0.1", "Address the Foxglove WebSocket server listens on (loopback by "
                              "default: give 0.0.0.0 to serve the rig network)", read_only=True)
        port = p.declare("port", 0, "Port of the Foxglove WebSocket server (0: a free port chosen by the system; "
                         "the URL is logged)", read_only=True, range=(0, 65535))
        max_stations = p.declare("max_stations", 2000, "Stations kept for the residual series, the table and the "
                                 "trajectory (the oldest dropped)", read_only=True, range=(1, 1_000_000))
        backlog = p.declare("message_backlog", 1024, "Messages buffered per client; beyond it the oldest is "
                            "dropped (a slow client never holds up the node)", read_only=True, range=(16, 1_000_000))
        republish = p.declare("republish_s", 2.0, "Period the series, table, trajectory and frame are sent again "
                              "(for clients that connected since), s", read_only=True, range=(0.1, 3600.0))
        self.view = lv.LiveView(max_stations)
        self.ctx = foxglove.Context()                     # this node's channels only, not the SDK's global ones
        self.ch_station = _json_channel(self.ctx, lv.TOPIC_STATION, lv.json_schema(
            lv.station_fields(SurveyStation.get_fields_and_field_types()), _fields_of,
            title=lv.CHANNELS[lv.TOPIC_STATION]))
        self.ch_residuals = _json_channel(self.ctx, lv.TOPIC_RESIDUALS, _series_schema())
        self.ch_table = _json_channel(self.ctx, lv.TOPIC_TABLE, _table_schema())
        self.ch_diagnostics = _json_channel(self.ctx, lv.TOPIC_DIAGNOSTICS, lv.json_schema(
            DiagnosticArray.get_fields_and_field_types(), _fields_of, title=lv.CHANNELS[lv.TOPIC_DIAGNOSTICS]))
        self.ch_status = _json_channel(self.ctx, lv.TOPIC_CALIBRATION_STATUS, lv.json_schema(
            CalibrationStatus.get_fields_and_field_types(), _fields_of,
            title=lv.CHANNELS[lv.TOPIC_CALIBRATION_STATUS]))
        self.ch_scene = SceneUpdateChannel(lv.TOPIC_TRAJECTORY, context=self.ctx)
        self.ch_frames = FrameTransformsChannel(lv.TOPIC_FRAMES, context=self.ctx)
        self.ch_log = LogChannel(lv.TOPIC_LOG, context=self.ctx)
        self.server = foxglove.start_server(name="inclinometer_calib live", host=self.host, port=port,
                                            context=self.ctx, message_backlog_size=backlog)
        self.url = f"ws://{self.host}:{self.server.port}"
        self._last_stamp = math.nan
        self.create_subscription(SurveyStation, c.TOPIC_STATION, self._on_station, c.reliable_qos(100))
        self.create_subscription(DiagnosticArray, c.TOPIC_DIAGNOSTICS, self._on_diagnostics, c.reliable_qos(10))
        self.create_subscription(CalibrationStatus, c.TOPIC_STATUS, self._on_status, c.reliable_qos(10))
        self.timer = c.steady_timer(self, republish, self._send_survey)
        self.get_logger().info(f"Foxglove live view on {self.url} (open it in Foxglove: Open connection -> "
                               "Foxglove WebSocket; layout config/foxglove_layout.json)")

    def _on_station(self, msg):
        s = station_dict(msg)
        self.view.add(s)
        self._last_stamp = t = s["stamp"]
        self.ch_station.log(lv.jsonable(s))
        for level, text in lv.log_entries(s):
            self.ch_log.log(lv.log_message(level, text, t))
        self._send_survey()

    def _send_survey(self):
        """The survey so far: residual series, table, trajectory and its frame (also on the timer)."""
        t = self._last_stamp
        self.ch_frames.log(lv.frame_transforms(t))
        if not self.view.stations:
            return
        self.ch_residuals.log(lv.jsonable(self.view.residuals()))
        self.ch_table.log(lv.jsonable(self.view.table()))
        self.ch_scene.log(lv.scene_update(self.view.trajectory(), t))

    def _on_diagnostics(self, msg):
        self.ch_diagnostics.log(lv.jsonable(lv.message_dict(msg)))

    def _on_status(self, msg):
        self.ch_status.log(lv.jsonable(lv.message_dict(msg)))

    def destroy_node(self):
        server = getattr(self, "server", None)
        if server is not None:
            server.stop()
        super().destroy_node()


def main(args=None):
    return c.run(LiveNode, args)


if __name__ == "__main__":
    sys.exit(main())
