"""`tpdeb-train`: actor, replay and learner components in one process (Sample Factory's serial
mode): the same core and the same configuration as the distributed services, connected in
memory. For debugging, tests and quick experiments on one core.

Loop: the actor steps its vector env; every completed fragment is inserted into the dual replay
when the rate limiter allows it, otherwise the learner trains until it does; the learner trains
whenever the limiter allows a sample, so the replay ratio is exact whatever the machine's speed.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from tpdeb.services.config import ConfigError, resolve, to_toml
from tpdeb.services.config.presets import shown
from tpdeb.services.config.train import TrainConfig
from tpdeb.services.envs import make_vector_env, space_dims
from tpdeb.services.seeding import seed_everything
from tpdeb.services.store.checkpoint import save_training
from tpdeb.services.store.metrics import MetricsWriter, hyperparameter_table
from tpdeb.tpdeb_core.fragments import Collector, stack_fragments
from tpdeb.tpdeb_core.learner import Learner
from tpdeb.tpdeb_core.model import ActorCritic


class SerialRunner:
    """Wires the core components together; `run()` trains to total_timesteps."""

    def __init__(self, config: TrainConfig, out=sys.stdout):
        self.config = config
        self.out = out
        torch.set_num_threads(config.torch_threads)
        seed_everything(config.seed)
        self.envs = make_vector_env(config.env_id, config.num_envs)
        obs_dim, act_dim, low, high = space_dims(self.envs)
        self.model = ActorCritic(obs_dim, act_dim, config.hidden_sizes, config.init_log_std,
                                 config.obs_clip)
        self.learner = Learner(self.model, config.loss_config())
        # The actor acts with its own copy, refreshed on publication as a remote actor would be.
        self.collector = Collector(
            self.envs, self.model.numpy_policy(), config.fragment_len, config.gamma, low, high,
            seed=config.seed)
        self.replay = config.make_replay()
        self.limiter = config.rate_limiter()
        self.run_dir = config.default_run_dir()
        self.metrics = MetricsWriter(self.run_dir)
        self.recent_returns: deque[float] = deque(maxlen=20)
        self.loss_sums: dict[str, float] = {}
        self.loss_count = 0
        self.update_time_s = 0.0
        self.sample_lag_sum = 0.0

    @property
    def global_step(self) -> int:
        return self.collector.env_steps

    def progress(self) -> float:
        return min(1.0, self.global_step / self.config.total_timesteps)

    # -- the three components' jobs
    def insert(self, fragment) -> None:
        self.learner.observe(fragment)
        priority = fragment.initial_priority(
            self.config.priority_mode, self.config.priority_kappa, self.config.gamma,
            self.collector.policy.reward_scale())
        self.replay.insert(fragment, priority, fragment.num_steps)
        self.limiter.on_insert(fragment.num_steps)

    def learn(self) -> None:
        cfg = self.config
        beta = cfg.beta_start + (1.0 - cfg.beta_start) * self.progress()
        if cfg.anneal_lr:
            self.learner.set_learning_rate(cfg.learning_rate * max(1e-3, 1.0 - self.progress()))
        sample = self.replay.sample(cfg.batch_fragments, beta)
        self.limiter.on_sample(cfg.batch_steps)
        start = time.perf_counter()
        result = self.learner.step(stack_fragments(sample.items), sample.keys, sample.weights,
                                   sample.from_prioritized, sample.step_weights)
        self.update_time_s += time.perf_counter() - start
        self.replay.update_priorities(result.priority_keys, result.priorities)
        self.sample_lag_sum += float(np.mean(
            [self.learner.updates - 1 - f.policy_version for f in sample.items]))
        for key, value in result.metrics.items():
            self.loss_sums[key] = self.loss_sums.get(key, 0.0) + value
        self.loss_count += 1
        if self.learner.updates % cfg.params_publish_interval == 0:
            self.collector.set_policy(self.model.numpy_policy(), self.learner.updates)

    def run(self) -> dict:
        cfg = self.config
        (self.run_dir / "config.toml").write_text(to_toml(cfg))
        self.metrics.text("hyperparameters", hyperparameter_table(cfg))
        self.say(f"run dir {self.run_dir} | {cfg.env_id} | {cfg.total_timesteps:,} steps "
                 f"| seed {cfg.seed} | {cfg.algo} | preset: {shown(cfg.preset)}")
        start = last_log = time.perf_counter()
        last_step = 0
        interrupted = False
        try:
            while self.global_step < cfg.total_timesteps:
                for fragment in self.collector.step():
                    while not self.limiter.can_insert(fragment.num_steps):
                        self.learn()
                    self.insert(fragment)
                while self.limiter.can_sample(cfg.batch_steps):
                    self.learn()
                self.log_episodes()
                now = time.perf_counter()
                if now - last_log >= cfg.log_interval_s:
                    self.log_progress((self.global_step - last_step) / (now - last_log))
                    last_log, last_step = now, self.global_step
        except KeyboardInterrupt:
            interrupted = True
            self.say("interrupted: writing the checkpoint and stopping")
        elapsed = time.perf_counter() - start
        summary = self.log_progress(self.global_step / max(elapsed, 1e-9))
        checkpoint = self.save_checkpoint()
        self.say(f"{'stopped' if interrupted else 'done'} after {self.global_step:,} steps in "
                 f"{elapsed:.0f} s; checkpoint {checkpoint}")
        self.metrics.close()
        self.envs.close()
        return {**summary, "interrupted": interrupted, "elapsed_s": elapsed}

    # -- reporting
    def say(self, line: str) -> None:
        print(line, file=self.out, flush=True)

    def log_episodes(self) -> None:
        for episode_return, length in self.collector.episodes:
            self.recent_returns.append(episode_return)
            self.metrics.log(self.global_step, {"charts/episodic_return": episode_return,
                                                "charts/episodic_length": length})
        self.collector.episodes.clear()

    def log_progress(self, sps: float) -> dict:
        values = {"charts/SPS": sps, "charts/learning_rate": self.learner.optimizer
                  .param_groups[0]["lr"]}
        if self.loss_count:
            values.update({k: v / self.loss_count for k, v in self.loss_sums.items()})
            values["perf/update_ms"] = 1e3 * self.update_time_s / self.loss_count
            values["replay/sample_age_updates"] = self.sample_lag_sum / self.loss_count
        values["actor/param_version_lag"] = self.learner.updates - self.collector.policy_version
        values["perf/updates"] = self.learner.updates
        values.update({f"replay/{k}": v for k, v in self.replay.stats().items()
                       if isinstance(v, (int, float))})
        values["replay/samples_per_insert"] = self.limiter.stats()["samples_per_insert_achieved"]
        self.metrics.log(self.global_step, values)
        self.metrics.flush()
        self.loss_sums, self.loss_count, self.update_time_s, self.sample_lag_sum = {}, 0, 0.0, 0.0
        mean_return = float(np.mean(self.recent_returns)) if self.recent_returns else float("nan")
        self.say(f"[{self.global_step:>10,}/{self.config.total_timesteps:,}] SPS {sps:7,.0f} | "
                 f"return {mean_return:9.1f} (last {len(self.recent_returns)}) | "
                 f"updates {self.learner.updates:,} | replay {len(self.replay):,} fragments")
        return {"global_step": self.global_step, "mean_return": mean_return, "sps": sps,
                "updates": self.learner.updates}

    def save_checkpoint(self) -> Path:
        return save_training(self.run_dir, self.learner, self.config, self.global_step, "final")


def main(argv: list[str] | None = None) -> int:
    try:
        config = resolve(TrainConfig, argv, "tpdeb-train",
                         "Train TPDEB in one process (actor, replay and learner in memory).")
        runner = SerialRunner(config)
    except ConfigError as exc:
        print(f"tpdeb-train: error: {exc}", file=sys.stderr)
        return 2
    result = runner.run()
    return 130 if result["interrupted"] else 0


if __name__ == "__main__":
    sys.exit(main())
