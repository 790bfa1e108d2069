"""`tpdeb-actor`: steps a vector env with the latest parameters and sends fragments up.

Delivery: every fragment gets a per-actor sequence number and stays in the outbox until the
replay server acknowledges it; unacknowledged ones are resent after `resend_after_s` (the
replay de-duplicates). A full outbox makes the actor wait: back-pressure instead of loss.
New parameters arrive through a long poll (one request in flight, answered when a newer
version exists) that only keeps the latest bytes; the loop loads them between env steps, so the
actor never stalls on the network. The actor asks for them once per fragment, when its
fragments complete (IMPALA's actors refresh at the start of each unroll): a learner that
updates every few milliseconds would otherwise have every update shipped to and decoded by
every actor, and the parameter traffic (the learner's encoding, the router, the actors'
decoding) would cost more CPU than the acting it steers.
"""

from __future__ import annotations

import logging
import secrets
import sys
import threading
import time

import numpy as np
import zenoh

from tpdeb.protocol import (
    Ack,
    DecodeError,
    Keys,
    Params,
    Stats,
    decode,
    encode,
)
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import ActorServiceConfig
from tpdeb.services.envs import make_vector_env, space_dims
from tpdeb.services.logs import rate_limited
from tpdeb.services.net.session import (
    close_session,
    declare_publisher,
    fetch_spec,
    join_run,
    open_for,
)
from tpdeb.services.net.wire import policy_from_params, spec_mismatch
from tpdeb.services.process import StopSignal, actor_id_file, configure, fail, obey_control
from tpdeb.services.seeding import seed_everything
from tpdeb.tpdeb_core.fragments import Collector
from tpdeb.tpdeb_core.shards import shard_of

PROG = "tpdeb-actor"
log = logging.getLogger(PROG)
PARAMS_POLL_S = 10.0


class Outbox:
    """Sent-but-unacknowledged fragments by sequence number (thread-safe)."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._items: dict[int, list] = {}  # seq -> [payload, last_sent]
        self._cond = threading.Condition()
        self.acked = 0

    def add(self, seq: int, payload: bytes, now: float) -> None:
        with self._cond:
            self._items[seq] = [payload, now]

    def ack(self, seqs) -> None:
        with self._cond:
            for seq in seqs:
                if self._items.pop(int(seq), None) is not None:
                    self.acked += 1
            self._cond.notify_all()

    def wait_for_room(self, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self._items) < self.capacity, timeout_s)

    def make_all_due(self) -> None:
        """Resend everything at the next check (the replay server came back)."""
        with self._cond:
            for item in self._items.values():
                item[1] = -1e18

    def due(self, now: float, after_s: float) -> list[tuple[int, bytes]]:
        """Entries unacknowledged for `after_s`; their clocks restart."""
        with self._cond:
            out = [(seq, item[0]) for seq, item in self._items.items() if now - item[1] > after_s]
            for seq, _ in out:
                self._items[seq][1] = now
            return out

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class ActorService:
    def __init__(self, config: ActorServiceConfig, spec, envs, session, stop: StopSignal):
        self.config, self.spec, self.envs, self.session, self.stop = (
            config, spec, envs, session, stop)
        self.log_bad = rate_limited(log)
        self.collector: Collector | None = None  # made when the first parameters arrive
        self.outbox = Outbox(config.outbox_fragments)
        # A new number per process run: the replay de-duplicates by (actor, incarnation, seq),
        # so a restarted actor, whose seqs start at 0 again, is not taken for a resender.
        self.incarnation = secrets.randbits(62)
        self.sent = self.resent = 0
        self.last_stats, self.last_steps = 0.0, 0  # when stats last went out, at what count
        self.latest_params: bytes | None = None
        self.params_lock = threading.Lock()
        self.params_wanted = threading.Event()
        self.puller = threading.Thread(target=self._pull_params, daemon=True, name="params")
        self.params_cancel = zenoh.CancellationToken()
        self.actor_id = int(config.actor_id)  # `auto` is resolved before (join_run)
        # its replay shard's keys for fragments and acks, the run's for the rest
        self.shard = shard_of(self.actor_id, spec.replay_shards)
        self.keys = Keys(config.run_id, self.shard if spec.replay_shards > 1 else None)
        s, k = session, self.keys
        # BLOCK: on a congested link a fragment waits for room instead of being dropped (the
        # outbox bounds how much can wait; wait_before_close is set far above that).
        self.traj_publisher = declare_publisher(s, "traj", k.traj(self.actor_id))
        self.stats_publisher = declare_publisher(s, "stats", k.stats("actor", self.actor_id))
        self.subscribers = [
            s.declare_subscriber(k.ack(self.actor_id), self._on_ack),
            s.declare_subscriber(k.control, self._on_control),
        ]
        self.token = s.liveliness().declare_token(k.alive("actor", self.actor_id))
        # The replay server (re)appearing — a restart, or this actor reconnecting after a
        # partition — means acks may have been lost: resend the outbox at once.
        self.replay_watch = s.liveliness().declare_subscriber(
            k.alive("replay", self.shard), self._on_replay_alive, history=True)

    # -- callbacks (Zenoh threads): store, never block
    def _on_params(self, sample) -> None:
        with self.params_lock:
            self.latest_params = sample.payload.to_bytes()

    def _on_ack(self, sample) -> None:
        try:
            ack = decode(sample.payload.to_bytes(), Ack)
        except DecodeError as exc:
            self.log_bad(exc.kind, f"dropped a bad ack ({exc})")
            return
        if ack.incarnation == self.incarnation:  # not acks meant for an earlier run of ours
            self.outbox.ack(ack.seqs.tolist())

    def _on_replay_alive(self, sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self.outbox.make_all_due()

    def _on_control(self, sample) -> None:
        obey_control(sample, self.stop, self.log_bad)

    # -- parameters
    def wait_for_params(self) -> None:
        """Block until the learner's first parameters arrive."""
        deadline = time.monotonic() + self.config.connect_timeout_s
        while not self.stop and time.monotonic() < deadline:
            if self.latest_params is None:
                for reply in self.session.get(self.keys.params_latest, timeout=2.0):
                    if reply.ok is not None:
                        self._on_params(reply.ok)
            if self.refresh_params():
                return
            self.stop.wait(0.2)
        if not self.stop:
            raise ConfigError(f"no parameters from a learner of run {self.config.run_id!r} "
                              f"within {self.config.connect_timeout_s:g} s (is tpdeb-learner "
                              "running?)")

    def ask_params(self) -> bool:
        """One query for a version newer than ours, now (the long poll's, in the caller's
        thread); what arrives is loaded at the next `refresh_params`."""
        selector = f"{self.keys.params_latest}?after={self.policy_version}"
        got = False
        for reply in self.session.get(selector, timeout=PARAMS_POLL_S,
                                      cancellation_token=self.params_cancel):
            if reply.ok is not None:
                self._on_params(reply.ok)
                got = True
        return got

    def _pull_params(self) -> None:
        """Long-poll the learner for the next version: one request in flight, answered as soon
        as a version newer than ours exists, asked again when the loop wants newer ones (at its
        fragment boundaries). On a thin link only parameters that will be used cross it."""
        while not self.stop:
            if not self.params_wanted.wait(0.5):
                continue
            self.params_wanted.clear()
            try:
                got = self.ask_params()
            except zenoh.ZError:
                return  # the session is closing
            if not got:
                # No newer version in time, or no learner at all (then the query returns at
                # once): ask again, but not in a busy loop while the learner restarts.
                self.stop.wait(0.2)
                self.params_wanted.set()

    def refresh_params(self) -> bool:
        with self.params_lock:
            data, self.latest_params = self.latest_params, None
        if data is None:
            return False
        try:
            message = decode(data, Params, max_bytes=self.config.max_message_bytes)
            if message.version < self.policy_version:
                return False  # an older publication overtaken by a newer one
            policy = policy_from_params(message, self.spec)
        except DecodeError as exc:
            self.log_bad(exc.kind, f"dropped bad parameters ({exc})")
            return False
        if self.collector is None:
            cfg, spec = self.config, self.spec
            self.collector = Collector(
                self.envs, policy, spec.fragment_len, spec.gamma, spec.action_low,
                spec.action_high, seed=cfg.seed + 1000 * self.actor_id, actor_id=self.actor_id,
                incarnation=self.incarnation, policy_version=message.version)
        else:
            self.collector.set_policy(policy, message.version)
        return True

    @property
    def policy_version(self) -> int:
        return -1 if self.collector is None else self.collector.policy_version

    # -- the loop
    def run(self) -> None:
        cfg = self.config
        self.wait_for_params()
        if self.collector is None:  # stopped first: the run ended (or was stopped) before it
            return
        self.params_wanted.set()
        self.puller.start()
        log.info(f"actor {self.actor_id}: {cfg.num_envs} × {self.spec.env_id}, parameters "
                  f"v{self.collector.policy_version}")
        last_check = self.last_stats = time.monotonic()
        while not self.stop:
            self.refresh_params()
            fragments = self.collector.step()
            if fragments:  # a fragment boundary: ask for the newest version for the next ones
                self.params_wanted.set()
            for fragment in fragments:
                self.send(fragment)
            now = time.monotonic()
            if now - last_check >= 0.5:
                self.resend_due(now)
                last_check = now
            self.stats_due(now)

    def send(self, fragment) -> None:
        while not self.stop and not self.outbox.wait_for_room(0.05):
            # back-pressure: wait for acks, resend the lost, keep the parameters fresh, and
            # keep publishing stats (a held-back actor is not a hung one)
            now = time.monotonic()
            self.resend_due(now)
            self.refresh_params()
            self.stats_due(now)
        self.send_now(fragment)

    def stats_due(self, now: float) -> None:
        if now - self.last_stats >= self.config.stats_interval_s:
            steps = self.collector.env_steps
            self.publish_stats((steps - self.last_steps) / (now - self.last_stats))
            self.last_stats, self.last_steps = now, steps

    def send_now(self, fragment) -> None:
        """Encode, keep in the outbox until acknowledged, put (the caller made room)."""
        payload = encode(fragment, self.config.trajectory_compression)
        self.outbox.add(fragment.seq, payload, time.monotonic())
        self.traj_publisher.put(payload)
        self.sent += 1

    def resend_due(self, now: float) -> None:
        for _, payload in self.outbox.due(now, self.config.resend_after_s):
            self.traj_publisher.put(payload)
            self.resent += 1

    def publish_stats(self, sps: float) -> None:
        episodes = self.collector.episodes
        self.collector.episodes = []
        self.stats_publisher.put(encode(Stats(
            role="actor", ident=str(self.actor_id),
            values={"env_steps": self.collector.env_steps, "sps": sps,
                    "param_version": self.collector.policy_version, "sent": self.sent,
                    "acked": self.outbox.acked, "resent": self.resent,
                    "outbox": len(self.outbox), "incarnation": f"{self.incarnation:x}"},
            episode_returns=np.array([r for r, _ in episodes], np.float64),
            episode_lengths=np.array([n for _, n in episodes], np.int64))))

    def close(self) -> None:
        # A thread still inside a Zenoh query when the interpreter exits aborts the process:
        # cancel the long poll and wait for it first.
        self.stop.set(self.stop.reason or "closing")
        self.params_cancel.cancel()
        if self.puller.is_alive():
            self.puller.join(timeout=5)
        self.token.undeclare()
        self.envs.close()


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(ActorServiceConfig, argv, PROG,
                           "TPDEB actor: steps environments, sends fragments to the replay server.")
        # A bad env id, module or keyword argument fails here, in one line.
        envs = make_vector_env(config.env_id, config.num_envs, config.env_kwargs)
        obs_dim, act_dim, _, _ = space_dims(envs)
        session = open_for(config)
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    service = None
    try:
        keys = Keys(config.run_id)
        spec = fetch_spec(session, keys, config.connect_timeout_s, stop)
        problem = spec_mismatch(spec, config.env_id, obs_dim, act_dim, config.env_kwargs)
        if problem:
            raise ConfigError(f"run spec mismatch: {problem}")
        if config.actor_id == "auto":
            config.actor_id = str(join_run(session, keys, config.connect_timeout_s, stop))
            actor_id_file(config.run_id).write_text(config.actor_id)
            log.info(f"actor id {config.actor_id} from the replay server (--actor-id auto)")
        seed_everything(config.seed + 1000 * int(config.actor_id))
        service = ActorService(config, spec, envs, session, stop)
        service.run()
    except ConfigError as exc:
        if stop:  # stopped while waiting for the run: not an error
            log.info(f"actor {config.actor_id} stopped ({stop.reason}) before it started")
            return 0
        return fail(PROG, exc)
    finally:
        if service is not None:
            service.close()
        close_session(session, PROG)
    steps = service.collector.env_steps if service.collector is not None else 0
    log.info(f"actor {config.actor_id} stopped ({stop.reason}): {steps:,} "
              f"steps, {service.sent} fragments sent, {service.outbox.acked} acknowledged, "
              f"{service.resent} resent")
    return 0


if __name__ == "__main__":
    sys.exit(main())
