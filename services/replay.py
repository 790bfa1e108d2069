"""`tpdeb-replay`: the replay server. Owns the dual replay and the rate limiter; serves the run
spec and sample requests; applies priority updates; acknowledges every fragment it ingests.

Zenoh callbacks only decode and enqueue; one loop thread owns the replay, so no locks guard it:
receive → validate → (dedupe, rate-limit) → insert → log → fsync → ack; sample requests wait in
a queue until the rate limiter allows them (or `sample_wait_s` passes, then they get a "not
ready" reply). With `persist` on, a fragment is acknowledged only once it is in the write-ahead
log on disk, and snapshots of the whole state are written in the background
(services/store/persistence.py): a restarted server restores everything it ever acknowledged.
A disk that refuses the log (full) stops acknowledging and taking in fragments, not the server:
it says so once, keeps serving samples, and goes on when the log takes writes again.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import queue
import shutil
import sys
import threading
import time
from collections import defaultdict, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tpdeb.protocol import (
    Ack,
    Control,
    DecodeError,
    JoinReply,
    JoinRequest,
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
from tpdeb.services.config import ConfigError, to_toml
from tpdeb.services.config.service import ReplayServiceConfig
from tpdeb.services.envs import make_vector_env, space_dims
from tpdeb.services.logs import rate_limited
from tpdeb.services.net.session import close_session, declare_publisher, open_for
from tpdeb.services.net.wire import finite_values, run_spec
from tpdeb.services.process import StopSignal, configure, fail
from tpdeb.services.store.persistence import Incompatible, ReplayPersistence
from tpdeb.tpdeb_core.fragments import Fragment, initial_priority, stack_fragments
from tpdeb.tpdeb_core.moments import batch_moments, merge_moments

PROG = "tpdeb-replay"
log = logging.getLogger(PROG)
_NO_MOMENTS = (0.0, 0.0, 0.0)


class SeqWindow:
    """The sequence numbers seen from one actor incarnation, in O(fragments in flight) memory:
    every seq below `low`, plus the set `above` (actors send in order, so gaps close fast)."""

    def __init__(self, low: int = 0, above=()):
        self.low, self.above = low, set(above)

    def __contains__(self, seq: int) -> bool:
        return seq < self.low or seq in self.above

    def add(self, seq: int) -> None:
        self.above.add(seq)
        while self.low in self.above:
            self.above.remove(self.low)
            self.low += 1

    def state(self) -> tuple[int, list[int]]:
        return self.low, sorted(self.above)


SNAPSHOT_FORMAT = 2  # of what snapshot() saves (2: msgpack state); a restore refuses any other
PENALTY_S, PENALTY_MAX_S = 0.1, 30.0  # a bad message's sender is ignored this long, doubling
MAX_HANDLED_PER_PASS = 512  # inbox items one loop pass takes before it ingests, samples, acks
DISK_RETRY_S = 5.0  # while the log cannot be written, how often it is tried again
# Per actor id, the incarnations whose windows are kept: a dead one's is a few ints (its gaps
# are at most its outbox), so a thousand restarts cost little and a late resend from any of
# them is still recognised, and every acknowledged fragment stays accountable; past this the
# oldest is forgotten.
MAX_INCARNATIONS = 1024


# The fields of a saved state and their types: checked before any is used (a snapshot is read
# from a run dir that may come from elsewhere, like a message from the wire).
_SAVED = {"format": int, "env_id": str, "obs_dim": int, "act_dim": int, "replay": dict,
          "limiter": dict, "inserted_steps": int, "samples_served": int,
          "priority_updates": int, "ledgers": dict, "items": list}
_SAVED_LEDGER = {"ingested": int, "duplicates": int, "dropped_busy": int, "windows": dict}


def _check_fields(where: str, value, fields: dict) -> None:
    if not isinstance(value, dict):
        raise ConfigError(f"the replay snapshot's {where} is a {type(value).__name__}, not a map")
    for name, kind in fields.items():
        if name not in value:
            raise ConfigError(f"the replay snapshot's {where} lacks {name!r}")
        if not isinstance(value[name], kind) or isinstance(value[name], bool) and kind is int:
            raise ConfigError(f"the replay snapshot's {where}.{name} is "
                              f"{type(value[name]).__name__}, not {kind.__name__}")


def _check_saved(saved) -> None:
    """Refuse a decoded snapshot state whose fields are missing or of the wrong type."""
    _check_fields("state", saved, _SAVED)
    for actor_id, ledger in saved["ledgers"].items():
        if not isinstance(actor_id, int):
            raise ConfigError(f"the replay snapshot has a ledger for actor {actor_id!r}")
        _check_fields(f"ledger of actor {actor_id}", ledger, _SAVED_LEDGER)
        for incarnation, window in ledger["windows"].items():
            if not (isinstance(incarnation, int) and isinstance(window, list)
                    and len(window) == 2 and isinstance(window[0], int)
                    and isinstance(window[1], list)
                    and all(isinstance(seq, int) for seq in window[1])):
                raise ConfigError(f"the replay snapshot's window {incarnation!r} of actor "
                                  f"{actor_id} is not [low, [seq, …]]")


@dataclass
class ActorLedger:
    """Per-actor delivery accounting. `windows` (by incarnation) holds what was ingested, so a
    resent fragment is acknowledged again but stored once; `pending` what was received but not
    yet ingested (acknowledged only once it is)."""

    ingested: int = 0
    duplicates: int = 0
    dropped_busy: int = 0
    windows: dict = field(default_factory=dict)  # incarnation -> SeqWindow, oldest first
    pending: set = field(default_factory=set)  # (incarnation, seq)
    unacked: dict = field(default_factory=lambda: defaultdict(list))  # incarnation -> [seq]

    def window(self, incarnation: int) -> SeqWindow:
        if incarnation not in self.windows:
            self.windows[incarnation] = SeqWindow()
            while len(self.windows) > MAX_INCARNATIONS:
                del self.windows[next(iter(self.windows))]
        return self.windows[incarnation]

    def state(self) -> dict:
        return {"ingested": self.ingested, "duplicates": self.duplicates,
                "dropped_busy": self.dropped_busy,
                "windows": {inc: w.state() for inc, w in self.windows.items()}}

    @classmethod
    def from_state(cls, state: dict) -> ActorLedger:
        ledger = cls(state["ingested"], state["duplicates"], state["dropped_busy"])
        ledger.windows = {inc: SeqWindow(low, above)
                          for inc, (low, above) in state["windows"].items()}
        return ledger


class ReplayServer:
    def __init__(self, config: ReplayServiceConfig, spec, session, stop: StopSignal):
        self.config, self.spec, self.session, self.stop = config, spec, session, stop
        self.shard = config.shard
        self.keys = Keys(config.run_id, self.shard if config.replay_shards > 1 else None)
        part = config.shard_part(self.shard)  # 1/K of the capacities, its own seed
        self.replay = part.make_replay()
        self.limiter = part.rate_limiter()
        self.inbox: queue.Queue = queue.Queue()
        self.pending: deque[tuple[Fragment, bytes]] = deque()
        self.waiting: deque[tuple[float, object, SampleRequest]] = deque()
        self.ledgers: dict[int, ActorLedger] = defaultdict(ActorLedger)
        self.bad: dict[str, int] = defaultdict(int)
        self.queued: dict[str, int] = defaultdict(int)  # sender -> its messages in the inbox
        self.queued_lock = threading.Lock()
        self.flooded = 0  # dropped undecoded: their sender was penalised or had too many waiting
        self.strikes: dict[str, int] = {}  # sender -> bad messages since its last good one
        self.penalty: dict[str, float] = {}  # sender -> until when its messages are dropped
        self.log_bad = rate_limited(log)
        self.inserted_steps = 0
        self.samples_served = 0
        self.priority_updates = 0
        self.obs_moments = self.ret_moments = _NO_MOMENTS
        self.spec_bytes = encode(spec)
        self.persistence: ReplayPersistence | None = None
        self.restored = ""  # what restore() found, for the start-up line
        self.last_snapshot = time.monotonic()
        self.last_stats = 0.0
        self.disk_full, self.disk_retry_at = False, 0.0
        self._declare()

    def _declare(self) -> None:
        s, k = self.session, self.keys
        self.subscribers = [
            s.declare_subscriber(k.traj_all, self._arrived),
            s.declare_subscriber(k.priorities, lambda m: self.inbox.put(("prio", m))),
            s.declare_subscriber(k.control, lambda m: self.inbox.put(("control", m))),
        ]
        self.queryables = [
            s.declare_queryable(k.sample, lambda q: self.inbox.put(("sample", q))),
            s.declare_queryable(k.spec, self._answer_spec),  # every shard serves the one spec
        ]
        if self.shard == 0:  # one shard hands out the actor ids of the whole run
            self.queryables.append(
                s.declare_queryable(k.join, lambda q: self.inbox.put(("join", q))))
        self.joined: dict[int, int] = {}  # nonce → the actor id this process handed out
        self.ack_publishers: dict[int, object] = {}
        self.stats_publisher = declare_publisher(s, "stats", k.stats("replay", self.shard))
        self.token = s.liveliness().declare_token(k.alive("replay", self.shard))

    def _arrived(self, sample) -> None:
        """A trajectory message (on a Zenoh thread): queued, unless its sender is serving a
        penalty for bad messages or already has `max_queued_per_sender` waiting: then dropped
        here and counted."""
        sender, limit = str(sample.key_expr), self.config.max_queued_per_sender
        with self.queued_lock:
            penalised = self.penalty.get(sender, 0.0) > time.monotonic()
            full = not penalised and self.queued[sender] >= limit
            if penalised or full:
                self.flooded += 1
            else:
                self.queued[sender] += 1
        if full:
            self.log_bad("flood", f"dropped a message from {sender}: {limit} of its messages "
                                  "are already waiting (max_queued_per_sender)")
        if not (penalised or full):
            self.inbox.put(("traj", sample))

    def _answer_spec(self, query) -> None:
        query.reply(self.keys.spec, self.spec_bytes)

    # -- the loop
    def run(self) -> None:
        while not self.stop:
            self.poll(0.05)

    def poll(self, timeout_s: float) -> None:
        """One pass of the loop: take what arrived (waiting up to `timeout_s` for the first
        item), ingest what the rate limiter allows, serve the sample requests it allows, make
        the log durable, then acknowledge; stats and snapshots when they are due."""
        try:
            kind, item = self.inbox.get(timeout=timeout_s) if timeout_s > 0 else \
                self.inbox.get_nowait()
            self._handle(kind, item)
            for _ in range(MAX_HANDLED_PER_PASS):  # what arrived meanwhile, before acting on it
                kind, item = self.inbox.get_nowait()
                self._handle(kind, item)
        except queue.Empty:
            pass
        if not self.disk_full:
            self._ingest_pending()
        self._serve_waiting()
        if self.persistence is None or self._durable():
            self._flush_acks()  # with the log on: the fragments acknowledged are on disk
        now = time.monotonic()
        if now - self.last_stats >= self.config.stats_interval_s:
            self.publish_stats()
            self.last_stats = now
        interval = self.config.snapshot_interval_s
        if (self.persistence is not None and not self.disk_full and interval
                and now - self.last_snapshot >= interval):
            self.snapshot()

    def _handle(self, kind: str, item) -> None:
        if kind == "sample":
            self._take_sample_request(item)
            return
        if kind == "join":
            self._answer_join(item)
            return
        payload = item.payload.to_bytes()
        sender = str(item.key_expr)
        if kind == "traj":
            with self.queued_lock:
                self.queued[sender] -= 1
                if self.penalty.get(sender, 0.0) > time.monotonic():
                    self.flooded += 1  # queued before its sender's bad message: not decoded
                    return
        limit = self.config.max_message_bytes
        try:
            if kind == "traj":
                self._receive_fragment(decode(payload, Trajectory, self.spec, limit), payload,
                                       sender)
            elif kind == "prio":
                self._apply_priorities(decode(payload, PriorityUpdate, self.spec, limit))
            elif kind == "control" and decode(payload, Control, max_bytes=limit).command == "stop":
                self.stop.set("stop message")
        except DecodeError as exc:
            self.reject(exc.kind, sender, exc.detail)

    def reject(self, kind: str, sender: str, detail: str) -> None:
        """A bad message: counted, said at a limited rate, and its sender's next messages are
        dropped on arrival for a while (PENALTY_S, doubling per bad message up to
        PENALTY_MAX_S, forgiven by its next good fragment), so garbage never queues ahead of
        the others'."""
        self.bad[kind] += 1
        self.log_bad(kind, f"dropped a bad message from {sender} ({kind}): {detail}")
        with self.queued_lock:
            strikes = self.strikes[sender] = self.strikes.get(sender, 0) + 1
            self.penalty[sender] = time.monotonic() + min(PENALTY_MAX_S,
                                                          PENALTY_S * 2 ** (strikes - 1))

    def _receive_fragment(self, message: Fragment, payload: bytes, sender: str) -> None:
        if self.keys.actor_id_of(sender) != message.actor_id:
            self.reject("sender", sender, f"carries actor_id {message.actor_id}")
            return
        ledger = self.ledgers[message.actor_id]
        ident = (message.incarnation, message.seq)
        if message.seq in ledger.window(message.incarnation):
            ledger.duplicates += 1
            # its first ack may have been lost: ack again (it is on disk already)
            ledger.unacked[message.incarnation].append(message.seq)
            return
        if ident in ledger.pending:
            ledger.duplicates += 1  # acknowledged once it is ingested
            return
        if len(self.pending) >= self.config.max_pending_fragments:
            ledger.dropped_busy += 1  # not acknowledged: the actor resends it later
            return
        ledger.pending.add(ident)
        self.pending.append((message, payload))
        if sender in self.strikes:
            with self.queued_lock:
                self.strikes.pop(sender, None)

    def _ingest_pending(self) -> None:
        while self.pending and self.limiter.can_insert(self.spec.fragment_len):
            message, payload = self.pending.popleft()
            self.ledgers[message.actor_id].pending.discard((message.incarnation, message.seq))
            self._insert(message)
            if self.persistence is not None:
                self.persistence.log(payload)

    def _insert(self, fragment: Fragment, replaying: bool = False) -> None:
        spec = self.spec
        priority = initial_priority(fragment, spec.priority_mode, spec.priority_kappa, spec.gamma)
        # The decoded fragment is the item: it goes back out in sample replies as it came in.
        self.replay.insert(fragment, priority, fragment.num_steps)
        if replaying:  # its samples were not logged: counted as the ratio let them be taken
            self.limiter.on_restored_insert(fragment.num_steps)
        else:
            self.limiter.on_insert(fragment.num_steps)
        self.inserted_steps += fragment.num_steps
        ledger = self.ledgers[fragment.actor_id]
        ledger.ingested += 1
        ledger.window(fragment.incarnation).add(fragment.seq)
        if replaying:
            return  # restored from the log: its moments were shipped, its ack was sent
        # Normaliser moments: every ingested step counted exactly once, shipped to the learner.
        self.obs_moments = merge_moments(self.obs_moments, batch_moments(fragment.obs[:-1]))
        self.ret_moments = merge_moments(self.ret_moments, batch_moments(fragment.disc_returns))
        ledger.unacked[fragment.incarnation].append(fragment.seq)

    def _durable(self) -> bool:
        """Sync the log; True when every logged fragment is on disk. A refused write or fsync
        (a full disk) is said once with the path: until the log takes writes again (tried every
        DISK_RETRY_S) nothing is acknowledged or taken in, so actors hold their fragments and
        resend them, while samples go on being served from memory."""
        now = time.monotonic()
        if self.disk_full and now < self.disk_retry_at:
            return False
        try:
            self.persistence.sync()
        except OSError as exc:
            if not self.disk_full:
                log.warning(f"the write-ahead log cannot be written: {self.persistence.dir}: "
                            f"{exc.strerror or exc}; no fragment is acknowledged or taken in "
                            f"until it can (samples go on), trying again every "
                            f"{DISK_RETRY_S:g} s")
            self.disk_full, self.disk_retry_at = True, now + DISK_RETRY_S
            return False
        if self.disk_full:
            log.info(f"the write-ahead log takes writes again: {self.persistence.dir}")
            self.disk_full = False
        return True

    def _flush_acks(self) -> None:
        for actor_id, ledger in self.ledgers.items():
            if not ledger.unacked:
                continue
            publisher = self.ack_publishers.get(actor_id)
            if publisher is None:
                publisher = declare_publisher(self.session, "ack", self.keys.ack(actor_id))
                self.ack_publishers[actor_id] = publisher
            for incarnation, seqs in ledger.unacked.items():
                publisher.put(encode(Ack(actor_id=actor_id, seqs=np.array(seqs, np.int64),
                                         incarnation=incarnation)))
            ledger.unacked.clear()

    # -- durability
    def enable_persistence(self, directory: Path) -> None:
        """Restore (restore=auto) what `directory` holds, then log and snapshot there."""
        if self.config.restore == "never" and directory.exists() and any(directory.iterdir()):
            aside = directory.with_name(f"{directory.name}.set-aside-{int(time.time())}")
            shutil.move(directory, aside)
            log.info(f"restore=never: earlier replay state moved to {aside}")
        persistence = ReplayPersistence(directory, self.config.keep_snapshots)
        started = time.perf_counter()
        state, records = persistence.load(self._decode_stored)
        if state is not None:
            self._load_state(state)
        replayed = 0
        for payload in records:
            self._insert(self._decode_stored(payload), replaying=True)
            replayed += 1
        if persistence.skipped:
            log.info(f"skipped an unreadable snapshot ({persistence.skipped})")
        if persistence.torn:
            log.info(f"the log ends in a torn record ({persistence.torn}): a crash mid-write, "
                     f"never acknowledged; restored the {replayed:,} logged fragments before it")
        self.persistence = persistence  # only now: a failed restore must not snapshot over it
        if state is not None or replayed:
            self.restored = (f"restored {len(self.replay):,} fragments ({self.inserted_steps:,} "
                             f"steps: snapshot + {replayed} logged) from {directory} in "
                             f"{time.perf_counter() - started:.1f} s")

    def _decode_stored(self, payload: bytes) -> Fragment:
        """A fragment from the log or a snapshot: wire bytes, checked as from the wire. Bytes of
        another schema version are refused whole (Incompatible), not passed over."""
        try:
            return decode(payload, Trajectory, self.spec, self.config.max_message_bytes)
        except DecodeError as exc:
            if exc.kind != "version":
                raise
            raise Incompatible("the replay state in the run dir holds fragments of another "
                               f"TPDEB version ({exc.detail}): restore it with the version that "
                               "wrote it, or start afresh with --restore never") from None

    def snapshot(self, wait: bool = False) -> bool:
        """Capture the state now (a shallow copy, timed) and write it in the background."""
        if self.persistence.writing and not wait:
            return False  # the previous one is still being written: try again next interval
        started = time.perf_counter()
        state = self.replay.state_dict()
        # The items (messages) are written one by one apart from the rest: B_p's in slot order,
        # then B_u's oldest first (see _load_state).
        items = state.pop("slot_items") + [item for _, item, _ in state["uniform"]]
        state["uniform"] = [(key, steps) for key, _, steps in state["uniform"]]
        saved = {"format": SNAPSHOT_FORMAT, "env_id": self.spec.env_id,
                 "obs_dim": self.spec.obs_dim, "act_dim": self.spec.act_dim, "replay": state,
                 "limiter": self.limiter.state_dict(), "inserted_steps": self.inserted_steps,
                 "samples_served": self.samples_served,
                 "priority_updates": self.priority_updates,
                 "ledgers": {a: ledger.state() for a, ledger in self.ledgers.items()}}
        if self.persistence.error is not None:
            log.info(f"a snapshot failed ({self.persistence.error}); the log still holds "
                      f"every fragment, but grows until one succeeds: check free space and "
                      f"permissions in {self.persistence.dir}")
            self.persistence.error = None
        started_write = self.persistence.snapshot(saved, items, encode, wait=wait)
        self.persistence.last_capture_ms = 1e3 * (time.perf_counter() - started)
        self.last_snapshot = time.monotonic()
        return started_write

    def _load_state(self, saved: dict) -> None:
        try:
            _check_saved(saved)
        except ConfigError as exc:
            raise ConfigError(f"{exc}: the run dir's replay state is damaged or not TPDEB's; "
                              "use another --run-dir, or --restore never") from None
        if saved.get("format") != SNAPSHOT_FORMAT:
            raise ConfigError(f"the replay snapshot in the run dir has format "
                              f"{saved.get('format')!r}, this version reads {SNAPSHOT_FORMAT}: "
                              "restore it with the version that wrote it, or --restore never")
        for name in ("env_id", "obs_dim", "act_dim"):
            if saved[name] != getattr(self.spec, name):
                raise ConfigError(f"the replay state in the run dir is for {name}="
                                  f"{saved[name]!r}, this run has {getattr(self.spec, name)!r}:"
                                  " use another --run-dir, or --restore never")
        state, items = saved["replay"], saved["items"]
        prioritized = len(state["slots"])
        state["slot_items"] = items[:prioritized]
        state["uniform"] = [(key, item, steps) for (key, steps), item
                            in zip(state["uniform"], items[prioritized:], strict=True)]
        try:
            self.replay.load_state_dict(state)
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise ConfigError(f"cannot restore the replay state: {exc}; use the same "
                              "capacities, or --restore never") from None
        self.limiter.load_state_dict(saved["limiter"])
        self.inserted_steps = saved["inserted_steps"]
        self.samples_served = saved["samples_served"]
        self.priority_updates = saved["priority_updates"]
        for actor_id, ledger in saved["ledgers"].items():
            self.ledgers[actor_id] = ActorLedger.from_state(ledger)

    # -- sampling
    def _request(self, query, message_type, what: str):
        """A query's request, or None once a bad one is counted and the query dropped."""
        try:
            return decode(query.payload.to_bytes() if query.payload is not None else b"",
                          message_type)
        except DecodeError as exc:
            self.reject(exc.kind, what, exc.detail)
            query.drop()
            return None

    def _take_sample_request(self, query) -> None:
        request = self._request(query, SampleRequest, "a sample request")
        if request is not None:
            self.waiting.append((time.monotonic(), query, request))

    def _answer_join(self, query) -> None:
        """`--actor-id auto`: the lowest id no actor known to this replay holds (one that has
        sent fragments, or was handed out); the same again to a repeated ask."""
        request = self._request(query, JoinRequest, "a join request")
        if request is None:
            return
        actor_id = self.joined.get(request.nonce)
        if actor_id is None:
            taken = set(self.ledgers) | set(self.joined.values())
            actor_id = next(i for i in itertools.count() if i not in taken)
            self.joined[request.nonce] = actor_id
            log.info(f"actor id {actor_id} handed out (--actor-id auto)")
        try:
            query.reply(self.keys.join, encode(JoinReply(actor_id, request.nonce)))
        finally:
            query.drop()

    def _serve_waiting(self) -> None:
        largest = self.config.largest_batch
        while self.waiting:
            since, query, request = self.waiting[0]
            steps = request.batch_size * self.spec.fragment_len
            if request.batch_size > largest:
                self._reply(query, self._not_ready(request, f"a batch of {request.batch_size} "
                                                   f"fragments is more than this run's largest "
                                                   f"({largest}: max_batch_fragments)"))
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
        sample = self.replay.sample(request.batch_size, request.beta, request.num_prioritized)
        self.limiter.on_sample(steps)
        self.samples_served += 1
        reply = SampleReply(
            request_id=request.request_id, ready=True, keys=sample.keys.astype(np.int64),
            weights=sample.weights.astype(np.float32),
            from_prioritized=sample.from_prioritized.astype(bool),
            step_weights=sample.step_weights,
            batch=stack_fragments(sample.items),
            inserted_steps=self.inserted_steps,
            obs_moments=Moments(*self.obs_moments) if self.obs_moments[0] else None,
            ret_moments=Moments(*self.ret_moments) if self.ret_moments[0] else None,
            reason="", **self._view())
        self.obs_moments = self.ret_moments = _NO_MOMENTS
        return reply

    def _view(self) -> dict:
        """What this replay holds (a sharded learner splits its next batch by it)."""
        view = self.replay.view()
        return {"prioritized_items": view.prioritized, "uniform_items": view.uniform,
                "mass": view.mass, "min_mass": view.min_mass}

    def _not_ready(self, request: SampleRequest, reason: str) -> SampleReply:
        return SampleReply.not_ready(request.request_id, reason, self.inserted_steps,
                                     tuple(self.replay.view()))

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
                  "bad_messages": sum(self.bad.values()) + self.flooded,
                  "bad/flood": self.flooded,
                  "disk_full": float(self.disk_full)}
        values.update({f"bad/{kind}": n for kind, n in self.bad.items()})
        if self.persistence is not None:
            p = self.persistence
            values.update({"snapshots_written": p.snapshots_written,
                           "snapshot_capture_ms": p.last_capture_ms,
                           "snapshot_write_s": p.last_snapshot_s,
                           "log_sync_ms": 1e3 * p.sync_s_total / max(p.syncs, 1)})
        for actor_id, ledger in self.ledgers.items():
            values[f"actor{actor_id}/ingested"] = ledger.ingested
            values[f"actor{actor_id}/duplicates"] = ledger.duplicates
            values[f"actor{actor_id}/dropped_busy"] = ledger.dropped_busy
        return values

    def publish_stats(self) -> None:
        self.stats_publisher.put(encode(Stats(
            role="replay", ident=str(self.shard), values=finite_values(self.stats()),
            episode_returns=np.zeros(0), episode_lengths=np.zeros(0, np.int64))))

    def close(self) -> None:
        for query in (q for _, q, _ in self.waiting):
            query.drop()
        self.waiting.clear()
        if self.persistence is not None:
            self.disk_retry_at = 0.0  # one last try
            if self._durable():
                self._flush_acks()
                self.snapshot(wait=True)  # a restart then replays no log at all
            else:
                log.warning(f"stopped with {self.persistence.unwritten} fragments not on disk "
                            "and never acknowledged: their actors send them again")
            with contextlib.suppress(OSError):
                self.persistence.close()
        self.token.undeclare()


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(ReplayServiceConfig, argv, PROG,
                           "TPDEB replay server: dual prioritized/uniform replay over Zenoh.")
        envs = make_vector_env(config.env_id, 1, config.env_kwargs)
        spec = run_spec(config, *space_dims(envs))
        envs.close()
        # With --listen it is the run's router; with only --connect, a client of one.
        session = open_for(config, "router" if config.listen else "client")
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    server = ReplayServer(config, spec, session, stop)
    server_dir = config.default_run_dir()
    try:
        server_dir.mkdir(parents=True, exist_ok=True)
        (server_dir / ("replay.toml" if config.replay_shards == 1
                       else f"replay-{config.shard}.toml")).write_text(to_toml(config))
        if config.persist:
            server.enable_persistence(server_dir / (
                "replay" if config.replay_shards == 1 else f"replay-{config.shard}"))
    except (ConfigError, OSError, DecodeError, Incompatible) as exc:
        server.close()
        close_session(session, PROG)
        return fail(PROG, exc)
    where = ", ".join(config.listen) or f"the router at {', '.join(config.connect)}"
    shard = (f" as replay shard {config.shard} of {config.replay_shards}"
             if config.replay_shards > 1 else "")
    log.info(f"run {config.run_id}: serving {spec.env_id} (obs {spec.obs_dim}, act "
              f"{spec.act_dim}, T {spec.fragment_len}) on {where}{shard}")
    if server.restored:
        log.info(server.restored)
    try:
        server.run()
    finally:
        server.close()
        close_session(session, PROG)
    log.info(f"stopped ({stop.reason}); {server.inserted_steps:,} steps ingested, "
              f"{sum(server.bad.values())} bad messages dropped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
