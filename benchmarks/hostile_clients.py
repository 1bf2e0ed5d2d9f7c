"""Hostile peers as programs of their own (``python -c SCRIPT ARGS``, run under ``nice -n 19``), shared
by the fault suite and :mod:`benchmarks.bench_hostile`: each binds its socket(s) to a loopback
address of its own (127.0.0.0/8 is all loopback on Linux) and never reads what the service sends."""

from __future__ import annotations

IGTL_FLOODER = r"""
import socket, struct, sys
port, source, kind = int(sys.argv[1]), sys.argv[2], sys.argv[3]
batch = struct.pack(">H12s20sQQQ", 1, kind.encode(), b"", 0, 0, 0) * 1000  # empty bodies: CRC 0
while True:
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # never read: a small window fills soon
    s.bind((source, 0))
    try:
        s.connect(("127.0.0.1", port))
        print("flooding", flush=True)
        while True:
            s.sendall(batch)
    except OSError:
        print("dropped", flush=True)
    finally:
        s.close()
"""
"""OpenIGTLink GET_ query headers without reading: ``PORT SOURCE KIND``; prints ``flooding`` once
connected and ``dropped`` each time the server closes it (it reconnects)."""

SLOW_READER = r"""
import socket, sys
port, source, n = int(sys.argv[1]), sys.argv[2], int(sys.argv[3])
req = f"GET /static/swagger/swagger-ui-bundle.js HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode() * 10
held = []
for _ in range(n):
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # never read: a small window fills soon
    s.bind((source, 0))
    try:
        s.connect(("127.0.0.1", port))
        s.sendall(req)
    except OSError:
        pass
    held.append(s)
print("holding", flush=True)
sys.stdin.read()  # until the test closes our stdin
"""
"""``N`` HTTP connections each pipelining ten GETs of the 1.7 MB Swagger bundle, never reading:
``PORT SOURCE N``; prints ``holding`` once all are open and holds them until its stdin closes."""
