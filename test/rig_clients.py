"""A rig's WITS0 client for the graph tests: connects to the wits node's TCP port as soon as it
listens and keeps what it reads until the node closes the connection (the graph stopped) or
``stop`` is set.  What it received is parsed with :mod:`wits_parser` (written from the spec)."""
import socket
import time


def wits_client(port, got, stop):
    """Append every chunk read from tcp://127.0.0.1:``port`` to ``got`` (run in a thread)."""
    s = None
    while s is None and not stop.is_set():
        try:
            s = socket.create_connection(("127.0.0.1", port), timeout=1)
        except OSError:
            time.sleep(0.1)
    if s is None:
        return
    s.settimeout(0.5)
    while True:
        try:
            chunk = s.recv(65536)
        except socket.timeout:
            if stop.is_set():
                break
            continue
        except OSError:
            break
        if not chunk:
            break
        got.append(chunk)
    s.close()
