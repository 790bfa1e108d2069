"""A Zenoh client that watches a run from outside and prints one JSON line per event, stamped
with the wall clock (comparable across network namespaces of one host):

    python tests/watch.py ENDPOINT RUN_ID

{"t": …, "stats": ROLE, "ident": …, "values": {…}} for every stats message and
{"t": …, "alive": KEY, "up": true|false} for every liveliness change. Tests start it where its
view is the one they need (e.g. inside the namespace of the router). Stops on SIGTERM/SIGINT.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh

from tpdeb.protocol import DecodeError, Keys, Stats, decode
from tpdeb.services.net.session import open_session
from tpdeb.services.process import StopSignal

lock = threading.Lock()


def emit(record: dict) -> None:
    with lock:
        print(json.dumps({"t": time.time(), **record}), flush=True)


def on_stats(sample) -> None:
    try:
        stats = decode(sample.payload.to_bytes(), Stats)
    except DecodeError:
        return
    emit({"stats": stats.role, "ident": stats.ident, "values": stats.values})


def on_alive(sample) -> None:
    emit({"alive": str(sample.key_expr), "up": sample.kind == zenoh.SampleKind.PUT})


def main() -> int:
    endpoint, run_id = sys.argv[1], sys.argv[2]
    keys = Keys(run_id)
    session = open_session("client", [], [endpoint], connect_timeout_s=60)
    stop = StopSignal().install()
    try:
        session.declare_subscriber(keys.stats_all, on_stats)
        session.liveliness().declare_subscriber(keys.alive_all, on_alive, history=True)
        emit({"watching": endpoint})
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
