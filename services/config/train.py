"""The training configuration shared by the single-process runner and the distributed services.

Defaults are a measured starting point (a prototype's, on InvertedPendulum and HalfCheetah;
the task presets in deploy/presets/ tune them). Flag names follow CleanRL where it has one.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

from tpdeb.protocol.messages import MAX_BATCH_SIZE, MAX_REPLAY_SHARDS
from tpdeb.services.config import ConfigError
from tpdeb.services.device import check_device_setting
from tpdeb.tpdeb_core.loss_config import LossConfig, PriorityConfig
from tpdeb.tpdeb_core.policy import POLICY_STDS
from tpdeb.tpdeb_core.rate_limiter import RateLimiter
from tpdeb.tpdeb_core.replay import RETENTIONS, DualReplay

ALGOS = ("tpdeb", "impact", "ppo-per")


@dataclass
class RunSettings:
    """Which run this is: what every process that trains or acts for it holds."""

    SECTION = "run"

    exp_name: str = "tpdeb"
    """name of this experiment, part of the default run directory"""
    algo: str = "tpdeb"
    """tpdeb | impact | ppo-per: the algorithm (the paper's method or one of its baselines);
    impact and ppo-per fix the settings that define them"""
    preset: str = "auto"
    """auto: the task's preset deploy/presets/{env_id}.toml when there is one (with
    train_for_seconds > 0, its race preset deploy/presets/race/{env_id}.toml first) | none | a
    TOML file; settings given by --config, TPDEB_* or flags override the preset's"""
    env_id: str = "HalfCheetah-v5"
    """gymnasium environment id (continuous actions, flat observations); module:Env-v0
    imports module (from the current directory first) to register Env-v0"""
    env_kwargs: str = ""
    """keyword arguments for gymnasium.make: a JSON object ('{"ctrl_cost_weight": 0.2}') or a
    TOML inline table ('ctrl_cost_weight = 0.2'); in a config file also a table
    [run.env_kwargs]; every peer of the run must use the same"""
    seed: int = 1
    """seed of torch, numpy and every environment (env i of actor a gets seed + 1000 a + i)"""
    total_timesteps: int = 1_000_000
    """environment steps to train for"""
    train_for_seconds: float = 0.0
    """seconds of training after which the run ends (0: no limit); with total_timesteps,
    whichever binds first ends it, and schedules follow the one further along"""
    run_dir: str = ""
    """run directory; empty means runs/{env_id}__{exp_name}__{seed}__{unix time}"""
    log_interval_s: float = 5.0
    """seconds between progress lines"""

    def __post_init__(self):
        chain_post_init(RunSettings, self)
        from tpdeb.services.envs import canonical_env_kwargs

        try:
            self.env_kwargs = canonical_env_kwargs(self.env_kwargs)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        check(self, [
            (0 <= self.seed < 2**31, "seed", "must be an integer in [0, 2^31)"),
            (self.total_timesteps >= 1, "total_timesteps", "must be ≥ 1"),
            (math.isfinite(self.train_for_seconds) and self.train_for_seconds >= 0,
             "train_for_seconds", "must be a finite number ≥ 0 (0: no limit)"),
            (self.algo in ALGOS, "algo", f"must be one of {', '.join(ALGOS)}"),
        ])

    def default_run_dir(self) -> Path:
        if self.run_dir:
            return Path(self.run_dir)
        return Path("runs") / f"{self.env_id}__{self.exp_name}__{self.seed}__{int(time.time())}"


@dataclass
class ActingSettings:
    """How an actor collects: what it holds besides the run's identity (the fragment length,
    the networks and γ come to it in the run spec)."""

    SECTION = "actor"

    num_envs: int = 8
    """environments stepped together by an actor"""
    trajectory_compression: str = "none"
    """none | zstd: lossless compression of the fragments actors send"""

    def __post_init__(self):
        chain_post_init(ActingSettings, self)
        check(self, [
            (self.num_envs >= 1, "num_envs", "must be ≥ 1"),
            (self.trajectory_compression in ("none", "zstd"), "trajectory_compression",
             "must be none or zstd"),
        ])


@dataclass
class EvalSettings:
    """Evaluation while training: the current policy, deterministically, on envs of its own."""

    SECTION = "eval"

    eval_interval: str = "100000"
    """env steps between evaluations of the current policy, or seconds with an s suffix
    ('60s'); 0: none. Each logs eval/mean_return (metrics, TensorBoard) and a new best is kept
    as best_policy.npz and checkpoints/best.pt"""
    eval_episodes: int = 5
    """episodes per evaluation (episode i from reset(seed = 2^31 + seed + i): the same starts
    every time, and none an actor's env uses)"""

    def __post_init__(self):
        chain_post_init(EvalSettings, self)
        try:
            self.eval_every()
        except ValueError:
            raise ConfigError(f"eval_interval={self.eval_interval!r}: expected env steps (100000), "
                              "seconds with an s suffix (60s) or 0 (no evaluation)") from None
        check(self, [(self.eval_episodes >= 1, "eval_episodes", "must be ≥ 1")])

    def eval_every(self) -> tuple[int, float]:
        """(env steps, seconds) between evaluations; one of them 0. (0, 0): none."""
        text = str(self.eval_interval).strip().lower()
        if text.endswith("s"):
            seconds = float(text[:-1])
            if not (math.isfinite(seconds) and seconds >= 0):
                raise ValueError(text)
            return 0, seconds
        steps = int(float(text))
        if steps < 0 or steps != float(text):
            raise ValueError(text)
        return steps, 0.0

    @property
    def eval_seed(self) -> int:
        return (2**31 + self.seed) % 2**32


def chain_post_init(cls, obj) -> None:
    """The next `__post_init__` after `cls`'s in `obj`'s classes (the groups check in turn)."""
    more = getattr(super(cls, obj), "__post_init__", None)
    if more is not None:
        more()


@dataclass
class ModelSettings:
    """The fragments and the networks: what the run spec carries to the actors with γ and the
    priority definition."""

    SECTION = "model"

    fragment_len: int = 64
    """T: steps per fragment (a replay item)"""
    hidden_sizes: tuple[int, ...] = (64, 64)
    """hidden layer sizes of the policy and value MLPs"""
    init_log_std: float = 0.0
    """initial log standard deviation of the Gaussian policy"""
    obs_clip: float = 10.0
    """clip normalised observations to ±this"""
    policy_std: str = "global"
    """global: one learned log-std per action dimension | state: a log-std head on the policy's
    last hidden layer, bounded to [-5, 2]"""

    def __post_init__(self):
        chain_post_init(ModelSettings, self)
        self.hidden_sizes = tuple(self.hidden_sizes)
        check(self, [
            (self.policy_std in POLICY_STDS, "policy_std",
             f"must be one of {', '.join(POLICY_STDS)}"),
            (self.fragment_len >= 2, "fragment_len", "must be ≥ 2"),
            (len(self.hidden_sizes) >= 1 and min(self.hidden_sizes) >= 1, "hidden_sizes",
             "needs at least one positive layer size"),
        ])


@dataclass
class ReplaySettings:
    """The dual buffer and how it is sampled: what the replay server and the learner, which
    asks for batches, share."""

    SECTION = "replay"

    batch_fragments: int = 8
    """fragments per learner batch (B); a batch holds B·T steps"""
    max_batch_fragments: int = 0
    """batch growth: the learner doubles its batch from batch_fragments up to this many
    fragments while it is the run's limit and a doubled batch's update costs at most 1.5× the
    smaller one's (a GPU's headroom turned into env steps; the replay ratio is kept, so a
    larger batch means fewer updates per env step); 0: batch_fragments, no growth"""
    replay_ratio: float = 16.0
    """sampled steps per inserted step (Reverb's samples_per_insert)"""
    max_replay_ratio: float = 0.0
    """upper end of a replay-ratio band: while inserts are scarce (a thin link, slow actors)
    the learner may replay up to this many sampled steps per inserted step instead of waiting,
    and inserts still wait below replay_ratio; 0: one fixed ratio"""
    rate_error_buffer_steps: float = 0.0
    """rate limiter tolerance in sampled steps; 0 picks twice the smallest deadlock-free value"""
    learning_starts_fragments: int = 8
    """fragments inserted before the first update"""
    prioritized_capacity: int = 64
    """N_p: fragments held by the prioritized buffer"""
    uniform_capacity_steps: int = 8192
    """N_u: steps held by the uniform FIFO buffer"""
    zeta: float = 0.2
    """share of each batch drawn from the prioritized buffer (0 = uniform replay only)"""
    alpha: float = 1.0
    """priority exponent: sampling ∝ priority^alpha"""
    beta_start: float = 0.4
    """initial importance-weight exponent, annealed linearly to 1 over training"""
    replay_retention: str = "priority"
    """priority: a full prioritized buffer gives up its lowest-priority fragment (TPDEB) | fifo:
    its oldest (a FIFO still sampled by priority, the PPO+PER baseline)"""
    replay_shards: int = 1
    """replay servers (shards): actor a writes to shard a mod K, the learner draws each batch
    from all in proportion to what they hold; each holds 1/K of the capacities above, with
    its own log, snapshots and rate limiter"""

    def __post_init__(self):
        chain_post_init(ReplaySettings, self)
        check(self, [
            (self.batch_fragments >= 1, "batch_fragments", "must be ≥ 1"),
            (self.max_batch_fragments == 0 or self.max_batch_fragments >= self.batch_fragments,
             "max_batch_fragments", f"must be 0 (no growth) or ≥ batch_fragments="
             f"{self.batch_fragments}"),
            (self.max_batch_fragments <= MAX_BATCH_SIZE, "max_batch_fragments",
             f"must be ≤ {MAX_BATCH_SIZE} (the largest batch a sample reply carries)"),
            (self.prioritized_capacity >= 1, "prioritized_capacity", "must be ≥ 1"),
            (0.0 <= self.zeta <= 1.0, "zeta", "must be in [0, 1]"),
            (0.0 <= self.beta_start <= 1.0, "beta_start", "must be in [0, 1]"),
            (self.alpha >= 0.0, "alpha", "must be ≥ 0"),
            (self.replay_retention in RETENTIONS, "replay_retention",
             f"must be one of {', '.join(RETENTIONS)}"),
            (self.learning_starts_fragments >= 1, "learning_starts_fragments", "must be ≥ 1"),
            (1 <= self.replay_shards <= MAX_REPLAY_SHARDS, "replay_shards",
             f"must be in [1, {MAX_REPLAY_SHARDS}]"),
            (self.max_replay_ratio == 0.0 or self.max_replay_ratio >= self.replay_ratio,
             "max_replay_ratio", f"must be 0 (a fixed ratio) or ≥ replay_ratio="
             f"{self.replay_ratio} (the upper end of the band)"),
        ])


COMPILE_MODES = ("auto", "off")


@dataclass
class LearnerSettings:
    """How the learner runs and publishes, besides the loss."""

    SECTION = "learner"

    anneal_lr: bool = False
    """anneal the learning rate linearly to 0 over the run (its steps or its seconds,
    whichever is further along)"""
    params_publish_interval: int = 1
    """learner updates between parameter publications to the actors"""
    params_dtype: str = "float32"
    """float32 | float16: precision of the weights broadcast to the actors (normaliser
    statistics always travel in float64)"""
    torch_threads: int = 1
    """torch intra-op threads (1 leaves the other core to the environments)"""
    device: str = "auto"
    """auto | cpu | cuda | cuda:N: where the learner's networks train (auto: the first GPU
    when torch sees one, else the CPU)"""
    anneal_log_std: bool = False
    """hold the global log-std under a ceiling that falls linearly from init_log_std to
    final_log_std over the run (less exploration noise late in training); the KL term reads
    the behaviour policies' log-std under the same ceiling"""
    final_log_std: float = -2.0
    """the ceiling of the log-std at the end of the run (with anneal_log_std)"""
    schedule_steps: int = 0
    """env steps by which anneal_lr and anneal_log_std reach their end values, when that comes
    before the run's own end (0: the run's steps or seconds, whichever is further along); the
    rest of the run trains at the end values (a clock budget longer than the steps a preset
    was tuned for)"""
    obs_norm_steps: int = 0
    """env steps after which the observation normaliser holds its moments (0: it takes in every
    batch's observations for the whole run); the policy then learns on inputs that no longer
    shift under it as the states it visits change"""
    compile: str = "auto"
    """auto: the update runs eagerly from the first batch while torch.compile prepares it in
    the background (the cache under ~/.cache/tpdeb makes later starts quick), then runs
    compiled | off: eager throughout (for debugging the loss)"""
    checkpoint_interval_s: float = 60.0
    """seconds between periodic checkpoints in {run_dir}/checkpoints (0: only the final one)"""
    keep_checkpoints: int = 3
    """periodic checkpoints kept; older ones are deleted once a newer one is in place"""
    resume: str = "auto"
    """auto: continue from the run dir's newest loadable checkpoint (a fresh start if there is
    none) | never: start fresh (earlier checkpoints are moved aside) | PATH: continue from that
    checkpoint file"""
    learners: int = 1
    """data-parallel learner processes (torch.distributed: gloo on CPUs, NCCL between GPUs):
    each samples batch_fragments of its own per update and the gradients are averaged, so an
    update learns from learners × batch_fragments fragments; rank 0 publishes the parameters
    and writes checkpoints and metrics"""

    def __post_init__(self):
        chain_post_init(LearnerSettings, self)
        check(self, [
            (self.params_publish_interval >= 1, "params_publish_interval", "must be ≥ 1"),
            (self.params_dtype in ("float32", "float16"), "params_dtype",
             "must be float32 or float16"),
            (self.torch_threads >= 1, "torch_threads", "must be ≥ 1"),
            (self.compile in COMPILE_MODES, "compile", f"must be one of {COMPILE_MODES}"),
            (self.checkpoint_interval_s >= 0, "checkpoint_interval_s",
             "must be ≥ 0 (0 turns periodic checkpoints off)"),
            (self.keep_checkpoints >= 1, "keep_checkpoints", "must be ≥ 1"),
            (self.schedule_steps >= 0, "schedule_steps",
             "must be ≥ 0 (0: the schedules follow the run's own budget)"),
            (self.obs_norm_steps >= 0, "obs_norm_steps",
             "must be ≥ 0 (0: the normaliser follows the whole run)"),
            (1 <= self.learners <= 1024, "learners", "must be in [1, 1024]"),
            (bool(self.resume.strip()), "resume", "use auto, never or the path of a checkpoint"),
            (check_device_setting(self.device) is None, "device",
             check_device_setting(self.device) or ""),
        ])


def check(config, rules: list[tuple[bool, str, str]]) -> None:
    """Refuse the first broken rule, naming the setting and its value."""
    for ok, name, rule in rules:
        if not ok:
            raise ConfigError(f"{name}={getattr(config, name)!r}: {rule}")


@dataclass
class SamplingConfig(RunSettings, ModelSettings, ReplaySettings, PriorityConfig):
    """What a replay is built from: the run, its fragments, the buffers and the priorities (the
    replay server holds this; the learner holds it with the loss)."""

    def __post_init__(self):
        try:  # the groups' checks; the core's raise ValueError
            super().__post_init__()
        except ConfigError:
            raise
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if self.uniform_capacity_steps < self.fragment_len:
            raise ConfigError(
                f"uniform_capacity_steps={self.uniform_capacity_steps} cannot hold one fragment "
                f"of fragment_len={self.fragment_len} steps: raise it")
        self.rate_limiter()  # refuses deadlocking replay-ratio settings

    @property
    def batch_steps(self) -> int:
        return self.batch_fragments * self.fragment_len

    @property
    def largest_batch(self) -> int:
        """The most fragments a batch may hold (batch growth's ceiling)."""
        return max(self.batch_fragments, self.max_batch_fragments)

    def rate_limiter(self) -> RateLimiter:
        largest = self.largest_batch * self.fragment_len  # the limiter is built for it
        minimum = RateLimiter.min_error_buffer(
            self.replay_ratio, self.fragment_len, largest) if self.replay_ratio > 0 else 0
        error_buffer = self.rate_error_buffer_steps or 2.0 * minimum
        capacity = self.prioritized_capacity * self.fragment_len + self.uniform_capacity_steps
        try:
            return RateLimiter(
                samples_per_insert=self.replay_ratio,
                min_size_to_sample=self.learning_starts_fragments * self.fragment_len,
                error_buffer=error_buffer,
                insert_steps=self.fragment_len,
                sample_steps=largest,
                capacity_steps=capacity,
                max_samples_per_insert=self.max_replay_ratio or None,
            )
        except ValueError as exc:
            raise ConfigError(f"replay ratio settings: {exc}") from None

    def shard_part(self, shard: int) -> SamplingConfig:
        """Replay shard `shard`'s settings (`replay_shards` > 1): 1/K of the capacities and of
        the fragments before sampling starts (rounded up), its own sampling seed. K = 1: these."""
        k = self.replay_shards
        if k == 1:
            return self
        return dataclasses.replace(
            self, prioritized_capacity=-(-self.prioritized_capacity // k),
            uniform_capacity_steps=max(self.fragment_len, -(-self.uniform_capacity_steps // k)),
            learning_starts_fragments=-(-self.learning_starts_fragments // k),
            seed=(self.seed + 7919 * shard) % 2**31)

    def make_replay(self) -> DualReplay:
        return DualReplay(
            self.prioritized_capacity, self.uniform_capacity_steps, zeta=self.zeta,
            alpha=self.alpha, seed=self.seed, priority_mode=self.priority_mode,
            retention=self.replay_retention)


@dataclass
class LearningConfig(SamplingConfig, LearnerSettings, LossConfig):
    """What the learner trains by: the replay's settings (it asks for the batches), its own and
    the loss's."""

    def __post_init__(self):
        chain_post_init(LearningConfig, self)
        if self.anneal_log_std and self.policy_std != "global":
            raise ConfigError(f"anneal_log_std=true holds the global log-std, not "
                              f"policy_std={self.policy_std!r}: set policy_std=global")
        if self.max_batch_fragments > self.batch_fragments and self.learners > 1:
            raise ConfigError(
                f"max_batch_fragments={self.max_batch_fragments} (batch growth) is for one "
                f"learner, not learners={self.learners}: the ranks would time and grow apart; "
                f"set batch_fragments to the batch each rank should take")

    def loss_config(self) -> LossConfig:
        names = {f.name for f in dataclasses.fields(LossConfig)}
        try:
            return LossConfig(**{k: v for k, v in dataclasses.asdict(self).items() if k in names})
        except ValueError as exc:
            raise ConfigError(str(exc)) from None


@dataclass
class TrainConfig(LearningConfig, ActingSettings, EvalSettings):
    """Everything a training run is set by: the run, acting, the replay, the networks, the loss
    and the optimiser (the single-process runner and the cluster's [train] hold it whole)."""
