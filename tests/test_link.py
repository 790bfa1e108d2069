"""`tpdeb-link` as a process: it bridges both ways, and a SIGTERM with connections still open
stops it cleanly — every connection closed, exit 0, no traceback or abandoned task in its log."""

from __future__ import annotations

import socket
import sys
import time

from tests.procs import free_port

# A stand-in for the router: echoes every byte back (both directions of the link carry data).
ECHO = """
import asyncio, sys
async def echo(reader, writer):
    while data := await reader.read(65536):
        writer.write(data)
        await writer.drain()
    writer.close()
async def main():
    server = await asyncio.start_server(echo, "127.0.0.1", int(sys.argv[1]))
    print("listening", flush=True)
    async with server:
        await server.serve_forever()
asyncio.run(main())
"""


def through(port: int) -> socket.socket:
    """A connection through the link that has carried data both ways, left open."""
    conn = socket.create_connection(("127.0.0.1", port), timeout=10)
    conn.sendall(b"x" * 100_000)
    got = 0
    while got < 100_000:
        chunk = conn.recv(65536)
        assert chunk, "the link closed the connection"
        got += len(chunk)
    return conn


def test_sigterm_with_open_connections_stops_cleanly(procs):
    router_port, link_port = free_port(), free_port()
    router = procs.spawn_command([sys.executable, "-c", ECHO, str(router_port)], "echo", {})
    procs.wait_for_line(router, "listening")
    link = procs.spawn("link", "--listen", f"tcp/127.0.0.1:{link_port}",
                       "--connect", f"tcp/127.0.0.1:{router_port}", "--publish-stats", "false",
                       "--up-bytes-per-s", "1000000")
    procs.wait_for_line(link, "tpdeb-link: ")
    open_connections = [through(link_port) for _ in range(3)]
    link.terminate()
    assert link.wait(20) == 0
    log = procs.output(link)
    for bad in ("Traceback", "Task was destroyed", "Exception ignored", "Error"):
        assert bad not in log, log
    assert log.rstrip().endswith("tpdeb-link: stopped"), log
    for conn in open_connections:  # each one closed by the link, not left hanging
        conn.settimeout(5)
        deadline = time.monotonic() + 5
        while (data := conn.recv(65536)) and time.monotonic() < deadline:
            pass
        assert data == b""
        conn.close()
