"""Every message of TPDEB's wire (DESIGN §3): one dataclass each, a rule on every field.

A fragment and a batch of them travel as the core's own classes (`Trajectory` is
tpdeb_core.schema's `Fragment`, `Batch` its `FragmentBatch`): their array rules (dtype, dims,
lower bound) come from that declaration, the rules of a fragment's scalars and every rule
spanning several fields are the wire's. tpdeb_core.schema is the one core module protocol
imports: the data's shape is the algorithm's, the wire validates it.

Array shapes name their dimensions. T (steps per fragment), obs_dim and act_dim come from the run
spec when the decoder has one; otherwise, like B, K, n and k, they are sized by the first field
that uses them and every other field must agree. Rules spanning several fields live in each
class's `cross_check` (for the core's classes, the check given to `core_message`). Classes
holding arrays compare by identity (eq=False): dataclass equality on numpy fields would raise
instead of answering.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tpdeb.protocol.keys import MAX_ACTOR_ID, NAME_RULE, SCHEMA_VERSION
from tpdeb.protocol.schema import (
    Array,
    Bool,
    DecodeError,
    DictOf,
    Float,
    Int,
    ListOf,
    Nested,
    OrNone,
    Scalar,
    Scope,
    Str,
    adopt,
)
from tpdeb.tpdeb_core.schema import Fragment, FragmentBatch, array_specs

F4, F8, I8, B1 = "<f4", "<f8", "<i8", "|b1"
PRIORITY_MODES = ("trajectory", "step", "none")  # as tpdeb_core.replay, which we may not import
POLICY_STDS = ("global", "state")  # as tpdeb_core.policy, which we may not import
CONTROL_COMMANDS = ("stop",)
MAX_BATCH_SIZE = 4096
MAX_REPLAY_SHARDS = 256


def wire(rule, **kwargs):
    """A dataclass field that carries its wire rule."""
    return field(metadata={"rule": rule}, **kwargs)


@dataclass(eq=False)
class RunSpec:
    """What all peers of a run must agree on; served by the replay, a mismatch is refused."""

    env_id: str = wire(Str(min_len=1, max_len=128))
    obs_dim: int = wire(Int(ge=1, le=2**20, dim="obs_dim"))
    act_dim: int = wire(Int(ge=1, le=2**16, dim="act_dim"))
    fragment_len: int = wire(Int(ge=1, le=2**16, dim="T"))
    hidden_sizes: list[int] = wire(ListOf(Int(ge=1, le=2**16), max_len=16))
    gamma: float = wire(Float(ge=0.0, le=1.0))
    obs_clip: float = wire(Float(gt=0.0))
    init_log_std: float = wire(Float())
    policy_std: str = wire(Str(choices=POLICY_STDS))  # the policy's standard deviation
    priority_mode: str = wire(Str(choices=PRIORITY_MODES))
    priority_kappa: float = wire(Float(ge=0.0))
    action_low: np.ndarray = wire(Array(F4, "act_dim"))  # float32[act_dim]
    action_high: np.ndarray = wire(Array(F4, "act_dim"))
    env_kwargs: str = wire(Str(max_len=4096), default="")  # gym.make's, as sorted JSON
    # replay servers of the run: an actor writes to shard actor_id mod replay_shards
    replay_shards: int = wire(Int(ge=1, le=MAX_REPLAY_SHARDS), default=1)
    schema_version: int = wire(Int(), default=SCHEMA_VERSION)

    def cross_check(self, scope: Scope, where: str) -> None:
        if self.schema_version != SCHEMA_VERSION:
            raise DecodeError("version", f"{where}: schema version {self.schema_version}, "
                                         f"this peer speaks {SCHEMA_VERSION}")
        if (self.action_low > self.action_high).any():
            raise DecodeError("value", f"{where}: action_low > action_high")


def core_message(cls: type, cross_check, **scalar_rules) -> type:
    """The core's class `cls` as a message: each array field's rule from its declaration, each
    other field's from `scalar_rules`."""
    arrays = {name: Array(spec.dtype, spec.dims, ge=spec.ge)
              for name, spec in array_specs(cls).items()}
    return adopt(cls, {**arrays, **scalar_rules}, cross_check)


def _check_trajectory(fragment: Fragment, scope: Scope, where: str) -> None:
    steps, index = fragment.num_steps, fragment.trunc_index
    if steps < 1:
        raise DecodeError("shape", f"{where}: a fragment needs at least one step")
    if index.size and (index[-1] >= steps or (np.diff(index) <= 0).any()):
        raise DecodeError("value", f"{where}.trunc_index must be strictly increasing steps "
                                   f"in [0, {steps})")
    # The learner bootstraps those steps from trunc_obs: they must really be truncations.
    if not fragment.truncated[index].all():
        raise DecodeError("value", f"{where}.trunc_index names steps that are not truncated")


# One fragment: T steps of one env of one actor (DESIGN §2 "Fragments"). De-duplication is by
# (actor_id, incarnation, seq).
Trajectory = core_message(
    Fragment, _check_trajectory, policy_version=Int(), reward_scale=Float(gt=0.0),
    actor_id=Int(le=MAX_ACTOR_ID), env_index=Int(le=MAX_ACTOR_ID), seq=Int(),
    incarnation=Int(ge=0))


@dataclass(eq=False)
class Ack:
    """Replay → actor: these sequence numbers are stored (or were duplicates); stop resending."""

    actor_id: int = wire(Int(le=MAX_ACTOR_ID))
    seqs: np.ndarray = wire(Array(I8, "n", ge=0))
    incarnation: int = wire(Int(ge=0), default=0)  # the actor process run these seqs belong to


@dataclass(eq=False)
class Params:
    """Learner → actors: the model's state_dict as numpy (normaliser included), versioned."""

    version: int = wire(Int())
    # float16 when the learner broadcasts weights at reduced precision (params_dtype)
    arrays: dict[str, np.ndarray] = wire(DictOf(Str(min_len=1), Array("<f2 <f4 <f8 <i8", "*")))


@dataclass
class SampleRequest:
    """Learner → replay query for a batch of fragments."""

    request_id: int = wire(Int())
    batch_size: int = wire(Int(ge=1, le=MAX_BATCH_SIZE))
    beta: float = wire(Float(ge=0.0, le=1.0))  # importance-weight exponent
    # B_p's rows where the learner splits batches over replay shards (tpdeb_core.shards); None:
    # round(ζB), the replay's own split
    num_prioritized: int | None = wire(OrNone(Int(ge=0, le=MAX_BATCH_SIZE)), default=None)

    def cross_check(self, scope: Scope, where: str) -> None:
        if self.num_prioritized is not None and self.num_prioritized > self.batch_size:
            raise DecodeError("value", f"{where}.num_prioritized={self.num_prioritized} is more "
                                       f"than the batch ({self.batch_size})")


@dataclass(eq=False)
class Moments:
    """Sufficient statistics of a running mean/variance, merged with Chan's parallel formula."""

    count: float = wire(Float(ge=0.0))
    mean: np.ndarray = wire(Array(F8, "*"))
    m2: np.ndarray = wire(Array(F8, "*", ge=0.0))  # sum of squared deviations from the mean

    def cross_check(self, scope: Scope, where: str) -> None:
        if self.mean.shape != self.m2.shape:
            raise DecodeError("shape", f"{where}: mean {self.mean.shape} but m2 {self.m2.shape}")


def _check_batch(batch: FragmentBatch, scope: Scope, where: str) -> None:
    steps, size = batch.rewards.shape
    if batch.trunc_t.size and (batch.trunc_t.max() >= steps or batch.trunc_b.max() >= size):
        raise DecodeError("value", f"{where}: a truncation index is outside the "
                                   f"[T, B] = [{steps}, {size}] batch")
    # The learner bootstraps those steps from trunc_obs: they must really be truncations.
    if not batch.truncated[batch.trunc_t, batch.trunc_b].all():
        raise DecodeError("value", f"{where}.trunc_t/trunc_b name steps that are not truncated")


# B sampled fragments stacked time-major ([T(+1), B, …]), the learner's input as it is: the
# replay stacks once, the learner decodes a dozen arrays instead of B messages.
Batch = core_message(FragmentBatch, _check_batch)


@dataclass(eq=False)
class SampleReply:
    """Replay → learner: a batch (prioritized items first) or, when not ready, why not."""

    request_id: int = wire(Int())
    ready: bool = wire(Bool())
    keys: np.ndarray = wire(Array(I8, "B", ge=0))
    weights: np.ndarray = wire(Array(F4, "B", ge=0.0))  # importance weights, 1.0 for uniform
    from_prioritized: np.ndarray = wire(Array(B1, "B"))
    # "step" mode: per-step loss weights of each fragment (Σ of the importance weights of the
    # transitions drawn at that step); None in the other modes
    step_weights: np.ndarray | None = wire(OrNone(Array(F4, "B T", ge=0.0)))
    batch: Batch | None = wire(OrNone(Nested(Batch)))  # None when not ready
    inserted_steps: int = wire(Int())
    obs_moments: Moments | None = wire(OrNone(Nested(Moments)))
    ret_moments: Moments | None = wire(OrNone(Nested(Moments)))
    reason: str = wire(Str(), default="")
    # What the replay holds when it answers (tpdeb_core.shards.ShardView): B_p's and B_u's item
    # counts, B_p's sampling mass and its P_min's mass — a sharded learner's next split
    prioritized_items: int = wire(Int(), default=0)
    uniform_items: int = wire(Int(), default=0)
    mass: float = wire(Float(ge=0.0), default=0.0)
    min_mass: float = wire(Float(ge=0.0), default=0.0)

    @classmethod
    def not_ready(cls, request_id: int, reason: str, inserted_steps: int = 0,
                  view: tuple = (0, 0, 0.0, 0.0)) -> SampleReply:
        """The empty reply: no batch, and why (e.g. "rate limiter"), with the replay's view."""
        return cls(request_id, False, np.zeros(0, np.int64), np.zeros(0, np.float32),
                   np.zeros(0, bool), None, None, inserted_steps, None, None, reason, *view)

    def cross_check(self, scope: Scope, where: str) -> None:
        if not self.ready and (self.batch is not None or not self.reason):
            raise DecodeError("value", f"{where}: a reply that is not ready carries no batch and "
                                       "says why")
        if self.ready and self.batch is None:
            raise DecodeError("value", f"{where}: a ready reply carries a batch")
        if self.batch is not None:
            steps, size = self.batch.rewards.shape
            if size != len(self.keys):
                raise DecodeError("shape", f"{where}.batch holds {size} fragments, keys "
                                           f"{len(self.keys)}")
            if self.step_weights is not None and self.step_weights.shape != (size, steps):
                raise DecodeError("shape", f"{where}.step_weights: {self.step_weights.shape}, "
                                           f"the batch is [B, T] = [{size}, {steps}]")
        obs_dim = scope.get("obs_dim")
        if self.obs_moments is not None and obs_dim is not None \
                and self.obs_moments.mean.shape != (obs_dim,):
            raise DecodeError("shape", f"{where}.obs_moments: mean {self.obs_moments.mean.shape}, "
                                       f"expected ({obs_dim},)")


@dataclass(eq=False)
class PriorityUpdate:
    """Learner → replay: new priorities for fragment keys (per step in "step" mode)."""

    keys: np.ndarray = wire(Array(I8, "n", ge=0))
    priorities: np.ndarray = wire(Array(F8, "n | n T", ge=0.0))


@dataclass(eq=False)
class Stats:
    """Any process → monitors: scalar metrics and finished episodes since the last Stats."""

    role: str = wire(Str(min_len=1, max_len=64, pattern=NAME_RULE))
    ident: str = wire(Str(min_len=1, max_len=64, pattern=NAME_RULE))
    values: dict[str, float | int | str] = wire(DictOf(Str(min_len=1, max_len=128), Scalar()))
    episode_returns: np.ndarray = wire(Array(F8, "k"),
                                       default_factory=lambda: np.zeros(0, np.float64))
    episode_lengths: np.ndarray = wire(Array(I8, "k", ge=0),
                                       default_factory=lambda: np.zeros(0, np.int64))


@dataclass
class Control:
    """A broadcast to every process of the run."""

    command: str = wire(Str(choices=CONTROL_COMMANDS))
    reason: str = wire(Str(), default="")


@dataclass
class JoinRequest:
    """Actor → replay: a free actor id, please (`--actor-id auto`: identical replicas)."""

    nonce: int = wire(Int(ge=0))  # the asker's random number: a repeated ask gets the same id


@dataclass
class JoinReply:
    """Replay → actor: the id to act under, held by no other actor the replay knows of."""

    actor_id: int = wire(Int(le=MAX_ACTOR_ID))
    nonce: int = wire(Int(ge=0))


# The envelope's type name of each message class.
MESSAGE_TYPES: dict[str, type] = {
    "Trajectory": Trajectory, "Batch": Batch, **{cls.__name__: cls for cls in (
        RunSpec, Ack, Params, SampleRequest, SampleReply, Moments, PriorityUpdate, Stats, Control,
        JoinRequest, JoinReply)}}
MESSAGE_NAMES: dict[type, str] = {cls: name for name, cls in MESSAGE_TYPES.items()}
