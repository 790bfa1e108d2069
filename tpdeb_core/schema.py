"""The fragment's schema, declared once (DESIGN §2 "Fragments", §3 "The wire").

`Fragment` declares every array a fragment holds by name, dtype and named dimensions; the rest
follows from it: the Collector's per-step buffers, `FragmentBatch` (the batched fields stacked
along a new axis 1) and the wire's rules for both (protocol/messages.py: this is the one core
module protocol imports; the data's shape is the algorithm's, the wire validates it). A fragment
travels, is stored and is sampled as this very object; no other class mirrors it.

Dimensions: T steps per fragment ("T+1": one more), K truncated steps, obs_dim, act_dim, and B
fragments in a batch. Dtypes are spelt as the wire spells them (explicitly little-endian).

Pure: numpy and the standard library only.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, make_dataclass

import numpy as np

F4, I4, I8, B1 = "<f4", "<i4", "<i8", "|b1"


@dataclass(frozen=True)
class ArraySpec:
    """One array field: dtype, named dimensions ("T+1 obs_dim"), a lower bound on every
    element if any, and whether `stack_fragments` stacks it into the batch."""

    dtype: str
    dims: str
    ge: float | None = None
    batched: bool = False

    def shape(self, **sizes: int) -> tuple[int, ...]:
        """The shape for named sizes: "T+1 obs_dim" with T=64, obs_dim=17 → (65, 17)."""
        return tuple(sizes[name] + int(offset or 0)
                     for name, _, offset in (dim.partition("+") for dim in self.dims.split()))


def array(dtype: str, dims: str, *, ge: float | None = None, batched: bool = False):
    """A dataclass field holding an array, with its ArraySpec as metadata."""
    return field(metadata={"array": ArraySpec(dtype, dims, ge, batched)})


def array_specs(cls: type) -> dict[str, ArraySpec]:
    """Name → ArraySpec of every array field of `cls` (Fragment, FragmentBatch), in order."""
    return {f.name: f.metadata["array"] for f in fields(cls) if "array" in f.metadata}


@dataclass(eq=False)  # eq on numpy fields would raise instead of answering
class Fragment:
    """T steps of one env of one actor (DESIGN §2 "Fragments"). Truncation bootstraps from the
    real final observation (`trunc_obs`); termination does not."""

    obs: np.ndarray = array(F4, "T+1 obs_dim", batched=True)  # raw; the last: bootstrap obs
    actions: np.ndarray = array(F4, "T act_dim", batched=True)  # raw Gaussian samples, unclipped
    rewards: np.ndarray = array(F4, "T", batched=True)  # raw, scaled at learn time
    terminated: np.ndarray = array(B1, "T", batched=True)
    truncated: np.ndarray = array(B1, "T", batched=True)
    behaviour_mean: np.ndarray = array(F4, "T act_dim", batched=True)
    behaviour_log_std: np.ndarray = array(F4, "T act_dim", batched=True)
    behaviour_logp: np.ndarray = array(F4, "T", batched=True)
    disc_returns: np.ndarray = array(F4, "T")  # running discounted return: reward-scale moments
    td_abs: np.ndarray = array(F4, "T", ge=0.0)  # |δ_t|, actor's value net: initial priority
    trunc_index: np.ndarray = array(I4, "K", ge=0)  # the truncated steps, ascending
    trunc_obs: np.ndarray = array(F4, "K obs_dim")  # their real final observations
    policy_version: int = 0  # the behaviour policy's parameter version
    reward_scale: float = 1.0  # the actor's reward scale when it computed td_abs
    actor_id: int = 0
    env_index: int = 0
    seq: int = 0  # per actor run: acknowledgements and de-duplication
    incarnation: int = 0  # which run of the actor process (a restarted one counts seq from 0)

    @property
    def num_steps(self) -> int:
        return int(self.rewards.shape[0])

    def discounts(self, gamma: float) -> np.ndarray:
        """γ_t: zero where the episode ended (truncation bootstraps through the reward)."""
        return gamma * ~(self.terminated | self.truncated)


def _with_batch_axis(dims: str) -> str:
    """A per-fragment field's dims in the batch: B after the time axis ("T act_dim" → "T B
    act_dim")."""
    time, *rest = dims.split()
    return " ".join([time, "B", *rest])


_FRAGMENT = array_specs(Fragment)
STACKED = tuple(name for name, spec in _FRAGMENT.items() if spec.batched)

FragmentBatch = make_dataclass(
    "FragmentBatch",
    [*((name, np.ndarray, array(_FRAGMENT[name].dtype, _with_batch_axis(_FRAGMENT[name].dims)))
       for name in STACKED),
     # the B fragments' truncations, concatenated: time index, fragment, real final observation
     ("trunc_t", np.ndarray, field(metadata={"array": _FRAGMENT["trunc_index"]})),
     ("trunc_b", np.ndarray, array(I4, "K", ge=0)),
     ("trunc_obs", np.ndarray, field(metadata={"array": _FRAGMENT["trunc_obs"]})),
     ("policy_version", np.ndarray, array(I8, "B"))],  # each fragment's behaviour policy
    eq=False,
    namespace={"__module__": __name__, "__doc__": (
        "B fragments stacked time-major, what `Learner.step` trains on: every batched Fragment "
        "field with B after its time axis (obs [T+1, B, obs_dim], rewards [T, B], …), the "
        "truncations of all B fragments and each fragment's policy version. The replay server "
        "stacks once per sample and ships it as it is; the learner trains on what it decoded.")})
