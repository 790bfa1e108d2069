"""`tpdeb-train`: the replay server, the learner service and an actor in one process (Sample
Factory's serial mode): the same objects the distributed processes run, wired to an in-memory
bus instead of Zenoh, and stepped in turn by one thread, so a run is reproducible from its seed.
For debugging, tests and quick experiments on one core.

The schedule: the actor steps its vector env when its outbox has room, asking for the newest
parameters at its fragment boundaries; the replay server takes what arrived (ingesting what the
rate limiter allows, acknowledging it); the learner trains while the limiter allows a sample. A
query that waits for an answer runs the replay's and the learner's loops meanwhile (the bus's
pump), as their processes would. What changes against the cluster is the wiring, nothing else.
"""

from __future__ import annotations

import dataclasses
import logging
import sys
import time

import torch

from tpdeb.services.actor import ActorService
from tpdeb.services.budget import clock
from tpdeb.services.config import ConfigError, to_toml
from tpdeb.services.config.presets import shown
from tpdeb.services.config.service import (
    ActorServiceConfig,
    LearnerServiceConfig,
    ReplayServiceConfig,
)
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.device import describe
from tpdeb.services.envs import make_vector_env, space_dims
from tpdeb.services.evaluator import Evaluator, Schedule, figures, policy_of
from tpdeb.services.learner import LearnerService
from tpdeb.services.net.memory import MemoryBus
from tpdeb.services.net.wire import run_spec
from tpdeb.services.preflight import preflight, run_dir_resume
from tpdeb.services.process import StopSignal, configure, fail
from tpdeb.services.replay import ReplayServer
from tpdeb.services.store.checkpoint import choose_resume
from tpdeb.services.store.metrics import hyperparameter_table

PROG = "tpdeb-train"
RUN_ID = "serial"
log = logging.getLogger(PROG)


class SerialRunner:
    """The three services on one bus; `run()` trains to total_timesteps (or for
    train_for_seconds, whichever binds first)."""

    def __init__(self, config: TrainConfig):
        if config.replay_shards != 1:
            raise ConfigError(f"replay_shards={config.replay_shards}: one process has one "
                              "replay; shards are for a cluster (tpdeb-cluster --set "
                              "replay_shards=K)")
        if config.max_batch_fragments > config.batch_fragments:
            raise ConfigError(f"max_batch_fragments={config.max_batch_fragments}: batch growth "
                              "follows a learner that is the limit of a cluster; one process "
                              "takes turns (tpdeb-cluster --set max_batch_fragments=N)")
        self.config = config
        torch.set_num_threads(config.torch_threads)
        self.run_dir = config.default_run_dir()
        settings = {**dataclasses.asdict(config), "run_dir": str(self.run_dir), "run_id": RUN_ID}

        def config_of(cls, **more):  # each service's config: the settings it holds
            names = {f.name for f in dataclasses.fields(cls)}
            return cls(**{k: v for k, v in settings.items() if k in names}, **more)

        self.stop = StopSignal()
        self.bus = MemoryBus()
        envs = make_vector_env(config.env_id, config.num_envs, config.env_kwargs)
        spec = run_spec(config, *space_dims(envs))
        # The learner first: it seeds torch and numpy as its process does. It resumes from the
        # run dir's newest checkpoint as the cluster's does (`resume`); the replay is in memory
        # and starts empty.
        resume = choose_resume(config.resume, self.run_dir, lambda line: log.info(line))
        self.learner = LearnerService(config_of(LearnerServiceConfig), spec, self.bus.session(),
                                      self.stop, resume)
        self.step_base = self.learner.global_step  # the env steps of the run being continued
        self.replay = ReplayServer(config_of(ReplayServiceConfig, persist=False), spec,
                                   self.bus.session(), self.stop)
        self.actor = ActorService(config_of(ActorServiceConfig, actor_id=0), spec, envs,
                                  self.bus.session(), self.stop)
        self.bus.pump = self._pump
        self.requests = 0
        # Evaluation inline, between two updates (services/evaluator.py): its time is the run's.
        self.schedule = Schedule(*config.eval_every())
        self.evaluator = Evaluator(config, self.run_dir, log.info)
        self.eval_s = 0.0

    def _pump(self) -> None:
        self.replay.poll(0.0)
        self.learner.serve_params()

    # -- the schedule
    def act(self) -> None:
        actor = self.actor
        actor.refresh_params()
        fragments = actor.collector.step()
        if fragments and self.learner.param_version() > actor.policy_version:
            actor.ask_params()  # the newest version, for the next fragments
        for fragment in fragments:
            actor.send_now(fragment)
        if actor.collector.episodes:
            actor.publish_stats(0.0)

    def learn(self) -> None:
        batch_steps = self.config.batch_steps
        while self.replay.limiter.can_sample(batch_steps) and len(self.replay.replay):
            self.requests += 1
            batch = self.learner.fetch(self.requests)
            if batch is None:
                return
            self.learner.train_on(batch)
            self.replay.poll(0.0)  # its priorities; the fragments the limiter now lets in

    def run(self) -> dict:
        cfg, learner = self.config, self.learner
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "config.toml").write_text(to_toml(cfg))
        if not learner.resumed:
            learner.metrics.text("hyperparameters", hyperparameter_table(cfg))
        learner.budget.restart_clock()
        log.info(f"run dir {self.run_dir} | {cfg.env_id} | {learner.budget.describe()} | seed "
                 f"{cfg.seed} | {cfg.algo} | preset: {shown(cfg.preset)} | learner on "
                 f"{describe(learner.device)}")
        if learner.resumed:
            log.info(f"continuing at {self.step_base:,} env steps and "
                     f"{clock(learner.budget.spent_before)} of training; the replay is kept in "
                     f"memory and starts empty, so updates wait for "
                     f"{cfg.learning_starts_fragments} new fragments")
        learner.publish_params(eager=True)
        self.actor.wait_for_params()
        start = last_log = last_checkpoint = time.perf_counter()
        last_step, interrupted = learner.global_step, False
        try:
            while not learner.limit_reached():
                if self.actor.outbox.wait_for_room(0.0):
                    self.act()
                self.replay.poll(0.0)
                learner.global_step = self.step_base + self.replay.inserted_steps
                self.learn()
                learner.drain_stats()
                if self.schedule.due(learner.global_step, learner.budget.elapsed()):
                    self.evaluate()
                now = time.perf_counter()
                if now - last_log >= cfg.log_interval_s:
                    self.replay.publish_stats()
                    learner.drain_stats()
                    learner.log_progress((learner.global_step - last_step) / (now - last_log))
                    last_log, last_step = now, learner.global_step
                if cfg.checkpoint_interval_s and now - last_checkpoint >= cfg.checkpoint_interval_s:
                    learner.periodic_checkpoint()
                    last_checkpoint = now
        except KeyboardInterrupt:
            interrupted = True
            log.info("interrupted: writing the checkpoint and stopping")
        return self.finish(start, interrupted)

    def evaluate(self) -> None:
        """The current policy's evaluation, logged; a new best kept (best_policy.npz, best.pt)."""
        learner = self.learner
        started = time.perf_counter()
        step, version = learner.global_step, learner.param_version()
        evaluation, best = self.evaluator(policy_of(learner.learner.model.arrays(), learner.spec),
                                          version, step)
        learner.metrics.log(step, figures(evaluation))
        if best:
            learner.save_best(evaluation.mean, version)
        self.schedule.done(step, learner.budget.elapsed())
        self.eval_s += time.perf_counter() - started

    def finish(self, start: float, interrupted: bool) -> dict:
        learner = self.learner
        elapsed = time.perf_counter() - start
        self.replay.publish_stats()
        learner.drain_stats()
        learner.log_progress((learner.global_step - self.step_base) / max(elapsed, 1e-9))
        summary = {"global_step": learner.global_step, "mean_return": learner.mean_return(),
                   "updates": learner.learner.updates, "interrupted": interrupted,
                   "elapsed_s": elapsed, "ended_by": learner.ended_by, "eval_s": self.eval_s}
        if self.eval_s:
            log.info(f"evaluation took {self.eval_s:.1f} s of the run's {elapsed:.1f} s "
                     f"({100 * self.eval_s / max(elapsed, 1e-9):.1f} %)")
        learner.finish(not interrupted)
        self.replay.close()
        self.actor.close()
        self.evaluator.close()
        return summary


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(TrainConfig, argv, PROG,
                           "Train TPDEB in one process (replay, learner and actor in memory).")
        preflight(config)
        run_dir_resume(config)
        runner = SerialRunner(config)
    except ConfigError as exc:
        return fail(PROG, exc)
    result = runner.run()
    return 130 if result["interrupted"] else 0


if __name__ == "__main__":
    sys.exit(main())
