"""`tpdeb-replay`: the replay server. Owns the dual replay and the rate limiter; serves the run
spec and sample requests; applies priority updates; acknowledges every fragment it ingests.

Zenoh callbacks only decode and enqueue; one loop thread owns the replay, so no locks guard it:
receive → validate → (dedupe, rate-limit) → insert → ack; sample requests wait in a queue until
the rate limiter allows them (or `sample_wait_s` passes, then they get a "not ready" reply).
"""

from __future__ import annotations

import queue
import sys
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field

import numpy as np
import zenoh

from protocol import (
    Ack,
    Control,
    DecodeError,
    Keys,
    Moments,
    PriorityUpdate,
    SampleReply,
    SampleRequest,
    Stats,
    Trajectory,
    decode,
    encode,
)
from services.config import ConfigError, resolve, to_toml
from services.envs import make_vector_env, space_dims
from services.service_config import ReplayServiceConfig
from services.wire import finite_values, message_to_fragment, run_spec
from services.zsession import RateLimitedLog, StopSignal, fail, open_for, say
from tpdeb_core.model import batch_moments, merge_moments
from tpdeb_core.replay import DualReplay

PROG = "tpdeb-replay"
_NO_MOMENTS = (0.0, 0.0, 0.0)


@dataclass
class ActorLedger:
    """Per-actor delivery accounting; `seen` de-duplicates resent fragments."""

    ingested: int = 0
    duplicates: int = 0
    dropped_busy: int = 0
    seen: set = field(default_factory=set)
    unacked: list = field(default_factory=list)


class ReplayServer:
    def __init__(self, config: ReplayServiceConfig, spec, session, stop: StopSignal):
        self.config, self.spec, self.session, self.stop = config, spec, session, stop
        self.keys = Keys(config.run_id)
        self.replay = DualReplay(
            config.prioritized_capacity, config.uniform_capacity_steps, zeta=config.zeta,
            alpha=config.alpha, seed=config.seed, priority_mode=config.priority_mode)
        self.limiter = config.rate_limiter()
        self.inbox: queue.Queue = queue.Queue()
        self.pending: deque[Trajectory] = deque()
        self.waiting: deque[tuple[float, object, SampleRequest]] = deque()
        self.ledgers: dict[int, ActorLedger] = defaultdict(ActorLedger)
        self.bad: dict[str, int] = defaultdict(int)
        self.log_bad = RateLimitedLog(PROG)
        self.inserted_steps = 0
        self.samples_served = 0
        self.priority_updates = 0
        self.obs_moments = self.ret_moments = _NO_MOMENTS
        self.spec_bytes = encode(spec)
        self._declare()

    def _declare(self) -> None:
        s, k = self.session, self.keys
        self.subscribers = [
            s.declare_subscriber(k.traj_all, lambda m: self.inbox.put(("traj", m))),
            s.declare_subscriber(k.priorities, lambda m: self.inbox.put(("prio", m))),
            s.declare_subscriber(k.control, lambda m: self.inbox.put(("control", m))),
        ]
        self.queryables = [
            s.declare_queryable(k.sample, lambda q: self.inbox.put(("sample", q))),
            s.declare_queryable(k.spec, self._answer_spec),
        ]
        self.ack_publishers: dict[int, object] = {}
        self.stats_publisher = s.declare_publisher(k.stats("replay", 0))
        self.token = s.liveliness().declare_token(k.alive("replay", 0))

    def _answer_spec(self, query) -> None:
        query.reply(self.keys.spec, self.spec_bytes)

    # -- the loop
    def run(self) -> None:
        last_stats = 0.0
        while not self.stop:
            try:
                kind, item = self.inbox.get(timeout=0.05)
                self._handle(kind, item)
                while True:  # drain what arrived meanwhile before acting on it
                    kind, item = self.inbox.get_nowait()
                    self._handle(kind, item)
            except queue.Empty:
                pass
            self._ingest_pending()
            self._serve_waiting()
            self._flush_acks()
            now = time.monotonic()
            if now - last_stats >= self.config.stats_interval_s:
                self.publish_stats()
                last_stats = now

    def _handle(self, kind: str, item) -> None:
        if kind == "sample":
            self._take_sample_request(item)
            return
        payload = item.payload.to_bytes()
        sender = str(item.key_expr)
        limit = self.config.max_message_bytes
        try:
            if kind == "traj":
                self._receive_fragment(decode(payload, Trajectory, self.spec, limit), sender)
            elif kind == "prio":
                self._apply_priorities(decode(payload, PriorityUpdate, self.spec, limit))
            elif kind == "control" and decode(payload, Control, max_bytes=limit).command == "stop":
                self.stop.set("stop message")
        except DecodeError as exc:
            self.reject(exc.kind, sender, exc.detail)

    def reject(self, kind: str, sender: str, detail: str) -> None:
        self.bad[kind] += 1
        self.log_bad(kind, f"dropped a bad message from {sender} ({kind}): {detail}")

    def _receive_fragment(self, message: Trajectory, sender: str) -> None:
        if self.keys.actor_id_of(sender) != message.actor_id:
            self.reject("sender", sender, f"carries actor_id {message.actor_id}")
            return
        ledger = self.ledgers[message.actor_id]
        if message.seq in ledger.seen:
            ledger.duplicates += 1
            ledger.unacked.append(message.seq)  # its first ack may have been lost: ack again
            return
        if len(self.pending) >= self.config.max_pending_fragments:
            ledger.dropped_busy += 1  # not acknowledged: the actor resends it later
            return
        ledger.seen.add(message.seq)
        self.pending.append(message)

    def _ingest_pending(self) -> None:
        while self.pending and self.limiter.can_insert(self.spec.fragment_len):
            self._insert(self.pending.popleft())

    def _insert(self, message: Trajectory) -> None:
        fragment = message_to_fragment(message)
        priority = fragment.initial_priority(self.spec.priority_mode, self.spec.priority_kappa,
                                             self.spec.gamma, message.reward_scale)
        # The decoded message is the item: it goes back out in sample replies as it came in.
        self.replay.insert(message, priority, fragment.num_steps)
        self.limiter.on_insert(fragment.num_steps)
        self.inserted_steps += fragment.num_steps
        # Normaliser moments: every ingested step counted exactly once, shipped to the learner.
        self.obs_moments = merge_moments(self.obs_moments, batch_moments(fragment.obs[:-1]))
        self.ret_moments = merge_moments(self.ret_moments, batch_moments(fragment.disc_returns))
        ledger = self.ledgers[message.actor_id]
        ledger.ingested += 1
        ledger.unacked.append(message.seq)

    def _flush_acks(self) -> None:
        for actor_id, ledger in self.ledgers.items():
            if not ledger.unacked:
                continue
            publisher = self.ack_publishers.get(actor_id)
            if publisher is None:
                # Acks are small and unblock actors: ahead of bulk data on a shared link.
                publisher = self.session.declare_publisher(
                    self.keys.ack(actor_id), priority=zenoh.Priority.DATA_HIGH, express=True)
                self.ack_publishers[actor_id] = publisher
            publisher.put(encode(Ack(actor_id=actor_id, seqs=np.array(ledger.unacked, np.int64),
                                     ingested=ledger.ingested)))
            ledger.unacked = []

    # -- sampling
    def _take_sample_request(self, query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        try:
            request = decode(payload, SampleRequest)
        except DecodeError as exc:
            self.reject(exc.kind, "a sample request", exc.detail)
            query.drop()
            return
        self.waiting.append((time.monotonic(), query, request))

    def _serve_waiting(self) -> None:
        batch_steps = self.config.batch_fragments * self.spec.fragment_len
        while self.waiting:
            since, query, request = self.waiting[0]
            steps = request.batch_size * self.spec.fragment_len
            if steps > batch_steps * 4:
                self._reply(query, self._not_ready(request, f"batch of {request.batch_size} "
                                                   "fragments is larger than this run allows"))
            elif self.limiter.can_sample(steps) and len(self.replay):
                self._reply(query, self._sample(request, steps))
            elif time.monotonic() - since > self.config.sample_wait_s:
                self._reply(query, self._not_ready(request, self._why_not_ready()))
            else:
                return
            self.waiting.popleft()

    def _why_not_ready(self) -> str:
        stats = self.limiter.stats()
        return (f"rate limiter: {self.inserted_steps} steps inserted, "
                f"{stats.get('sampled_steps', 0)} sampled")

    def _sample(self, request: SampleRequest, steps: int) -> SampleReply:
        sample = self.replay.sample(request.batch_size, request.beta)
        self.limiter.on_sample(steps)
        self.samples_served += 1
        reply = SampleReply(
            request_id=request.request_id, ready=True, keys=sample.keys.astype(np.int64),
            weights=sample.weights.astype(np.float32),
            from_prioritized=sample.from_prioritized.astype(bool),
            step_index=sample.step_index.astype(np.int64),
            fragments=list(sample.items),
            inserted_steps=self.inserted_steps,
            obs_moments=Moments(*self.obs_moments) if self.obs_moments[0] else None,
            ret_moments=Moments(*self.ret_moments) if self.ret_moments[0] else None)
        self.obs_moments = self.ret_moments = _NO_MOMENTS
        return reply

    def _not_ready(self, request: SampleRequest, reason: str) -> SampleReply:
        empty = np.zeros(0, np.int64)
        return SampleReply(
            request_id=request.request_id, ready=False, keys=empty,
            weights=np.zeros(0, np.float32), from_prioritized=np.zeros(0, bool),
            step_index=empty, fragments=[], inserted_steps=self.inserted_steps,
            obs_moments=None, ret_moments=None, reason=reason)

    def _reply(self, query, reply: SampleReply) -> None:
        try:
            query.reply(self.keys.sample, encode(reply))
        finally:
            query.drop()

    def _apply_priorities(self, update: PriorityUpdate) -> None:
        priorities = (list(update.priorities) if update.priorities.ndim == 2
                      else update.priorities)
        try:
            self.priority_updates += self.replay.update_priorities(update.keys, priorities)
        except ValueError as exc:
            self.reject("value", "a priority update", str(exc))

    # -- reporting
    def stats(self) -> dict:
        replay = {k: v for k, v in self.replay.stats().items() if isinstance(v, (int, float))}
        limiter = self.limiter.stats()
        values = {**replay, "inserted_steps": self.inserted_steps,
                  "samples_served": self.samples_served,
                  "priority_updates": self.priority_updates,
                  "pending_fragments": len(self.pending),
                  "waiting_requests": len(self.waiting),
                  "samples_per_insert": limiter.get("samples_per_insert_achieved", 0.0),
                  "bad_messages": sum(self.bad.values())}
        values.update({f"bad/{kind}": n for kind, n in self.bad.items()})
        for actor_id, ledger in self.ledgers.items():
            values[f"actor{actor_id}/ingested"] = ledger.ingested
            values[f"actor{actor_id}/duplicates"] = ledger.duplicates
            values[f"actor{actor_id}/dropped_busy"] = ledger.dropped_busy
        return values

    def publish_stats(self) -> None:
        self.stats_publisher.put(encode(Stats(
            role="replay", ident="0", values=finite_values(self.stats()),
            episode_returns=np.zeros(0), episode_lengths=np.zeros(0, np.int64))))

    def close(self) -> None:
        for query in (q for _, q, _ in self.waiting):
            query.drop()
        self.waiting.clear()
        self.token.undeclare()


def main(argv: list[str] | None = None) -> int:
    try:
        config = resolve(ReplayServiceConfig, argv, PROG,
                         "TPDEB replay server: dual prioritized/uniform replay over Zenoh.")
        envs = make_vector_env(config.env_id, 1)
        spec = run_spec(config, *space_dims(envs))
        envs.close()
        session = open_for(config, "router")
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    server = ReplayServer(config, spec, session, stop)
    if config.run_dir:
        server_dir = config.default_run_dir()
        server_dir.mkdir(parents=True, exist_ok=True)
        (server_dir / "replay.toml").write_text(to_toml(config))
    say(PROG, f"run {config.run_id}: serving {spec.env_id} (obs {spec.obs_dim}, act "
              f"{spec.act_dim}, T {spec.fragment_len}) on {', '.join(config.listen)}")
    try:
        server.run()
    finally:
        server.close()
        session.close()
    say(PROG, f"stopped ({stop.reason}); {server.inserted_steps:,} steps ingested, "
              f"{sum(server.bad.values())} bad messages dropped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
