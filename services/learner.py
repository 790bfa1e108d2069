"""`tpdeb-learner`: trains on batches sampled from the replay server and publishes parameters.

Several sample requests stay in flight (one fetch thread each) so a batch is usually waiting
when an update ends. The loop: take a batch → merge the normaliser moments it carries → one
`Learner.step` → send new priorities → publish parameters every `params_publish_interval`
updates. Global steps are the replay's ingested env steps; at `total_timesteps`, or after
`train_for_seconds` of training if that comes first (services/budget.py), the learner writes its
final checkpoint and `end.json` and tells every process of the run to stop.

Checkpoints (services/store/checkpoint.py): every `checkpoint_interval_s` the loop writes
`checkpoints/ckpt_{updates}_{global_step}.pt` atomically and keeps the newest
`keep_checkpoints`. `--resume auto` (the default) continues from the run dir's newest loadable
checkpoint, so a learner restarted after a crash picks up where its last checkpoint left off.

Parameter versions: the version published is `updates + version_offset`, not the update count
itself. A restarted learner restores the update count of its last checkpoint, but its
predecessor may have published later versions before dying, and actors ignore versions older
than theirs. The offset lifts the first version after a restart above the high-water mark
(`VersionMark`) that every published version stays under. Fragments carry the version they were
collected with, so policy lag and sample age are measured in versions as well.
"""

from __future__ import annotations

import json
import logging
import queue
import sys
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch
import zenoh

from tpdeb.protocol import (
    Control,
    DecodeError,
    Keys,
    PriorityUpdate,
    RunSpec,
    SampleReply,
    SampleRequest,
    Stats,
    decode,
    encode,
)
from tpdeb.services.budget import Budget, clock
from tpdeb.services.compiled import BackgroundCompile
from tpdeb.services.config import ConfigError, to_toml
from tpdeb.services.config.presets import shown
from tpdeb.services.config.service import LearnerServiceConfig
from tpdeb.services.device import describe, resolve_device
from tpdeb.services.logs import rate_limited
from tpdeb.services.net.model_wire import model_for, params_message
from tpdeb.services.net.session import close_session, declare_publisher, fetch_spec, open_for
from tpdeb.services.net.wire import finite_values
from tpdeb.services.policy_file import POLICY_FILE, acting_arrays, policy_bytes, policy_meta
from tpdeb.services.process import StopSignal, configure, fail
from tpdeb.services.ranks import Agreement, Group, learner_tensors, rank_device
from tpdeb.services.seeding import seed_everything
from tpdeb.services.shards import Gathered, ShardSet
from tpdeb.services.store.checkpoint import (
    BEST_CHECKPOINT,
    FINAL,
    PERIODIC,
    VersionMark,
    checkpoint_dir,
    choose_resume,
    rotate,
    save_training,
    set_aside,
    spec_problem,
)
from tpdeb.services.store.diskio import DiskGuard, write_atomic
from tpdeb.services.store.metrics import MetricsWriter, hyperparameter_table
from tpdeb.tpdeb_core.batch_growth import BatchGrowth
from tpdeb.tpdeb_core.learner import Batch, Learner, place
from tpdeb.tpdeb_core.model import state_arrays

PROG = "tpdeb-learner"
log = logging.getLogger(PROG)
LINK_TAGS = ("up_bytes_per_s", "down_bytes_per_s", "queue_bytes", "latency_ms")


class LearnerService:
    def __init__(self, config: LearnerServiceConfig, spec: RunSpec, session, stop: StopSignal,
                 resume: tuple[Path, dict] | None = None, group: Group | None = None):
        """`resume`: the checkpoint (path, state) to continue from (see `choose_resume`);
        `group`: this learner's place among data-parallel learners (services/ranks.py)."""
        self.config, self.spec, self.session, self.stop = config, spec, session, stop
        self.group, self.rank = group, group.rank if group is not None else 0
        self.agreed: Agreement | None = None  # the group's, for the update under way
        self.keys = Keys(config.run_id)
        seed_everything(config.seed)
        self.model = model_for(spec)
        self.device = resolve_device(config.device)
        # off the CPU, batches go through pinned memory and priorities come back a turn late
        self.pin = self.defer_priorities = self.device.type != "cpu"
        try:  # the run spec's model against this learner's loss settings
            self.learner = Learner(self.model, config.loss_config(), self.device)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if group is not None:
            self.learner.rules.reduce = group.reducer()
        self.run_dir = config.default_run_dir()
        self.global_step = 0
        self.budget = Budget(config.total_timesteps, config.train_for_seconds)
        self.ended_by: str | None = None
        self.resumed = resume is not None
        self._start_from(resume)
        # The model's state tensors (views of its parameters and buffers, which every update and
        # restore changes in place): taken once, walking the module tree per publication costs
        # more than encoding the parameters.
        self.state = self.model.state_dict()
        self.checkpoint_s, self.checkpoints_written = 0.0, 0
        self._writers()
        self.log_bad = rate_limited(log)
        self._pipeline()
        self.stats_inbox: queue.Queue = queue.Queue()
        self.replay_stats: dict = {}
        self.link_stats: dict = {}
        self.actors_heard: set[str] = set()  # actors whose stats arrived
        self.actor_stats: dict[str, dict] = {}  # the latest of each (delivery counters)
        self.trained_keys: set[int] = set()
        self.trained_floor = -1  # keys ≤ this are no longer remembered (see train_on)
        # (in keys: with replay shards a batch's keys are key · K + shard)
        self.replay_items = (config.prioritized_capacity + (
            config.uniform_capacity_steps // config.fragment_len)) * spec.replay_shards
        self.lag_sum, self.lag_count = 0.0, 0
        self.evaluations_logged = 0
        self.recent_returns: deque[float] = deque(maxlen=20)
        self.sums: dict[str, float] = {}
        self.count = 0
        self.wait_s = self.update_s = 0.0
        self.replies = [0, 0]  # batches received, of them through shared memory (a window's)
        self.params_bytes = b""
        self.params_version = self.current_version = -1  # the encoded one, the latest one
        self.waiting_queries: list[tuple[object, int]] = []  # (query, version it has)
        self.params_lock = threading.Lock()
        self._declare()
        if group is not None:
            self._join_group()

    def _pipeline(self) -> None:
        """The batches' queue, the compiled update and the priorities waiting to go."""
        # (the reply, its batch placed on the device): fetch threads decode and place the next
        # batches while an update runs
        self.batches: queue.Queue[tuple[SampleReply, Batch]] = queue.Queue(
            maxsize=self.config.requests_in_flight)
        self.compiler = BackgroundCompile(self.learner) if self.config.compile == "auto" else None
        self.compiled = False
        self.pending: tuple | None = None  # a batch's priorities not yet sent
        cfg = self.config
        self.growth = (BatchGrowth(cfg.batch_fragments, cfg.largest_batch)
                       if cfg.largest_batch > cfg.batch_fragments else None)

    @property
    def batch_fragments(self) -> int:
        """What the fetchers ask for: the configured batch, or the size batch growth holds."""
        return self.growth.size if self.growth is not None else self.config.batch_fragments

    @property
    def run_step(self) -> int:
        """The run's env steps as the settings that follow them read it: rank 0's in a group."""
        return self.global_step if self.agreed is None else self.agreed.global_step

    def _writers(self) -> None:
        """The run dir's writers, each of which a full disk costs writes, not the run."""
        self.metrics = MetricsWriter(self.run_dir, log,
                                     self.global_step if self.resumed else None)
        self.checkpoint_guard = DiskGuard(
            "periodic checkpoint", checkpoint_dir(self.run_dir), log, retry_s=0.0,
            consequence="training goes on and the previous checkpoint stays valid; the next is "
                        f"tried in {self.config.checkpoint_interval_s:g} s")
        self.mark_guard = DiskGuard("parameter-version mark", self.versions.path, log,
                                    consequence="actors keep their parameters until it is")

    def _declare(self) -> None:
        """Publishers, the parameters' queryable, the stats subscriber, the liveliness token
        and the sample fetchers (not started)."""
        s, k = self.session, self.keys
        # Monitors may subscribe; actors pull through params/latest instead (see
        # _answer_latest). Latest wins, so a congested link may drop one.
        self.params_publisher = declare_publisher(s, "params", k.params)
        self.priorities_publisher = declare_publisher(s, "priorities", k.priorities)
        # replay shards: each one's sample queryable and priorities, one batch from all
        shards = self.spec.replay_shards
        self.shard_set = (ShardSet(shards, self.config.zeta, self.config.seed + 7919 * self.rank,
                                   retry_s=self.config.request_timeout_s)
                          if shards > 1 else None)
        self.shard_keys = [k.of_shard(shard) for shard in range(shards)] if shards > 1 else []
        self.shard_priorities = [declare_publisher(s, "priorities", keys.priorities)
                                 for keys in self.shard_keys]
        self.replay_watch = (s.liveliness().declare_subscriber(
            k.of_role("alive", "replay"), self._on_replay_alive, history=True)
            if self.shard_set is not None else None)
        self.control_publisher = declare_publisher(s, "control", k.control)
        self.stats_publisher = declare_publisher(s, "stats", k.stats("learner", self.rank))
        # rank 0 answers for the group (its parameters are every rank's)
        self.latest_queryable = (s.declare_queryable(k.params_latest, self._answer_latest)
                                 if self.rank == 0 else None)
        self.stats_subscriber = s.declare_subscriber(k.stats_all, self.stats_inbox.put)
        self.token = s.liveliness().declare_token(k.alive("learner", self.rank))
        self.fetch_cancel = zenoh.CancellationToken()
        self.fetchers = [threading.Thread(target=self._fetch_loop, args=(i,), daemon=True,
                                          name=f"fetch-{i}")
                         for i in range(self.config.requests_in_flight)]

    def _join_group(self) -> None:
        """Rank 0's learner (restored from its checkpoint, or new) copied to every rank."""
        numbers = self.group.broadcast_state(
            learner_tensors(self.learner, self.model),
            [self.global_step, self.budget.spent_before, self.learner.updates])
        self.global_step, self.budget.spent_before = int(numbers[0]), numbers[1]
        self.learner.updates = int(numbers[2])
        log.info(f"learner rank {self.rank} of {self.group.size}: the group starts from rank "
                 f"0's state ({self.learner.updates:,} updates, {self.global_step:,} env steps)")

    # -- checkpoints
    def _start_from(self, resume: tuple[Path, dict] | None) -> None:
        """The checkpoint restored (or, `--resume never`, the earlier start's files moved
        aside), then the parameter versions placed above any published before."""
        restored_version = -1
        if resume is not None:
            restored_version = self.restore(*resume)
            # an earlier end's record no longer says how this run ends (written again at its end)
            (self.run_dir / "end.json").unlink(missing_ok=True)
        elif self.config.resume == "never":
            aside = set_aside(self.run_dir)
            if aside is not None:
                log.info(f"--resume never: starting fresh; earlier files moved to {aside}")
        self.versions = VersionMark(checkpoint_dir(self.run_dir))
        self.version_offset = self.versions.offset(self.learner.updates, restored_version)
        if resume is not None:
            log.info(f"resumed from {resume[0]}: {self.learner.updates:,} updates, version "
                     f"{self.param_version():,}, {self.global_step:,} env steps")

    def restore(self, path: Path, state: dict) -> int:
        """Load a checkpoint's learner state and counters; returns its parameter version."""
        cfg = self.config
        problem = spec_problem(state, self.spec)
        if problem:
            raise ConfigError(f"checkpoint {path} does not fit this run: {problem}; pass "
                              "--resume never or another --run-dir")
        try:
            self.learner.load_state_dict(state)
        except (RuntimeError, ValueError, KeyError, TypeError) as exc:
            reason = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else repr(exc)
            raise ConfigError(f"checkpoint {path} does not fit this learner's model ({reason}); "
                              "pass --resume never or another --run-dir") from None
        # Settings given now win over those stored in the optimiser's state; an adapted KL
        # coefficient is state and stays.
        self.learner.set_learning_rate(cfg.learning_rate)
        if cfg.kl_target <= 0:
            self.learner.kl_coef = cfg.kl_coef
        self.global_step = int(state["global_step"])
        self.budget.spent_before = float(state.get("train_elapsed_s", 0.0))
        return int(state["version"])

    def param_version(self) -> int:
        """The version of the current parameters (see the module docstring)."""
        return self.learner.updates + self.version_offset

    def save_checkpoint(self, tag: str) -> Path:
        return save_training(self.run_dir, self.learner, self.config, self.global_step, tag,
                             self.param_version(), self.spec, self.budget.elapsed())

    def periodic_checkpoint(self) -> Path | None:
        """A full disk must not end the training: the previous checkpoint stays valid (a
        checkpoint is written beside it and renamed), said once per outage."""
        started, written = time.perf_counter(), []

        def write() -> None:
            written.append(self.save_checkpoint(PERIODIC))
            rotate(checkpoint_dir(self.run_dir), self.config.keep_checkpoints)

        if not self.checkpoint_guard.attempt(write):
            return None
        self.checkpoint_s += time.perf_counter() - started
        self.checkpoints_written += 1
        return written[0]

    # -- parameters down
    def publish_params(self, eager: bool = False) -> None:
        """A new version exists: answer the queries waiting for one (and put it on the `params`
        key for any monitor). Encoded only when someone takes it: actors ask once per fragment,
        far less often than the learner updates. Rank 0 alone publishes for a group."""
        if self.rank:
            return
        version = self.param_version()
        # on disk before any actor can hold this version; if the disk refuses, actors keep the
        # version they have until it takes the mark
        if not self.mark_guard.attempt(lambda: self.versions.reserve(version)):
            return
        with self.params_lock:
            self.current_version = version
        if eager:
            self._encoded_params()
        self.serve_params()
        # Nobody subscribed (the usual case: actors pull): no copy to send. Zenoh builds
        # without matching status put anyway.
        matching = getattr(self.params_publisher, "matching_status", None)
        if matching is None or matching.matching:
            self.params_publisher.put(self._encoded_params())

    def _encoded_params(self) -> bytes:
        """The current version's bytes, encoded once (main thread only: updates change the
        arrays in place)."""
        if self.params_version != self.current_version:
            data = encode(params_message(state_arrays(self.state), self.current_version,
                                         self.config.params_dtype))
            with self.params_lock:
                self.params_bytes, self.params_version = data, self.current_version
        return self.params_bytes

    def serve_params(self) -> None:
        """Answer the waiting queries that the current version satisfies."""
        with self.params_lock:
            if not self.waiting_queries:
                return
            due = [q for q, after in self.waiting_queries if after < self.current_version]
            self.waiting_queries = [(q, after) for q, after in self.waiting_queries
                                    if after >= self.current_version]
        if due:
            data = self._encoded_params()
            for query in due:
                self._reply(query, data)

    def _answer_latest(self, query) -> None:
        """Long poll: `params/latest?after=V` is answered as soon as a version newer than V
        exists: at once when the current version's bytes are at hand, else by the loop
        between two updates (`serve_params`). Actors pull one version at a time, so a thin
        link carries only parameters someone will use and never queues stale ones ahead of
        acks."""
        after = query.parameters.get("after")
        try:
            after = int(after) if after is not None else -1
        except ValueError:
            after = -1
        with self.params_lock:
            ready = self.params_version == self.current_version > after
            data = self.params_bytes if ready else b""
            if not ready:
                self.waiting_queries.append((query, after))
        if data:
            self._reply(query, data)

    def _reply(self, query, data: bytes) -> None:
        try:
            query.reply(self.keys.params_latest, data)
        except zenoh.ZError:
            pass  # the asker gave up (timed out or left)
        finally:
            query.drop()

    def _on_replay_alive(self, sample) -> None:
        """A replay shard's token appeared (it is asked again) or went (left out until then)."""
        ident = str(sample.key_expr).rsplit("/", 1)[-1]
        if ident.isdecimal() and int(ident) < self.shard_set.shards:
            if sample.kind == zenoh.SampleKind.PUT:
                self.shard_set.back(int(ident))
            else:
                self.shard_set.gone(int(ident))

    # -- batches in
    def beta(self) -> float:
        progress = self.budget.progress(self.global_step)
        return self.config.beta_start + (1.0 - self.config.beta_start) * progress

    def _fetch_loop(self, slot: int) -> None:
        request_id = slot
        while not self.stop:
            request_id += self.config.requests_in_flight
            batch = self.fetch(request_id)
            if batch is None:
                self.stop.wait(0.02)  # replay absent or rate-limited: do not spin
                continue
            placed = place(batch.batch, batch.weights, batch.step_weights, self.device,
                           self.pin)
            while not self.stop:
                try:
                    self.batches.put((batch, placed), timeout=0.1)
                    break
                except queue.Full:
                    pass

    def fetch(self, request_id: int) -> SampleReply | None:
        """One sample request: the batch, or None when the replay had none to give (absent,
        rate-limited) or its reply was bad."""
        if self.shard_set is not None:
            return self.fetch_sharded(request_id)
        request = SampleRequest(request_id=request_id, batch_size=self.batch_fragments,
                                beta=self.beta())
        got = self._answer(self._ask(self.keys.sample, request))
        if got is None:
            return None
        self.global_step = max(self.global_step, got.inserted_steps)
        return got if got.ready else None

    def _ask(self, key: str, request: SampleRequest, handler=None):
        """A sample query sent: its replies come through the handler returned (Zenoh's
        default), or through the callback `handler` given (then nothing is returned)."""
        return self.session.get(key, handler, payload=encode(request),
                                timeout=self.config.request_timeout_s,
                                cancellation_token=self.fetch_cancel)

    def _answer(self, replies) -> SampleReply | None:
        """The last good reply to a sample query (None: none came, or none could be read)."""
        got = None
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                got = decode(reply.ok.payload.to_bytes(), SampleReply, self.spec,
                             self.config.max_message_bytes)
            except DecodeError as exc:
                self.log_bad(exc.kind, f"dropped a bad sample reply ({exc})")
                continue
            if got.ready:  # a batch; whether it came through shared memory
                self.replies = [self.replies[0] + 1,
                                self.replies[1] + (reply.ok.payload.as_shm() is not None)]
        return got

    def fetch_sharded(self, request_id: int) -> SampleReply | None:
        """One batch from the replay shards: each asked for its rows at once; the rows of a
        shard that was not ready (or did not answer) asked again of those that were. None when
        the batch could not be filled (what its replies carried of the normalisers' moments
        is kept for the next one)."""
        shards, beta, size = self.shard_set, self.beta(), self.batch_fragments
        counts, ready = shards.plan(size), []
        for _ in range(2):
            asked_at, asked = time.monotonic(), {}
            for shard, (n_p, n_u) in enumerate(counts):
                if n_p + n_u:
                    asked[shard] = Gathered()
                    self._ask(self.shard_keys[shard].sample, SampleRequest(
                        request_id=request_id, batch_size=int(n_p + n_u), beta=beta,
                        num_prioritized=int(n_p)), asked[shard].handler())
            missing = 0
            for shard, query in asked.items():
                got = self._answer(query.wait(self.config.request_timeout_s))
                if got is None:  # each shard's own wait, not the replies read before it
                    waited = query.ended_at - asked_at
                    if (out := shards.missed(shard, waited)) is not None:
                        log.info(f"replay shard {shard} did not answer ({waited:.1f} s): left "
                                 f"out of the batches for {out:.0f} s")
                else:
                    shards.heard(shard, got)
                if got is not None and got.ready:
                    ready.append((shard, got))
                else:
                    missing += int(counts[shard].sum())
            if not missing:
                break
            counts = shards.plan(missing, among=sorted({shard for shard, _ in ready}))
            if not counts.any():
                break
        self.global_step = max(self.global_step, shards.inserted_steps)
        if sum(len(reply.keys) for _, reply in ready) < size:
            shards.set_aside([reply for _, reply in ready])
            return None
        return shards.join(ready, beta)

    # -- the loop
    def run(self) -> bool:
        cfg = self.config
        (self.run_dir / "config.toml").write_text(to_toml(cfg))
        self.metrics.text("hyperparameters", hyperparameter_table(cfg))
        self.publish_params(eager=True)  # actors starting up wait for the first version
        for fetcher in self.fetchers:
            fetcher.start()
        self.budget.restart_clock()
        log.info(f"run {cfg.run_id}: training {self.spec.env_id} for {self.budget.describe()} "
                  f"({cfg.algo}, preset: {shown(cfg.preset)}) on {describe(self.device)}; run "
                  f"dir {self.run_dir}")
        start = last_checkpoint = time.monotonic()
        self.reported = (start, self.global_step, start, self.global_step)
        first_step = self.global_step
        checkpointed_updates = self.learner.updates
        while True:
            waited = time.perf_counter()
            if self.group is None:
                if self.stop or self.limit_reached():
                    break
                try:
                    batch = self.batches.get(timeout=0.1)
                except queue.Empty:
                    batch = None
            else:  # every rank updates together, or they all stop
                batch = self.group_batch()
                if batch is None:
                    break
            got = time.perf_counter()
            self.wait_s += got - waited
            if batch is not None:
                self.train_on(*batch)
            self.serve_params()
            self.drain_stats()
            now = self.report()
            if batch is not None and self.growth is not None:
                self.grow(busy_s=time.perf_counter() - got, waited_s=got - waited)
            if (cfg.checkpoint_interval_s and now - last_checkpoint >= cfg.checkpoint_interval_s
                    and self.rank == 0):
                last_checkpoint = now
                # no update since the last one: it would only repeat it
                if (self.learner.updates != checkpointed_updates
                        and self.periodic_checkpoint() is not None):
                    checkpointed_updates = self.learner.updates
        finished = self.limit_reached()
        elapsed = time.monotonic() - start
        self.log_progress((self.global_step - first_step) / max(elapsed, 1e-9))
        return finished

    def report(self) -> float:
        """Stats and the progress line when they are due; returns the time."""
        now, cfg = time.monotonic(), self.config
        last_stats, stats_step, last_log, last_step = self.reported
        if now - last_stats >= cfg.stats_interval_s:
            self.publish_stats((self.global_step - stats_step) / (now - last_stats))
            last_stats, stats_step = now, self.global_step
        if now - last_log >= cfg.log_interval_s:
            self.log_progress((self.global_step - last_step) / (now - last_log))
            last_log, last_step = now, self.global_step
        self.reported = (last_stats, stats_step, last_log, last_step)
        return now

    def group_batch(self) -> tuple[SampleReply, Batch] | None:
        """This rank's next batch once the group agrees on the update (`self.agreed`: every
        rank's moments, rank 0's progress); None when the group stops — a rank's signal or
        rank 0's budget. Parameters are served and stats published while it waits."""
        batch = None
        while batch is None and not (self.stop or (self.rank == 0 and self.limit_reached())):
            try:
                batch = self.batches.get(timeout=0.1)
            except queue.Empty:
                self.serve_params()
                self.drain_stats()
                self.report()
        reply = batch[0] if batch is not None else None
        self.agreed = self.group.agree(
            reply.obs_moments if reply else None, reply.ret_moments if reply else None,
            self.spec.obs_dim, self.global_step, self.budget.elapsed(), stop=batch is None,
            compiled=self.compile_state())
        if self.compiler is not None and not self.compiled and self.agreed.compiled:
            self.switch_compiled(self.agreed.compiled > 0)
        return None if self.agreed.stop else batch

    def compile_state(self) -> int:
        """This rank's compiled update for the group's agreement: 1 ready, −1 failed, 0 not
        (yet)."""
        compiler = self.compiler
        if compiler is None or self.compiled or compiler.thread is None or not compiler.ready():
            return 0
        return 1 if compiler.error is None else -1

    def train_on(self, batch: SampleReply, placed: Batch | None = None) -> None:
        """One update on a sample reply (`placed`: its batch on the device already)."""
        cfg = self.config
        if self.agreed is None:  # alone: the moments this batch's reply carries
            parts = ([batch.obs_moments], [batch.ret_moments])
        else:  # in a group: every rank's, in rank order, the same on every rank
            parts = (self.agreed.obs, self.agreed.ret)
        if cfg.obs_norm_steps and self.run_step >= cfg.obs_norm_steps:
            parts = ([], parts[1])  # the observation normaliser holds from here on
        for rms, moments in zip((self.model.obs_rms, self.model.ret_rms), parts, strict=True):
            for part in moments:
                if part is not None:
                    rms.merge(part.count, part.mean, part.m2)
        self.follow_schedules()
        if placed is None:
            placed = place(batch.batch, batch.weights, batch.step_weights, self.device, self.pin)
        fragments = batch.batch  # the FragmentBatch as decoded
        version = self.param_version()  # of the parameters this update starts from
        started = time.perf_counter()
        norm = self.learner.normaliser()
        priorities = self.learner.update(placed, norm)
        self.send_priorities((batch.keys, batch.from_prioritized, priorities))
        self.update_s += time.perf_counter() - started
        if self.compiler is not None and not self.compiled and (
                self.growth is None or len(batch.keys) == self.batch_fragments):  # growth: the
            # batch size from here on, not one of the old size still in the queue
            self.prepare_compiled(placed, norm)
        if self.learner.updates % cfg.params_publish_interval == 0:
            self.publish_params()
        ages = (version - fragments.policy_version).tolist()
        self.sums["replay/sample_age_updates"] = self.sums.get("replay/sample_age_updates", 0.0) \
            + float(np.mean(ages))
        # Policy lag: how many versions behind the learner a fragment's behaviour policy was
        # when the learner first trained on it (replay keys grow with insertion order). Across
        # a restart the versions the restarted learner skipped count too. Keys at or below the
        # floor have been forgotten: the prioritized buffer may still hold (and serve) them, but
        # they are not new, and counting them as new would add their whole age to the lag.
        fresh = [(key, age) for key, age in zip(batch.keys.tolist(), ages, strict=True)
                 if key > self.trained_floor and key not in self.trained_keys]
        for key, age in fresh:
            self.trained_keys.add(key)
            self.lag_sum += age
            self.lag_count += 1
        if len(self.trained_keys) > 4 * self.replay_items:  # forget keys long evicted
            self.trained_floor = max(self.trained_keys) - 2 * self.replay_items
            self.trained_keys = {k for k in self.trained_keys if k > self.trained_floor}
        self.count += 1

    def send_priorities(self, new: tuple | None) -> None:
        """The new priorities of a batch's prioritized samples, to the replay. On the CPU they
        are at hand when the update returns and leave at once; on an accelerator they are
        copied out without waiting (into pinned memory) and sent after the next update, by
        when the copy is done, so the host never stalls the device. None: send what waits."""
        ready, self.pending = self.pending, None
        if new is not None and not self.defer_priorities:
            ready, new = new, None
        if new is not None:
            keys, chosen, priorities = new
            copied = torch.cuda.Event()
            host = priorities.to("cpu", non_blocking=True)
            copied.record()
            self.pending = (keys, chosen, host, copied)
        if ready is None:
            return
        keys, chosen, priorities = ready[:3]
        if len(ready) == 4:
            ready[3].synchronize()
        idx = np.flatnonzero(chosen)
        if not len(idx):
            return
        keys, values = np.asarray(keys, np.int64)[idx], priorities.numpy()[idx].astype(np.float64)
        if self.shard_set is None:
            self.priorities_publisher.put(encode(PriorityUpdate(keys=keys, priorities=values)))
            return
        for shard, (where, own_keys) in self.shard_set.route(keys).items():
            self.shard_priorities[shard].put(encode(PriorityUpdate(
                keys=own_keys, priorities=values[where])))

    def prepare_compiled(self, placed: Batch, norm: torch.Tensor) -> None:
        """Start compiling the update after the first one (on its batch), and switch to it
        between two updates once it is ready."""
        compiler = self.compiler
        if compiler.thread is None:
            compiler.start(placed, norm)
        elif compiler.ready() and self.group is None:  # a group switches when all are ready
            self.switch_compiled(True)

    def switch_compiled(self, every_rank: bool) -> None:
        """Run the compiled update from the next one on, or stay eager for good where it (or,
        in a group, another rank's: `every_rank` false) could not be prepared: a group's
        ranks must run the same code at every update to stay bit for bit equal."""
        self.compiled = True
        if every_rank and self.compiler.install():
            return
        if not every_rank:
            if self.compiler.thread is not None:
                self.compiler.thread.join()
            log.warning("another learner rank could not compile the update; the group goes "
                        "on eager")
        self.compiler = None  # eager from here on, whatever the batch

    def grow(self, busy_s: float, waited_s: float) -> None:
        """Batch growth: one update's loop time to the rule (once the update runs compiled,
        where it compiles), and the fetchers asked for the size it picks."""
        if self.compiler is not None and not self.compiled:
            return
        size = self.growth.observe(busy_s, waited_s)
        if size is None:
            return
        old, seconds = self.growth.last
        if size < old:
            why = f"{seconds / self.growth.costs[size]:.2f}× one on {size}: kept at {size}"
        else:
            why = "the learner is the limit: the larger one is timed next"
        log.info(f"batch {old} → {size} fragments (an update on {old}: {1e3 * seconds:.1f} ms; "
                 f"{why})")
        if self.compiler is not None:  # compiled again for the new shape, eager meanwhile
            self.learner.use(self.learner.rules)
            self.compiler.reset()
            self.compiled = False

    def wait_for_compile(self) -> None:
        """A compile still running when the run ends is let finish: the interpreter must not
        exit under a thread inside the compiler (it would abort the process)."""
        thread = self.compiler.thread if self.compiler is not None else None
        if thread is not None and thread.is_alive():
            log.info("waiting for the update's compile to end before exiting")
            thread.join()

    def follow_schedules(self) -> None:
        """The learning rate and the log-std ceiling where they are annealed, at the run's
        progress (the steps' or the seconds', whichever is further along, or schedule_steps'
        where they come first)."""
        cfg, agreed, step = self.config, self.agreed, self.run_step
        progress = (self.budget.progress(step) if agreed is None
                    else self.budget.progress_at(step, agreed.elapsed_s))
        if cfg.schedule_steps > 0:
            progress = min(1.0, max(progress, step / cfg.schedule_steps))
        if cfg.anneal_lr:
            self.learner.set_learning_rate(cfg.learning_rate * max(1e-3, 1.0 - progress))
        if cfg.anneal_log_std:
            self.learner.log_std_ceiling = (cfg.init_log_std
                                            + (cfg.final_log_std - cfg.init_log_std) * progress)

    def drain_stats(self) -> None:
        while True:
            try:
                sample = self.stats_inbox.get_nowait()
            except queue.Empty:
                return
            try:
                stats = decode(sample.payload.to_bytes(), Stats)
            except DecodeError as exc:
                self.log_bad(exc.kind, f"dropped bad stats from {sample.key_expr} ({exc})")
                continue
            if stats.role == "replay":
                self.replay_stats = stats.values
            elif stats.role == "link":
                self.link_stats = stats.values
            elif stats.role == "evaluator":
                self.on_evaluation(stats.values)
            elif stats.role == "actor":
                self.actors_heard.add(stats.ident)
                self.actor_stats[stats.ident] = stats.values
                for ret, length in zip(stats.episode_returns.tolist(),
                                       stats.episode_lengths.tolist(), strict=True):
                    self.recent_returns.append(ret)
                    self.metrics.log(self.global_step, {"charts/episodic_return": ret,
                                                        "charts/episodic_length": length})

    def on_evaluation(self, values: dict) -> None:
        """An evaluator's report (its stats): each new evaluation logged once, at the global
        step it was made at; a new best answered with checkpoints/best.pt."""
        count = int(values.get("eval/count", 0))
        if count <= self.evaluations_logged:
            return  # a heartbeat, or a report already logged
        self.evaluations_logged = count
        step = int(values.get("eval/global_step", self.global_step))
        self.metrics.log(step, {k: v for k, v in values.items()
                                if k in ("eval/mean_return", "eval/std_return",
                                         "eval/mean_length")})
        if values.get("eval/best"):
            self.save_best(float(values["eval/mean_return"]), int(values["eval/param_version"]))

    def save_best(self, mean_return: float, evaluated_version: int) -> Path | None:
        """checkpoints/best.pt: the learner's state when a new best evaluation came, with the
        version evaluated (inline, the same; from an evaluator, a few updates before)."""
        written = []

        def write() -> None:
            written.append(save_training(
                self.run_dir, self.learner, self.config, self.global_step, "best",
                self.param_version(), self.spec, self.budget.elapsed(), name=BEST_CHECKPOINT,
                extra={"eval_mean_return": mean_return, "eval_version": evaluated_version}))

        self.checkpoint_guard.attempt(write)
        return written[0] if written else None

    def mean_return(self) -> float:
        return float(np.mean(self.recent_returns)) if self.recent_returns else float("nan")

    def param_version_lag(self) -> float:
        return self.lag_sum / self.lag_count if self.lag_count else float("nan")

    def publish_stats(self, sps: float) -> None:
        """What the cluster's display shows (only finite numbers travel)."""
        values = {"global_step": self.global_step, "total_timesteps":
                  self.config.total_timesteps, "sps": sps, "mean_return": self.mean_return(),
                  "updates": self.learner.updates, "param_version": self.param_version(),
                  "param_version_lag": self.param_version_lag(),
                  "actors": len(self.actors_heard)}
        left = self.budget.time_left()
        if left is not None:
            values["time_left_s"] = left
        self.stats_publisher.put(encode(Stats(
            role="learner", ident=str(self.rank), values=finite_values(values),
            episode_returns=np.zeros(0), episode_lengths=np.zeros(0, np.int64))))

    def log_progress(self, sps: float) -> None:
        values = {"charts/SPS": sps,
                  "charts/learning_rate": self.learner.learning_rate(),
                  "perf/updates": self.learner.updates,
                  "perf/param_version": self.param_version(),
                  "perf/train_elapsed_s": self.budget.elapsed()}
        if self.count:
            values.update(self.learner.read_metrics())  # the device's sums, read once
            values.update({k: v / self.count for k, v in self.sums.items()})
            values["perf/update_ms"] = 1e3 * self.update_s / self.count
            values["perf/batch_fragments"] = self.batch_fragments
        if self.checkpoints_written:
            values["perf/checkpoint_ms"] = 1e3 * self.checkpoint_s / self.checkpoints_written
        replies, shared = self.replies
        if replies:
            values["perf/sample_replies_shared_memory"] = shared / replies
        busy = self.update_s + self.wait_s
        if busy > 0:
            values["perf/batch_wait_fraction"] = self.wait_s / busy
        values["actor/param_version_lag"] = self.param_version_lag()
        values.update({f"replay/{k}": v for k, v in self.replay_stats.items()
                       if isinstance(v, (int, float)) and "/" not in k})
        values.update({f"link/{k}": self.link_stats[k] for k in LINK_TAGS if k in self.link_stats})
        values.update(self.delivery_totals())
        if self.link_stats and self.global_step:
            for way in ("up", "down"):
                values[f"link/{way}_bytes_per_env_step"] = \
                    self.link_stats.get(f"{way}_bytes_total", 0) / self.global_step
        self.metrics.log(self.global_step, values)
        self.metrics.flush()
        self.sums, self.count, self.wait_s, self.update_s = {}, 0, 0.0, 0.0
        self.replies = [0, 0]
        self.checkpoint_s, self.checkpoints_written = 0.0, 0
        self.lag_sum, self.lag_count = 0.0, 0
        log.info(f"[{self.global_step:>10,}/{self.config.total_timesteps:,}] SPS {sps:7,.0f} | "
                  f"return {self.mean_return():9.1f} | updates {self.learner.updates:,} | "
                  f"actors {len(self.actors_heard)}{self.budget.shown()}")

    def delivery_totals(self) -> dict[str, float]:
        """Fragments sent / acknowledged / resent by the actors (their current process runs)
        and ingested / duplicates / dropped while busy at the replay, over all actors."""
        totals = {}
        for name in ("sent", "acked", "resent"):
            if self.actor_stats:
                totals[f"delivery/{name}"] = sum(v.get(name, 0)
                                                 for v in self.actor_stats.values())
        for name in ("ingested", "duplicates", "dropped_busy"):
            per_actor = [v for k, v in self.replay_stats.items()
                         if k.startswith("actor") and k.endswith(f"/{name}")]
            if per_actor:
                totals[f"delivery/{name}"] = sum(per_actor)
        return totals

    def finish(self, finished: bool) -> None:
        # Nothing trained, nothing to keep (and a 0-step file would only shadow nothing).
        self.send_priorities(None)  # the last batch's, where they wait a turn
        self.wait_for_compile()
        # Only the end of the run's budget makes the final checkpoint; a stopped run's last is
        # a periodic one, which the next start resumes from like any other. A group's rank 0
        # keeps the group's checkpoint, policy and end.
        keeps = self.learner.updates and self.rank == 0
        path = (self.save_checkpoint(FINAL if finished else PERIODIC) if keeps
                else "none (no update yet)" if not self.learner.updates else "rank 0's")
        if keeps:
            self.write_policy()
        if finished and self.rank == 0:
            self.write_end(path)
            self.control_publisher.put(encode(Control(command="stop", reason=self.ended_by)))
        self.stop.set("finished")
        with self.params_lock:
            waiting, self.waiting_queries = self.waiting_queries, []
        for query, _ in waiting:
            query.drop()
        self.fetch_cancel.cancel()  # no thread may sit in a query when the interpreter exits
        for fetcher in self.fetchers:
            if fetcher.is_alive():
                fetcher.join(timeout=self.config.request_timeout_s)
        self.metrics.close()
        self.token.undeclare()
        log.info(f"{'done' if finished else 'stopped'} at {self.global_step:,} steps"
                  f"{f' ({self.ended_by} reached)' if finished else ''}, "
                  f"{self.learner.updates:,} updates, "
                  f"{clock(self.budget.elapsed())} of training; checkpoint {path}")

    def limit_reached(self) -> bool:
        """Whether the run's steps or its time are used up (`ended_by` says which)."""
        self.ended_by = self.ended_by or self.budget.reached(self.global_step)
        return self.ended_by is not None

    def write_policy(self) -> None:
        """policy.npz in the run dir: the final policy for numpy alone (`tpdeb.load_policy`)."""
        spec, cfg = self.spec, self.config
        meta = policy_meta(spec.env_id, spec.env_kwargs, spec.obs_dim, spec.act_dim,
                           cfg.obs_clip, spec.policy_std)
        data = policy_bytes(acting_arrays(self.learner.model.arrays()), spec.action_low,
                            spec.action_high, meta)
        try:
            write_atomic(self.run_dir / POLICY_FILE, lambda f: f.write(data))
        except OSError as exc:
            log.warning(f"{POLICY_FILE} not written ({exc})")

    def write_end(self, checkpoint) -> None:
        """`end.json` in the run dir: which limit ended the run, where and when."""
        record = {"ended_by": self.ended_by, "global_step": self.global_step,
                  "total_timesteps": self.config.total_timesteps,
                  "train_for_seconds": self.config.train_for_seconds,
                  "train_elapsed_s": round(self.budget.elapsed(), 3),
                  "updates": self.learner.updates, "checkpoint": str(checkpoint)}
        try:
            write_atomic(self.run_dir / "end.json",
                         lambda f: f.write(json.dumps(record, indent=1).encode()))
        except OSError as exc:
            log.warning(f"end.json not written ({exc})")


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(LearnerServiceConfig, argv, PROG,
                           "TPDEB learner: trains from the replay server, publishes parameters.")
        # The learner shares the machine with actors and the replay server: more intra-op
        # threads than it is given cores makes every update slower, not faster.
        torch.set_num_threads(config.torch_threads)
        # A device this machine lacks or a bad --resume PATH fails here, before any network
        # wait.
        resolve_device(config.device)
        if config.rank:  # a group's other ranks keep their files apart (rank 0's are the run's)
            config.run_dir = str(config.default_run_dir() / "ranks" / str(config.rank))
        resume = choose_resume(config.resume, config.default_run_dir(),
                               lambda line: log.info(line))
        session = open_for(config)
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    try:
        keys = Keys(config.run_id)
        spec = fetch_spec(session, keys, config.connect_timeout_s, stop)
        if (spec.env_id, spec.env_kwargs) != (config.env_id, config.env_kwargs):
            raise ConfigError(f"the replay server trains {spec.env_id!r} with env_kwargs "
                              f"{spec.env_kwargs or '{}'}, this learner was started with "
                              f"--env-id {config.env_id!r} and {config.env_kwargs or '{}'}")
        group = None
        if config.learners > 1:  # blocks until every rank is there
            config.device = rank_device(config.device, config.rank)
            log.info(f"learner rank {config.rank} of {config.learners}: meeting the others at "
                     f"{config.group_endpoint}")
            group = Group(config.rank, config.learners, config.group_endpoint,
                          resolve_device(config.device), config.group_timeout_s)
        service = LearnerService(config, spec, session, stop, resume, group)
    except ConfigError as exc:
        close_session(session, PROG)
        if stop:  # stopped while waiting for the replay server: not an error
            log.info(f"stopped ({stop.reason}) before training")
            return 0
        return fail(PROG, exc)
    finished = False
    try:
        finished = service.run()
    finally:
        service.finish(finished)
        close_session(session, PROG)
        if group is not None:
            group.close()
    # a rank above 0 leaves with its group; rank 0 ends the run (or is restarted with it)
    return 0 if finished or config.rank or stop.reason in ("SIGINT", "SIGTERM") else 1


if __name__ == "__main__":
    sys.exit(main())
