"""Zenoh session setup every service shares (DESIGN §3, "Zenoh facts").

Topology of the embedded default: the replay server opens a `router`-mode session listening on
`--listen`; the learner and the actors open `client` sessions connected to it, so everything
crosses one TCP connection per process (which is also what the link shim needs to throttle).
Multicast scouting is off; nothing is discovered that was not named.
"""

from __future__ import annotations

import json
import logging
import secrets
import socket
import ssl
import time

import zenoh

from tpdeb.protocol import DecodeError, JoinReply, JoinRequest, Keys, RunSpec, decode, encode
from tpdeb.protocol.topics import BY_NAME
from tpdeb.services.config import ConfigError
from tpdeb.services.net.security import Security, security_of

# A put blocked longer than this closes the transport and loses the data (DESIGN §3). Actors
# already bound their outbox, so waiting long here only delays them, it never loses anything.
BLOCK_WAIT_BEFORE_CLOSE_MS = 60_000


# A client that reached its router retries a failing handshake for this long before it says
# why: wrong credentials fail every time, and waiting out the whole connect timeout helps no
# one. Long enough for a handshake through a slow, queued link (the link shim's queue alone
# may hold it 0.5 s per message).
REFUSED_AFTER_S = 10.0
PROBE_TIMEOUT_S = 2.0


def qos(topic: str) -> dict:
    """Zenoh publisher options of a topic, as the topic table declares them (DESIGN §3)."""
    t = BY_NAME[topic]
    return {"priority": getattr(zenoh.Priority, t.priority.upper()),
            "congestion_control": getattr(zenoh.CongestionControl, t.congestion.upper()),
            "express": t.express}


def declare_publisher(session, topic: str, key: str):
    """A publisher on `key` of `topic` with the topic's QoS."""
    return session.declare_publisher(key, **qos(topic))


def zenoh_config(mode: str, listen: list[str], connect: list[str], connect_timeout_s: float = 60.0,
                 lease_ms: int = 10_000, tcp_buffer_bytes: int = 0,
                 security: Security | None = None, shared_memory: bool = False):
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                      json.dumps(BLOCK_WAIT_BEFORE_CLOSE_MS * 1000))  # microseconds
    conf.insert_json5("transport/link/tx/lease", json.dumps(lease_ms))
    # Shared memory carries messages over 3 KB between processes of one host around the TCP
    # link (Zenoh's transport optimisation, negotiated per link): for the replay, the learner
    # and the router where they share a host; never for actors, whose every byte must cross
    # the network path (and the link shim) it would cross between hosts.
    conf.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory))
    if tcp_buffer_bytes:
        # On a throttled link the kernel's autotuned send buffer (MBs on loopback) would queue
        # seconds of data ahead of acks and keep-alives; a small one keeps the queue in Zenoh,
        # where priorities apply.
        for option in ("so_sndbuf", "so_rcvbuf"):
            conf.insert_json5(f"transport/link/tcp/{option}", json.dumps(tcp_buffer_bytes))
    if mode == "client":
        # Keep retrying the router for a while: services may start in any order.
        timeout_ms = int(connect_timeout_s * 1e3)
        conf.insert_json5("connect/timeout_ms", json.dumps({"client": timeout_ms}))
        conf.insert_json5("connect/exit_on_failure", json.dumps({"client": True}))
        # After a router restart or a partition the client reconnects on its own; Zenoh's
        # default back-off (up to 4 s between tries) would add seconds to every recovery.
        conf.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}))
    if security is not None:
        apply_security(conf, security)
    return conf


def apply_security(conf, security: Security) -> None:
    """TLS files, user/password authentication and access-control rules (net/security.py)."""
    settings = {
        "transport/link/tls/root_ca_certificate": security.tls_ca,
        "transport/link/tls/listen_certificate": security.tls_cert,
        "transport/link/tls/listen_private_key": security.tls_key,
        "transport/auth/usrpwd/user": security.user,
        "transport/auth/usrpwd/password": security.password,
        "transport/auth/usrpwd/dictionary_file": security.auth_file,
    }
    for key, value in settings.items():
        if value:
            conf.insert_json5(key, json.dumps(str(value)))
    if security.access_control:
        conf.insert_json5("access_control", json.dumps(security.access_control))


def check_endpoints(name: str, endpoints: list[str]) -> None:
    for endpoint in endpoints:
        proto, _, address = endpoint.partition("/")
        host, _, port = address.rpartition(":")
        if proto not in ("tcp", "udp", "tls", "quic") or not host or not port.isdigit():
            raise ConfigError(f"{name}={endpoint!r}: expected PROTO/HOST:PORT, e.g. "
                              "tcp/127.0.0.1:7447")


def open_session(mode: str, listen: list[str], connect: list[str],
                 connect_timeout_s: float = 60.0, tcp_buffer_bytes: int = 0,
                 security: Security | None = None,
                 shared_memory: bool = False) -> zenoh.Session:
    """Open a session, turning Zenoh's errors into one line a user can act on. A client waits
    up to `connect_timeout_s` for its router (install signal handlers after this returns)."""
    check_endpoints("listen", listen)
    check_endpoints("connect", connect)
    security = security or Security()
    if mode == "client":
        if not connect:
            raise ConfigError("a client session needs a router to connect to: pass --connect "
                              "PROTO/HOST:PORT, e.g. tcp/127.0.0.1:7447")
        return _open_client(connect, connect_timeout_s, tcp_buffer_bytes, security,
                            shared_memory)
    try:
        return zenoh.open(zenoh_config(mode, listen, connect, connect_timeout_s,
                                       tcp_buffer_bytes=tcp_buffer_bytes, security=security,
                                       shared_memory=shared_memory))
    except zenoh.ZError as exc:
        text = str(exc)
        if "TLS" in text and any(e.startswith("tls/") for e in listen):
            raise ConfigError(f"cannot listen on {', '.join(listen)} with --tls-cert "
                              f"{security.tls_cert} and --tls-key {security.tls_key}: "
                              f"{_zenoh_reason(text)} (tpdeb-certs writes a matching pair)"
                              ) from None
        if "dictionary" in text:
            raise ConfigError(f"--auth-file {security.auth_file}: {_zenoh_reason(text)}") from None
        if listen and ("in use" in text.lower() or "bind" in text.lower()):
            raise ConfigError(f"cannot listen on {', '.join(listen)}: the address is in use or "
                              "not available; pick a free port (--listen)") from None
        raise ConfigError(f"cannot open a Zenoh session (mode {mode}, listen {listen}, "
                          f"connect {connect}): {text}") from None


def _zenoh_reason(text: str) -> str:
    """Zenoh's message without its source locations."""
    return text.split(" at /")[0].rstrip(". ")


def _open_client(connect: list[str], connect_timeout_s: float, tcp_buffer_bytes: int,
                 security: Security, shared_memory: bool) -> zenoh.Session:
    """Wait for a router to accept connections (it may start after us), then open the session.
    Zenoh answers a refused handshake (bad credentials, an untrusted certificate, TLS on one
    side only) by retrying until its timeout and a generic error, so the link is checked here
    first and a refusal is explained rather than waited out."""
    deadline = time.monotonic() + connect_timeout_s
    last = ""
    while (remaining := deadline - time.monotonic()) > 0:
        states = [probe_endpoint(e, security, min(remaining, PROBE_TIMEOUT_S)) for e in connect]
        if "up" not in states:
            last = next((s for s in states if s != "down"), last)
            time.sleep(min(0.5, max(0.0, deadline - time.monotonic())))
            continue
        attempt_s = max(0.5, min(deadline - time.monotonic(), REFUSED_AFTER_S))
        try:
            return zenoh.open(zenoh_config("client", [], connect, attempt_s,
                                           tcp_buffer_bytes=tcp_buffer_bytes, security=security,
                                           shared_memory=shared_memory))
        except zenoh.ZError:
            pass
        up = [e for e in connect if probe_endpoint(e, security, PROBE_TIMEOUT_S) == "up"]
        if up:  # still there, and it turned us away
            raise ConfigError(refusal(up[0], security))
    if last:
        raise ConfigError(last)
    raise ConfigError(f"no Zenoh router answered at {', '.join(connect)} within "
                      f"{connect_timeout_s:g} s: start the router (tpdeb-router, or tpdeb-replay "
                      "listening there) or fix --connect")


def _host_port(endpoint: str) -> tuple[str, int]:
    host, _, port = endpoint.partition("/")[2].rpartition(":")
    return host.strip("[]"), int(port)


def probe_endpoint(endpoint: str, security: Security, timeout_s: float) -> str:
    """"up" if something there takes a connection (and, for tls/, completes a handshake whose
    certificate this process trusts), "down" if not (yet), or a line saying what is wrong
    with it. An untrusted certificate raises ConfigError: waiting will not fix it."""
    host, port = _host_port(endpoint)
    try:
        sock = socket.create_connection((host, port), timeout=max(0.1, timeout_s))
    except OSError:
        return "down"
    with sock:
        if not endpoint.startswith("tls/"):
            # A bridge (the link shim) takes the connection and closes it at once when the
            # router behind it is down; a router waits for us to speak.
            sock.settimeout(0.3)
            try:
                return "down" if sock.recv(1) == b"" else "up"
            except TimeoutError:
                return "up"
            except OSError:
                return "down"
        try:
            context = ssl.create_default_context(cafile=security.tls_ca or None)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(f"--tls-ca {security.tls_ca}: not a readable PEM certificate "
                              f"({exc})") from None
        sock.settimeout(max(0.1, timeout_s))
        try:
            with context.wrap_socket(sock, server_hostname=host):
                return "up"
        except ssl.SSLCertVerificationError as exc:
            raise ConfigError(untrusted(endpoint, host, security, exc)) from None
        except TimeoutError:
            return (f"{endpoint} takes TCP connections but does not answer TLS: is the router "
                    "listening on tls/ (with --tls-cert and --tls-key), or should you connect "
                    "with tcp/?")
        except (ssl.SSLError, OSError):
            return "down"  # closed mid-handshake: a bridge whose router is not up yet


def untrusted(endpoint: str, host: str, security: Security, exc) -> str:
    if getattr(exc, "verify_code", 0) in (62, 64):  # X509_V_ERR_{HOSTNAME,IP_ADDRESS}_MISMATCH
        return (f"the router's certificate at {endpoint} does not name {host}: make a new one "
                f"with tpdeb-certs --hosts {host},… or connect by a name it lists")
    trusted = f"--tls-ca {security.tls_ca}" if security.tls_ca else "the system's CAs"
    return (f"the router at {endpoint} presented a certificate that {trusted} does not trust "
            f"({exc.verify_message}): pass the CA that signed it (its ca.pem) as --tls-ca or "
            "TPDEB_TLS_CA")


def refusal(endpoint: str, security: Security) -> str:
    """Why a router we reached turned the session away."""
    if endpoint.startswith("tcp/") and _speaks_tls(endpoint):
        return (f"the router at {endpoint} expects TLS: connect to "
                f"tls/{endpoint.partition('/')[2]} with --tls-ca (its CA certificate)")
    if security.user:
        return (f"the router at {endpoint} refused user {security.user!r}: the password "
                "(TPDEB_PASSWORD) is wrong, the router's --auth-file does not list the user, or "
                "the router checks no users (then leave TPDEB_USER unset)")
    return (f"the router at {endpoint} refused this session: it requires a user and password "
            "(set TPDEB_USER and TPDEB_PASSWORD)")


def _speaks_tls(endpoint: str) -> bool:
    context = ssl.create_default_context()
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    try:
        with socket.create_connection(_host_port(endpoint), timeout=PROBE_TIMEOUT_S) as sock, \
                context.wrap_socket(sock):
            return True
    except (OSError, ssl.SSLError):
        return False


def open_for(config, mode: str = "client") -> zenoh.Session:
    """A service's session from its config's listen/connect endpoints, security settings and,
    where it has the setting (not an actor's), shared memory."""
    return open_session(mode, list(config.listen), list(config.connect), config.connect_timeout_s,
                        config.tcp_buffer_bytes, security_of(config),
                        getattr(config, "shared_memory", False))


def close_session(session, prog: str) -> None:
    """Close a session at the end of a process. A close that times out (the router is gone or
    the machine is overloaded) loses nothing at that point: say so, and go on exiting."""
    try:
        session.close()
    except zenoh.ZError as exc:
        logging.getLogger(prog).info(
            f"the Zenoh session did not close cleanly ({str(exc).split(' at ')[0]}); exiting "
            "anyway")


def fetch_spec(session, keys: Keys, timeout_s: float, stop=None) -> RunSpec:
    """Ask the replay server for the run spec until it answers (or `timeout_s` passes)."""
    return ask_replay(session, keys, keys.spec, RunSpec, timeout_s, stop, what="run spec")


def join_run(session, keys: Keys, timeout_s: float, stop=None) -> int:
    """`--actor-id auto`: the id the replay server hands this process (DESIGN §5)."""
    nonce = secrets.randbits(62)
    answer = ask_replay(session, keys, keys.join, JoinReply, timeout_s, stop,
                        payload=encode(JoinRequest(nonce)), what="actor id")
    if answer.nonce != nonce:
        raise ConfigError(f"the replay server answered another actor's join ({answer.nonce}): "
                          "start this actor again, or give it a fixed --actor-id")
    return answer.actor_id


def ask_replay(session, keys: Keys, key: str, message_type, timeout_s: float, stop=None,
               payload: bytes | None = None, what: str = "answer"):
    """Query the replay server's `key` until a `message_type` answer arrives; ConfigError if
    it speaks another schema, answers garbage or is silent for `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not stop:
        for reply in session.get(key, payload=payload, timeout=2.0):
            if reply.ok is not None:
                try:
                    return decode(reply.ok.payload.to_bytes(), message_type)
                except DecodeError as exc:
                    if exc.kind == "version":
                        raise ConfigError(f"the replay server speaks another wire schema: "
                                          f"{exc.detail}; run the same TPDEB version") from None
                    raise ConfigError(f"bad {what} from the replay server: {exc}") from None
        time.sleep(0.2)
    raise ConfigError(f"no replay server answered for run {keys.run_id!r} within {timeout_s:g} s"
                      " (wrong --run-id or --connect?)")
