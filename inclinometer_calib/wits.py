"""WITS level 0 out: survey stations as record 07 (survey/directional) — ROS-free.

WITS level 0 is ASCII: a record starts with ``&&`` CR LF, each data line is a four-digit code
``RRII`` (record 07, item II) followed at once by the value, and the record ends with ``!!`` CR LF.
Items sent (an item whose value is undefined, NaN, is left out, as WITS readers expect):

====  ==========================================  ====================================
0701  well identifier                              text
0702  sidetrack / hole section number              integer
0703  record identifier                            7
0704  sequence identifier                          integer, one per record sent
0705  date                                         YYMMDD (UTC)
0706  time                                         HHMMSS (UTC)
0707  activity code                                integer (0: survey)
0708  survey depth, measured                       m
0709  survey depth, vertical (TVD)                 m
0711  hole depth, measured                         m
0712  survey type                                  text (``MWD``)
0713  inclination                                  deg
0714  azimuth, uncorrected (magnetic north)        deg
0715  azimuth, corrected (true or grid north)      deg
0716  magnetic toolface                            deg
0717  gravity toolface                             deg
0718  north–south displacement (+ north)           m
0719  east–west displacement (+ east)              m
0720  dogleg severity                              deg/30 m
====  ==========================================  ====================================

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

#: (item, field of a station dict, decimals) of the numeric items, in the order sent.
NUMERIC_ITEMS = (
    (8, "measured_depth_m", 2), (9, "tvd_m", 2), (11, "hole_depth_m", 2), (13, "drift_deg", 2),
    (14, "azimuth_magnetic_deg", 2), (15, "azimuth_deg", 2), (16, "magnetic_toolface_deg", 2),
    (17, "gravity_toolface_deg", 2), (18, "north_m", 2), (19, "east_m", 2), (20, "dls_deg_per_30m", 2),
)
RECORD = 7


def _line(item: int, value: str) -> str:
    return f"{RECORD:02d}{item:02d}{value}\r\n"


def encode(station: dict, sequence: int, well_id: str = "WELL", hole_section: int = 0,
           when: _dt.datetime | None = None, survey_type: str = "MWD") -> bytes:
    """One WITS0 record 07 of a survey station (a dict with the fields of ``SurveyStation`` and
    the trajectory's: ``measured_depth_m``, ``tvd_m``, ``north_m``, ``east_m``,
    ``dls_deg_per_30m``, ``azimuth_magnetic_deg``; ``hole_depth_m`` defaults to the survey depth).
    ``when``: the station's time (UTC)."""
    t = when or _dt.datetime.now(_dt.timezone.utc)
    lines = ["&&\r\n", _line(1, str(well_id)), _line(2, str(int(hole_section))), _line(3, str(RECORD)),
             _line(4, str(int(sequence))), _line(5, t.strftime("%y%m%d")), _line(6, t.strftime("%H%M%S")),
             _line(7, "0")]
    vals = dict(station)
    vals.setdefault("hole_depth_m", vals.get("measured_depth_m", float("nan")))
    for item, key, dec in NUMERIC_ITEMS:
        v = vals.get(key)
        if v is not None and math.isfinite(float(v)):
            lines.append(_line(item, f"{float(v):.{dec}f}"))
        if item == 11:                     # the survey type follows the hole depth
            lines.append(_line(12, survey_type))
    lines.append("!!\r\n")
    return "".join(lines).encode("ascii")


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
