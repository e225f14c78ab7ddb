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
magnetic and gravity toolface, north/east, dogleg severity (``wits.NUMERIC_ITEMS``), in the WITS
dictionary's metric or FPS units (``units``: ``m`` or ``ft``).  The corrected azimuth and north/east
are along the stations' one north (their ``azimuth_reference``, the correction node's ``north``):
record 07 has no item to say which, so the node says it in its log at the first station and
whenever it changes (:func:`wits.describe`).

WITSML (``witsml_file``, empty: off): after every survey station the node rewrites the run's
trajectory document (:mod:`witsml`: well ``well_id``, wellbore ``wellbore``; ``witsml.version`` 2.1
or 1.4.1.1, ``witsml.units`` m or ft, ``witsml.start_time``, the datum, the store's uids: the
``witsml.*`` parameters are :data:`witsml.OPTION_HELP`) with every station so far, validated against
the schema and written atomically (a temporary file renamed over it: a reader never sees half a
document, and one that does not validate is not written, said at ERROR); the well, wellbore (and
2.1 datum) documents beside it (:func:`witsml.parent_path`) unless ``witsml.well_uid`` names the
store's.  The geomagnetic model of each station comes from the calibration records on
``/calibration/coefficients`` (:func:`witsml.mag_models`), as the CLI takes it from the recorded
ones.  2.1 ``ActiveStatus`` is ``active`` while the node runs and ``inactive`` in the last rewrite
when it stops.  The message becomes the same station dict as a recorded bag's
(:func:`surveystation.from_msg`), so the live document equals ``inclinometer-calib witsml`` of the
recorded run with the same options.
"""
from __future__ import annotations

import datetime as dt
import sys

from rclpy.node import Node

from ..rig import witsml
from ..io.surveystation import from_msg as station_dict
from ..rig.wits import UNITS, WitsServer, describe, encode
from . import common as c
from inclinometer_calib.msg import CalibrationCoefficients, SurveyStation


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
        self.units = p.declare("units", "m", "Units of the records: m (the WITS dictionary's metric: M, DEG, "
                               "dogleg DGHM = deg/100 m) or ft (FPS: F, DEG, DGHF = deg/100 ft)", read_only=True,
                               choices=tuple(UNITS))
        max_buffer = p.declare("max_buffer_bytes", 1 << 20, "A client with more than this waiting is "
                               "dropped as stalled", read_only=True, range=(1024, 1 << 30))
        self.witsml_file = p.declare("witsml_file", "", "WITSML trajectory document rewritten (atomically) "
                                     "after every survey station (empty: none)", read_only=True)
        self.wellbore = p.declare("wellbore", "WELLBORE", "Wellbore name of the WITSML document (the well is "
                                  "well_id)", read_only=True)
        defaults = witsml.Options()
        version = p.declare("witsml.version", defaults.version, witsml.OPTION_HELP["version"], read_only=True,
                            choices=witsml.VERSIONS)
        self.witsml_options = {"well": self.well_id, "wellbore": self.wellbore, "version": version}
        for name in witsml.OPTION_HELP:
            if name not in self.witsml_options:
                self.witsml_options[name] = p.declare(
                    f"witsml.{name}", getattr(defaults, name), witsml.OPTION_HELP[name], read_only=True,
                    check=lambda v, name=name: witsml.option_problem(name, v, version))
        if not self.port and not self.output and not self.witsml_file:
            raise ValueError("give a TCP port, an output file and/or a witsml_file: nothing to send the stations to")
        self.stations = []           # every station received (station dicts), for the WITSML document
        self.witsml_written = 0      # stations in the document on disk
        self.mag_models = {}         # calibration record id -> its site's geomagnetic model (witsml.mag_models)
        self._notes_said = set()
        if self.witsml_file:
            witsml.Options(**self.witsml_options).check()   # a bad combination: said now, not at the first station
            witsml.load_schemas(version)  # load the schema now, not at the first station
            self.create_subscription(CalibrationCoefficients, c.TOPIC_COEFFICIENTS, self._on_record, c.latched_qos())
        self.server = WitsServer(self.host, self.port, max_buffer=max_buffer, say=self.get_logger().info) \
            if self.port else None
        self.sink = open(self.output, "ab") if self.output else None   # noqa: SIM115 (closed in destroy_node)
        self.sequence = 0
        self._said = ""              # the north and units last said (wits.describe)
        self._seen = set()           # (station id, stamp) of every station received: each sent once
        self.create_subscription(SurveyStation, c.TOPIC_STATION, self._on_station, c.reliable_qos(100))
        self.get_logger().info("WITS0 record 07 of the survey stations"
                               + (f" on tcp://{self.host}:{self.server.port}" if self.server else "")
                               + (f" to {self.output}" if self.output else "")
                               + (f"; WITSML {version} trajectory in {self.witsml_file}" if self.witsml_file else ""))

    def _on_station(self, msg):
        key = (msg.station_id, msg.header.stamp.sec, msg.header.stamp.nanosec)
        if key in self._seen:
            # the same station again: a correction node restarted mid-run publishes those its
            # predecessor's recording lacks, and some reached this node already
            self.get_logger().info(f"station {msg.station_id} received again (a restarted correction node): "
                                   "already sent")
            return
        self._seen.add(key)
        station = station_dict(msg)          # the one conversion (an older recording's too)
        if self.witsml_file:
            self.stations.append(station)
            if witsml.select_stations(self.stations[-1:])[0]:
                self._write_witsml(active=True)
        if not msg.coefficients_id:
            return                                   # raw: before any calibration
        if msg.status == 2:
            self.get_logger().warning(f"station {msg.station_id}: status error (probe moved or gravity out of "
                                      "tolerance): not sent as a survey")
            return
        self.sequence += 1
        said = describe([station], self.units)
        if said != self._said:
            self.get_logger().info(f"WITS0 record 07 from station {msg.station_id} on: {said}")
            self._said = said
        when = dt.datetime.fromtimestamp(station["stamp"], dt.timezone.utc)
        record = encode(station, self.sequence, self.well_id, self.hole_section, when, units=self.units)
        if self.server is not None:
            self.server.send(record)
        if self.sink is not None:
            self.sink.write(record)
            self.sink.flush()

    def _on_record(self, msg):
        """A calibration record: the geomagnetic model of its site, for the stations it corrects."""
        self.mag_models.update(witsml.mag_models([{"id": msg.id, "coefficients_yaml": msg.coefficients_yaml}]))

    def _write_witsml(self, active: bool) -> None:
        """Rewrite the WITSML documents with every station so far (validated, atomic)."""
        try:
            export = witsml.write_trajectory(self.witsml_file, self.stations, active=active, models=self.mag_models,
                                             **self.witsml_options)
        except (witsml.WitsmlError, OSError) as exc:
            self.get_logger().error(f"WITSML document {self.witsml_file} not rewritten (the previous one stays): "
                                    f"{exc}")
            return
        self.witsml_written = export.exported
        for note in export.notes:
            if note not in self._notes_said:
                self._notes_said.add(note)
                self.get_logger().warning(f"WITSML: {note}")

    def destroy_node(self):
        if self.witsml_file and self.witsml_written:
            self._write_witsml(active=False)         # the survey is over: the document stops growing
        if self.server is not None:
            self.server.close()
        if self.sink is not None:
            self.sink.close()
        super().destroy_node()


def main(args=None):
    return c.run(WitsNode, args)


if __name__ == "__main__":
    sys.exit(main())
