"""``wits`` node: the corrected survey stations out as WITS level 0 record 07 (:mod:`wits`).

Subscribes ``/survey/station`` (reliable) and sends every corrected station (one with a
``coefficients_id``; a station whose status is error — the probe moved — is not sent, and said)
as one record 07 to:

* a TCP server (``port``, ``host``: loopback by default; 0 disables): any number of clients, each
  with its own buffer; a client that stalls (more than ``max_buffer_bytes`` waiting) or goes away
  is dropped and said, the graph and the other clients never wait for it;
* a file or serial-like device (``output``, appended, flushed per record; empty: none).

Record items: well ``well_id``, hole section ``hole_section``, a sequence number per record, date
and time of the station's stamp (UTC), MD, TVD, inclination, magnetic and corrected azimuth,
magnetic and gravity toolface, north/east, dogleg severity (``wits.NUMERIC_ITEMS``).
"""
from __future__ import annotations

import datetime as dt
import sys

from rclpy.node import Node

from ..wits import WitsServer, encode
from . import common as c
from inclinometer_calib.msg import SurveyStation

FIELDS = ("measured_depth_m", "tvd_m", "drift_deg", "azimuth_magnetic_deg", "azimuth_deg", "magnetic_toolface_deg",
          "gravity_toolface_deg", "north_m", "east_m", "dls_deg_per_30m")


class WitsNode(Node):
    def __init__(self, **kwargs):
        super().__init__("wits", **kwargs)
        p = c.Params(self)
        self.port = p.declare("port", 0, "TCP port of the WITS0 server (0: no server)", read_only=True,
                              range=(0, 65535))
        self.host = p.declare("host", "127.0.0.1", "Address the server listens on (loopback by default: give "
                              "0.0.0.0 to serve the rig network)", read_only=True)
        self.output = p.declare("output", "", "File or serial-like device the records are appended to "
                                "(empty: none)", read_only=True)
        self.well_id = p.declare("well_id", "WELL", "Well identifier (item 0701)", read_only=True)
        self.hole_section = p.declare("hole_section", 0, "Sidetrack / hole section number (item 0702)",
                                      read_only=True, range=(0, 99))
        max_buffer = p.declare("max_buffer_bytes", 1 << 20, "A client with more than this waiting is "
                               "dropped as stalled", read_only=True, range=(1024, 1 << 30))
        if not self.port and not self.output:
            raise ValueError("give a TCP port and/or an output file: nothing to send the records to")
        self.server = WitsServer(self.host, self.port, max_buffer=max_buffer, say=self.get_logger().info) \
            if self.port else None
        self.sink = open(self.output, "ab") if self.output else None   # noqa: SIM115 (closed in destroy_node)
        self.sequence = 0
        self.create_subscription(SurveyStation, c.TOPIC_STATION, self._on_station, c.reliable_qos(100))
        self.get_logger().info("WITS0 record 07 of the survey stations"
                               + (f" on tcp://{self.host}:{self.server.port}" if self.server else "")
                               + (f" to {self.output}" if self.output else ""))

    def _on_station(self, msg):
        if not msg.coefficients_id:
            return                                   # raw: before any calibration
        if msg.status == 2:
            self.get_logger().warning(f"station {msg.station_id}: status error (probe moved or gravity out of "
                                      "tolerance): not sent as a survey")
            return
        self.sequence += 1
        when = dt.datetime.fromtimestamp(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, dt.timezone.utc)
        record = encode({k: getattr(msg, k) for k in FIELDS}, self.sequence, self.well_id, self.hole_section, when)
        if self.server is not None:
            self.server.send(record)
        if self.sink is not None:
            self.sink.write(record)
            self.sink.flush()

    def destroy_node(self):
        if self.server is not None:
            self.server.close()
        if self.sink is not None:
            self.sink.close()
        super().destroy_node()


def main(args=None):
    return c.run(WitsNode, args)


if __name__ == "__main__":
    sys.exit(main())
