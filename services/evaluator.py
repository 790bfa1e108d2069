"""Evaluation while training (`eval_interval`, `eval_episodes`), as SB3's EvalCallback and RLlib's
evaluation workers do it: every interval the current policy runs deterministically on envs of
its own (episode i from reset(seed = 2^31 + seed + i), the same starts each time) and the
figures go to metrics.jsonl and TensorBoard (`eval/mean_return`, `eval/std_return`,
`eval/mean_length`); a new best is kept as `best_policy.npz` (the policy evaluated) and
`checkpoints/best.pt` (the learner's state), with `best.json` saying which.

`tpdeb-train` evaluates inline, between two updates (its cost is the episodes' time). In the
cluster `tpdeb-evaluator` is a process of its own: it asks the learner for the newest parameters
when an evaluation is due (the learner's global step from its stats, or its own clock), runs the
episodes, writes `best_policy.npz` and publishes the figures as its stats, which the learner
logs and answers with `best.pt`. The episodes are tpdeb-eval's (`tpdeb.evaluate`): the same
policy gives the same figures in both.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import zenoh

from tpdeb.protocol import DecodeError, Keys, Params, Stats, decode, encode
from tpdeb.services.config import ConfigError
from tpdeb.services.config.service import EvaluatorServiceConfig
from tpdeb.services.evaluate import Evaluation, make_env, run_episodes
from tpdeb.services.logs import rate_limited
from tpdeb.services.net.session import close_session, declare_publisher, fetch_spec, open_for
from tpdeb.services.net.wire import finite_values
from tpdeb.services.policy_file import Policy, acting_arrays, policy_bytes, policy_meta
from tpdeb.services.process import StopSignal, configure, fail, obey_control
from tpdeb.services.store.diskio import write_atomic

PROG = "tpdeb-evaluator"
# Training comes first: on a machine whose cores the actors and the learner fill, the evaluator
# takes what they leave (its reports come later, its figures are the same).
NICENESS = 10
log = logging.getLogger(PROG)
BEST_POLICY = "best_policy.npz"
BEST_RECORD = "best.json"


class Schedule:
    """When the next evaluation is due: every `steps` env steps or every `seconds` (one of them
    0; both 0: never). Pure: the step count and the clock are passed in."""

    def __init__(self, steps: int, seconds: float):
        self.steps, self.seconds = steps, seconds
        self.next_step: int | None = None
        self.next_time: float | None = None

    @property
    def enabled(self) -> bool:
        return bool(self.steps or self.seconds)

    def due(self, global_step: int, now: float) -> bool:
        if self.steps:
            if self.next_step is None:  # the first at the next multiple (a resumed run's too)
                self.next_step = (global_step // self.steps + 1) * self.steps
            return global_step >= self.next_step
        if self.seconds:
            if self.next_time is None:
                self.next_time = now + self.seconds
            return now >= self.next_time
        return False

    def done(self, global_step: int, now: float) -> None:
        if self.steps:
            self.next_step = (global_step // self.steps + 1) * self.steps
        else:
            self.next_time = now + self.seconds


class Best:
    """The best evaluation of a run, in {run_dir}/best.json, so that a restart keeps it."""

    def __init__(self, run_dir: str | Path):
        self.path = Path(run_dir) / BEST_RECORD
        try:
            self.record = json.loads(self.path.read_text())
            self.mean = float(self.record["mean_return"])
        except (OSError, ValueError, KeyError, TypeError):
            self.record, self.mean = {}, float("-inf")

    def offer(self, evaluation: Evaluation, version: int, global_step: int) -> bool:
        """Whether `evaluation` is a new best (then recorded)."""
        if not evaluation.mean > self.mean:
            return False
        self.mean = evaluation.mean
        self.record = {"mean_return": evaluation.mean, "std_return": evaluation.std,
                       "episodes": len(evaluation.returns), "param_version": version,
                       "global_step": global_step, "time": time.time()}
        write_atomic(self.path, lambda f: f.write(json.dumps(self.record, indent=1).encode()))
        return True


def figures(evaluation: Evaluation) -> dict[str, float]:
    """An evaluation as the metrics it logs."""
    return {"eval/mean_return": evaluation.mean, "eval/std_return": evaluation.std,
            "eval/mean_length": float(np.mean(evaluation.lengths))}


def policy_of(arrays, spec) -> Policy:
    """The numpy policy of a model's arrays (a learner's, or parameters as published)."""
    meta = policy_meta(spec.env_id, spec.env_kwargs, spec.obs_dim, spec.act_dim, spec.obs_clip,
                       spec.policy_std)
    return Policy({**acting_arrays(arrays), "action_low": spec.action_low,
                   "action_high": spec.action_high}, meta, source="the current policy")


def write_best_policy(run_dir: str | Path, policy: Policy) -> None:
    data = policy_bytes(policy.file_arrays, policy.low, policy.high, policy.meta)
    write_atomic(Path(run_dir) / BEST_POLICY, lambda f: f.write(data))


class Evaluator:
    """One run's evaluations, inline or in the evaluator process: the episodes on an env of
    its own (made at the first), each offered as the best, a new best's policy written."""

    def __init__(self, config, run_dir: str | Path, say):
        self.config, self.run_dir, self.say = config, Path(run_dir), say
        self.best = Best(run_dir)
        self.env = None

    def __call__(self, policy: Policy, version: int, step: int) -> tuple[Evaluation, bool]:
        if self.env is None:
            self.env = make_env(policy, video=False)
        evaluation = run_episodes(policy, self.env, self.config.eval_episodes,
                                  self.config.eval_seed)
        best = self.best.offer(evaluation, version, step)
        if best:
            write_best_policy(self.run_dir, policy)
        self.say(f"evaluation at {step:,} env steps (version {version:,}): {evaluation.mean:.1f} "
                 f"± {evaluation.std:.1f} over {len(evaluation.returns)} episodes"
                 f"{' (best so far)' if best else ''}")
        return evaluation, best

    def close(self) -> None:
        if self.env is not None:
            self.env.close()


class EvaluatorService:
    """The cluster's evaluator (see the module docstring)."""

    def __init__(self, config: EvaluatorServiceConfig, spec, session, stop: StopSignal):
        self.config, self.spec, self.session, self.stop = config, spec, session, stop
        self.keys = k = Keys(config.run_id)
        self.schedule = Schedule(*config.eval_every())
        self.evaluate = Evaluator(config, config.default_run_dir(), log.info)
        self.global_step = 0
        self.evaluations = 0
        self.last: dict[str, float] = {}
        self.log_bad = rate_limited(log)
        self.stats_publisher = declare_publisher(session, "stats", k.stats("evaluator", 0))
        self.subscribers = [session.declare_subscriber(k.stats_all, self._on_stats),
                            session.declare_subscriber(k.control, self._on_control)]
        self.token = session.liveliness().declare_token(k.alive("evaluator", 0))

    def _on_stats(self, sample) -> None:
        """The learner's global step (what a step interval counts); others' stats pass."""
        if "/stats/learner/" not in str(sample.key_expr):
            return
        try:
            stats = decode(sample.payload.to_bytes(), Stats)
        except DecodeError as exc:
            self.log_bad(exc.kind, f"dropped bad learner stats ({exc})")
            return
        self.global_step = int(stats.values.get("global_step", self.global_step))

    def _on_control(self, sample) -> None:
        obey_control(sample, self.stop, self.log_bad)

    def newest_params(self) -> Params | None:
        for reply in self.session.get(self.keys.params_latest, timeout=5.0):
            if reply.ok is None:
                continue
            try:
                return decode(reply.ok.payload.to_bytes(), Params,
                              max_bytes=self.config.max_message_bytes)
            except DecodeError as exc:
                self.log_bad(exc.kind, f"dropped bad parameters ({exc})")
        return None

    def evaluate_now(self) -> None:
        params = self.newest_params()
        if params is None:
            return  # no learner answering yet: the next check asks again
        step = self.global_step
        evaluation, best = self.evaluate(policy_of(params.arrays, self.spec), params.version,
                                         step)
        self.evaluations += 1
        self.last = {**figures(evaluation), "eval/param_version": params.version,
                     "eval/global_step": step, "eval/count": self.evaluations,
                     "eval/best": float(best)}
        self.publish()

    def publish(self) -> None:
        self.stats_publisher.put(encode(Stats(
            role="evaluator", ident="0", values=finite_values(self.last),
            episode_returns=np.zeros(0), episode_lengths=np.zeros(0, np.int64))))

    def run(self) -> None:
        last_stats = 0.0
        while not self.stop:
            now = time.monotonic()
            if self.schedule.due(self.global_step, now):
                self.evaluate_now()
                self.schedule.done(self.global_step, time.monotonic())
            elif now - last_stats >= self.config.stats_interval_s:
                self.publish()  # a heartbeat: the cluster watches every service's stats
                last_stats = now
            self.stop.wait(0.2)

    def close(self) -> None:
        self.evaluate.close()
        self.token.undeclare()


def main(argv: list[str] | None = None) -> int:
    try:
        config = configure(EvaluatorServiceConfig, argv, PROG,
                           "TPDEB evaluator: runs the current policy deterministically every "
                           "eval_interval, for the learner to log and keep the best.")
        os.nice(NICENESS)
        session = open_for(config)
    except ConfigError as exc:
        return fail(PROG, exc)
    stop = StopSignal().install()
    service = None
    try:
        spec = fetch_spec(session, Keys(config.run_id), config.connect_timeout_s, stop)
        if spec.env_id != config.env_id:
            raise ConfigError(f"the run trains {spec.env_id!r}; this evaluator was started with "
                              f"--env-id {config.env_id!r}")
        service = EvaluatorService(config, spec, session, stop)
        service.run()
    except ConfigError as exc:
        if stop:
            return 0
        return fail(PROG, exc)
    except zenoh.ZError:
        if not stop:
            raise
    finally:
        if service is not None:
            service.close()
        close_session(session, PROG)
    log.info(f"stopped ({stop.reason}) after {service.evaluations if service else 0} "
             "evaluations")
    return 0


if __name__ == "__main__":
    sys.exit(main())
