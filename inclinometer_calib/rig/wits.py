"""WITS level 0 out: survey stations as record 07 (survey/directional) — ROS-free.

WITS level 0 is ASCII: a record starts with ``&&`` CR LF, each data line is a four-digit code
``RRII`` (record 07, item II) followed at once by the value, and the record ends with ``!!`` CR LF.
Items sent (an item whose value is undefined, NaN, is left out, as WITS readers expect), with the
WITS dictionary's names and units — metric (``units="m"``) or FPS (``units="ft"``):

====  ==========================================  =======  =======  ==================================
item  WITS dictionary name (mnemonic)             metric   FPS      sent
====  ==========================================  =======  =======  ==================================
0701  Well Identifier (WID)                                         text
0702  Sidetrack/Hole Sect No. (SKNO)                                integer
0703  Record Identifier (RID)                                       7
0704  Sequence Identifier (SQID)                                    integer, one per record sent
0705  Date (DATE)                                                   YYMMDD (UTC)
0706  Time (TIME)                                                   HHMMSS (UTC)
0707  Activity Code (ACTC)                                          0 (survey)
0708  Depth Svy/reading (meas) (DSVM)             M        F        measured depth
0709  Depth Svy/reading (vert) (DSVV)             M        F        TVD
0711  Depth Hole (meas) (DMEA)                    M        F        hole depth (the survey depth)
0712  Svy Type (STYP)                                               ``MWD``
0713  Svy Inclination (SINC)                      DEG      DEG      drift
0714  Svy Azimuth (uncorrected) (SAZU)            DEG      DEG      azimuth from magnetic north
0715  Svy Azimuth (corrected) (SAZC)              DEG      DEG      azimuth from the run's north
0716  Svy Magnetic Toolface (SMTF)                DEG      DEG      magnetic toolface
0717  Svy Gravity Toolface (SGTF)                 DEG      DEG      gravity toolface
0718  Svy North-South Position (SNS)              M        F        north along the run's north
0719  Svy East-West Position (SEW)                M        F        east, square to it
0720  Svy Dog Leg Severity (SDLS)                 DGHM     DGHF     deg per 100 m / per 100 ft
====  ==========================================  =======  =======  ==================================

Source of the names and units: the WITS dictionary (W.I.T.S., record 7 "Survey/Directional") as
vendored in ``mwdstd/mwdstdwits`` ``src/wits-dictionary.ts`` (items 0701–0726); ``DGHM``/``DGHF``
are its codes for degrees per hundred metres / feet (so the metric dogleg is per **100 m**, not
the 30 m the stations carry: ×100/30).  Feet are international feet (0.3048 m).

**One north.**  0715 (corrected azimuth) and 0718/0719 (north/east) are along the same north, the
station's ``azimuth_reference`` (the run's ``north``: grid by default on a site with a grid, else
true, else magnetic); a receiver recomputing positions from 0708/0713/0715 by minimum curvature
lands on 0718/0719.  Record 07 has no item for the north reference (items 0722–0726 are spares
without a definition), so it is declared here, in the nodes' and CLI's log
(:func:`describe`) and in docs/nodes.md.  0714 is always from magnetic north.  Angles are sent
with three decimals (0.001°: rounding moves a position by well under a centimetre over a long
well; with two a 1.5 km well can be a centimetre off), lengths with two.

:class:`WitsServer` streams the records to any number of TCP clients (loopback by default): each
client has its own outgoing buffer, written without blocking from one thread; a client that
stalls (its buffer grows past ``max_buffer`` bytes) or disconnects is dropped and said, and the
others lose nothing.  :func:`encode` also writes to a file or a serial-like device (any binary
stream).
"""
from __future__ import annotations

import datetime as _dt
import math
import selectors
import socket
import threading
from dataclasses import dataclass, field

from ..correct.trajectory import DLS_LENGTH, FOOT_M

#: (item, field of a station dict, decimals, quantity) of the numeric items, in the order sent;
#: quantity: ``length`` (m or ft), ``angle`` (deg) or ``dls`` (deg per 100 m or 100 ft).
NUMERIC_ITEMS = (
    (8, "measured_depth_m", 2, "length"), (9, "tvd_m", 2, "length"), (11, "hole_depth_m", 2, "length"),
    (13, "drift_deg", 3, "angle"), (14, "azimuth_magnetic_deg", 3, "angle"), (15, "azimuth_deg", 3, "angle"),
    (16, "magnetic_toolface_deg", 3, "angle"), (17, "gravity_toolface_deg", 3, "angle"),
    (18, "north_m", 2, "length"), (19, "east_m", 2, "length"), (20, "dls_deg_per_30m", 3, "dls"),
)
#: The WITS dictionary's units of record 07 (module docstring): units -> quantity -> (unit code,
#: factor from the station dict's value: m, deg, deg/30 m).
UNITS = {
    "m": {"length": ("M", 1.0), "angle": ("DEG", 1.0),
          "dls": ("DGHM", DLS_LENGTH["deg/100m"] / DLS_LENGTH["deg/30m"])},
    "ft": {"length": ("F", 1.0 / FOOT_M), "angle": ("DEG", 1.0),
           "dls": ("DGHF", DLS_LENGTH["deg/100ft"] / DLS_LENGTH["deg/30m"])},
}
RECORD = 7


def _line(item: int, value: str) -> str:
    return f"{RECORD:02d}{item:02d}{value}\r\n"


def encode(station: dict, sequence: int, well_id: str = "WELL", hole_section: int = 0,
           when: _dt.datetime | None = None, survey_type: str = "MWD", units: str = "m") -> bytes:
    """One WITS0 record 07 of a survey station (a station dict, :func:`surveystation.from_msg`:
    ``azimuth_deg`` and ``north_m``/``east_m`` along its ``azimuth_reference``, the trajectory's
    ``measured_depth_m``, ``tvd_m``, ``dls_deg_per_30m``, and ``azimuth_magnetic_deg``;
    ``hole_depth_m`` defaults to the survey depth), in ``units`` (:data:`UNITS`: ``m`` or ``ft``).
    ``when``: the station's time (UTC)."""
    if units not in UNITS:
        raise ValueError(f"WITS0 units {units!r}: one of {', '.join(UNITS)}")
    t = when or _dt.datetime.now(_dt.timezone.utc)
    lines = ["&&\r\n", _line(1, str(well_id)), _line(2, str(int(hole_section))), _line(3, str(RECORD)),
             _line(4, str(int(sequence))), _line(5, t.strftime("%y%m%d")), _line(6, t.strftime("%H%M%S")),
             _line(7, "0")]
    vals = dict(station)
    vals.setdefault("hole_depth_m", vals.get("measured_depth_m", float("nan")))
    for item, key, dec, quantity in NUMERIC_ITEMS:
        v = vals.get(key)
        if v is not None and math.isfinite(float(v)):
            lines.append(_line(item, f"{float(v) * UNITS[units][quantity][1]:.{dec}f}"))
        if item == 11:                     # the survey type follows the hole depth
            lines.append(_line(12, survey_type))
    lines.append("!!\r\n")
    return "".join(lines).encode("ascii")


def describe(stations, units: str = "m") -> str:
    """What a receiver of records 07 of ``stations`` (station dicts) must know, in words: the
    north of 0715/0718/0719 and the units (the record cannot say it, module docstring)."""
    norths = sorted({s.get("azimuth_reference") or "magnetic" for s in stations})
    u = UNITS[units]
    return (f"azimuth 0715 and north/east 0718/0719 along {' and '.join(norths)} north, 0714 from magnetic north; "
            f"units {u['length'][0]}, {u['angle'][0]}, dogleg {u['dls'][0]}")


@dataclass
class _Client:
    sock: socket.socket
    addr: tuple
    out: bytearray = field(default_factory=bytearray)


class WitsServer:
    """A WITS0 TCP server: ``send(record bytes)`` queues a record for every connected client.

    One background thread accepts clients and writes their buffers without blocking; ``port`` 0
    picks a free port (:attr:`port` says which).  ``say``: callable for what happens to clients."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, max_buffer: int = 1 << 20, say=None,
                 sndbuf: int = 1 << 16):
        self.say = say or (lambda msg: None)
        self.max_buffer = int(max_buffer)
        # a small kernel send buffer per client: a stalled client shows in our buffer soon, instead
        # of hiding megabytes in the kernel's
        self.sndbuf = int(sndbuf)
        self._sel = selectors.DefaultSelector()
        self._lsock = socket.create_server((host, port), reuse_port=False)
        self._lsock.setblocking(False)
        self.port = self._lsock.getsockname()[1]
        self.host = host
        self._sel.register(self._lsock, selectors.EVENT_READ, None)
        self._clients: dict = {}
        self._lock = threading.Lock()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._stop = False
        self.sent = 0
        self.dropped = []          # (address, why) of clients dropped
        self._thread = threading.Thread(target=self._run, name="wits-server", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        with self._lock:
            return len(self._clients)

    def send(self, record: bytes) -> None:
        """Queue ``record`` for every client connected now (never blocks)."""
        with self._lock:
            for c in list(self._clients.values()):
                c.out += record
                if len(c.out) > self.max_buffer:
                    self._drop(c, f"stalled: more than {self.max_buffer} bytes waiting")
                else:
                    self._sel.modify(c.sock, selectors.EVENT_READ | selectors.EVENT_WRITE, c)
            self.sent += 1
        self._wake_w.send(b"x")

    def _drop(self, c, why):
        # caller holds the lock
        self._clients.pop(c.sock.fileno(), None)
        try:
            self._sel.unregister(c.sock)
        except (KeyError, ValueError):
            pass
        c.sock.close()
        self.dropped.append((c.addr, why))
        self.say(f"WITS client {c.addr[0]}:{c.addr[1]} dropped: {why}")

    def _run(self):
        while not self._stop:
            for key, mask in self._sel.select(timeout=0.5):
                if key.data is None:                       # a new client
                    try:
                        sock, addr = self._lsock.accept()
                    except BlockingIOError:
                        continue
                    sock.setblocking(False)
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.sndbuf)
                    with self._lock:
                        c = _Client(sock, addr)
                        self._clients[sock.fileno()] = c
                        self._sel.register(sock, selectors.EVENT_READ, c)
                    self.say(f"WITS client {addr[0]}:{addr[1]} connected")
                elif key.data == "wake":
                    try:
                        self._wake_r.recv(4096)
                    except BlockingIOError:
                        pass
                else:
                    c = key.data
                    with self._lock:
                        if c.sock.fileno() not in self._clients:
                            continue
                        if mask & selectors.EVENT_READ:        # a client never sends: data or EOF
                            try:
                                data = c.sock.recv(4096)
                            except (BlockingIOError, InterruptedError):
                                data = b"?"
                            except OSError as exc:
                                self._drop(c, f"error: {exc}")
                                continue
                            if not data:
                                self._drop(c, "disconnected")
                                continue
                        if mask & selectors.EVENT_WRITE and c.out:
                            try:
                                n = c.sock.send(c.out)
                                del c.out[:n]
                            except (BlockingIOError, InterruptedError):
                                pass
                            except OSError as exc:
                                self._drop(c, f"error: {exc}")
                                continue
                        if not c.out:
                            self._sel.modify(c.sock, selectors.EVENT_READ, c)

    def close(self) -> None:
        self._stop = True
        self._wake_w.send(b"x")
        self._thread.join(timeout=5)
        with self._lock:
            for c in list(self._clients.values()):
                c.sock.close()
            self._clients.clear()
        self._lsock.close()
        self._wake_r.close()
        self._wake_w.close()
        self._sel.close()
