"""`tpdeb-link` as a process: it bridges both ways, and a SIGTERM with connections still open
stops it cleanly — every connection closed, exit 0, no traceback or abandoned task in its log;
and in-process, a connection still reaching the router when the link stops closes its sockets."""

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


def test_a_connection_cancelled_while_reaching_the_router_closes_both_its_sockets(monkeypatch):
    """The link stopping while a connection still waits on the router: the actor's side and the
    half-open socket to the router are closed then, not left to the garbage collector."""
    import asyncio

    from tpdeb.services import link

    made: list[socket.socket] = []
    real = link.bound_socket

    def kept(family, rcvbuf):
        made.append(real(family, rcvbuf))
        return made[-1]

    class Actor:  # the actor's side of the connection: only its close matters here
        closed = False

        def close(self):
            self.closed = True

    async def hang(sock, address):  # a router that never answers the SYN
        await asyncio.Event().wait()

    async def scenario() -> Actor:
        monkeypatch.setattr(link, "bound_socket", kept)
        monkeypatch.setattr(asyncio.get_running_loop(), "sock_connect", hang)
        bridge, actor = link.Link(link.LinkConfig(connect=f"tcp/127.0.0.1:{free_port()}")), Actor()
        bridge.accept(None, actor)
        await asyncio.sleep(0.05)
        assert made and made[0].fileno() != -1 and not actor.closed  # still connecting
        await bridge.close()
        assert not bridge.tasks
        return actor

    actor = asyncio.run(scenario())
    assert actor.closed and made[0].fileno() == -1
