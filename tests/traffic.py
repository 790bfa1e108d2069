"""Bulk TCP traffic for measuring a shaped path: `recv HOST PORT SECONDS` accepts one connection
and prints the achieved payload rate as JSON; `send HOST PORT SECONDS` writes as fast as the
path allows. The rate is the slope between the moment 20 % of the data had arrived and the end,
so the start (token-bucket burst, socket buffers filling) does not count."""

from __future__ import annotations

import json
import socket
import sys
import time


def receive(host: str, port: int, seconds: float) -> dict:
    with socket.create_server((host, port)) as server:
        print("listening", flush=True)
        conn, _ = server.accept()
        with conn:
            marks = []
            total = 0
            deadline = time.monotonic() + seconds + 30
            while time.monotonic() < deadline:
                data = conn.recv(65536)
                if not data:
                    break
                total += len(data)
                marks.append((time.monotonic(), total))
    if len(marks) < 10:
        return {"bytes": total, "bytes_per_s": 0.0}
    start = next(m for m in marks if m[1] >= 0.2 * total)
    end = marks[-1]
    return {"bytes": total, "seconds": end[0] - start[0],
            "bytes_per_s": (end[1] - start[1]) / (end[0] - start[0])}


def send(host: str, port: int, seconds: float) -> None:
    chunk = b"\x5a" * 16384
    with socket.create_connection((host, port), timeout=30) as conn:
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 32768)  # a short tail after the end
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            conn.sendall(chunk)


if __name__ == "__main__":
    mode, host, port, seconds = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    if mode == "recv":
        print(json.dumps(receive(host, port, seconds)), flush=True)
    else:
        send(host, port, seconds)
