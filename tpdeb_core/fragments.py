"""Fragments: T-step slices of one env's stream, built from a gymnasium vector env (DESIGN §2).

What a fragment holds is declared once, in `tpdeb_core/schema.py` (`Fragment`, `FragmentBatch`,
re-exported here); this module fills it: the Collector writes every env's step into buffers
sized from that declaration, `stack_fragments` stacks B fragments into a batch, and
`initial_priority` is the replay priority of one. The step in which a NEXT_STEP-mode vector env
resets an env is never recorded.

The env is injected (anything with gymnasium's vector API); this module imports neither
gymnasium nor anything that does I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from tpdeb.tpdeb_core.policy import NumpyPolicy
from tpdeb.tpdeb_core.replay import PRIORITY_MODES
from tpdeb.tpdeb_core.schema import STACKED, Fragment, FragmentBatch, array_specs

__all__ = ["Collector", "Fragment", "FragmentBatch", "fragment_priority", "fragment_return",
           "initial_priority", "join_batches", "stack_fragments"]

# What the Collector writes at every step: each per-step field but td_abs (computed when the
# fragment is complete), plus the actor's value estimates, which td_abs needs and nothing ships.
_RECORDED = {name: spec for name, spec in array_specs(Fragment).items()
             if spec.dims.split()[0] in ("T", "T+1") and name != "td_abs"}


def stack_fragments(fragments: Sequence[Fragment]) -> FragmentBatch:
    """B fragments (as the Collector made them or as the wire decoded them) → one batch."""
    stacked = {name: np.stack([getattr(f, name) for f in fragments], axis=1) for name in STACKED}
    obs_dim = stacked["obs"].shape[-1]
    trunc_t = [np.asarray(f.trunc_index, np.int32) for f in fragments]
    return FragmentBatch(
        **stacked,
        trunc_t=np.concatenate(trunc_t) if trunc_t else np.zeros(0, np.int32),
        trunc_b=np.concatenate([np.full(len(t), b, np.int32) for b, t in enumerate(trunc_t)])
        if trunc_t else np.zeros(0, np.int32),
        trunc_obs=np.concatenate([np.asarray(f.trunc_obs, np.float32).reshape(-1, obs_dim)
                                  for f in fragments]),
        policy_version=np.array([f.policy_version for f in fragments], np.int64))


def join_batches(batches: Sequence[FragmentBatch]) -> FragmentBatch:
    """Batches side by side (B₁ + B₂ + … fragments, in order): one batch from replay shards."""
    if len(batches) == 1:
        return batches[0]
    offsets = np.cumsum([0] + [b.policy_version.size for b in batches[:-1]])
    return FragmentBatch(
        **{name: np.concatenate([getattr(b, name) for b in batches], axis=1) for name in STACKED},
        trunc_t=np.concatenate([b.trunc_t for b in batches]),
        trunc_b=np.concatenate([b.trunc_b + offset for b, offset in
                                zip(batches, offsets.tolist(), strict=True)]).astype(np.int32),
        trunc_obs=np.concatenate([b.trunc_obs for b in batches]),
        policy_version=np.concatenate([b.policy_version for b in batches]))


def initial_priority(fragment: Fragment, mode: str, kappa: float, gamma: float):
    """The replay priority a fragment enters with: `fragment_priority` of its td_abs (and, for
    κ > 0, of its return under the reward scale the actor used)."""
    return fragment_priority(fragment.td_abs, mode, kappa,
                             fragment.rewards * fragment.reward_scale, fragment.discounts(gamma))


def fragment_return(rewards_scaled: np.ndarray, discounts: np.ndarray) -> np.ndarray:
    """G_t = Σ_k γ^k r_{t+k} within the fragment, cut at episode ends (discount 0)."""
    out = np.zeros_like(rewards_scaled, dtype=np.float64)
    acc = 0.0
    for t in range(len(rewards_scaled) - 1, -1, -1):
        acc = rewards_scaled[t] + discounts[t] * acc
        out[t] = acc
    return out


def fragment_priority(
    td_abs: np.ndarray,
    mode: str,
    kappa: float = 0.0,
    rewards_scaled: np.ndarray | None = None,
    discounts: np.ndarray | None = None,
):
    """Replay priority of a fragment from its per-step |δ_t| (DESIGN §2, "Initial priority").

    trajectory: Δτ + κ·|Ĝ| with Δτ = Σ_t |δ_t| and Ĝ the fragment's mean scaled return;
    step: the per-step array |δ_t| (+ κ·|G_t|); none: 1.0 (ignored by the replay).
    """
    if mode not in PRIORITY_MODES:
        raise ValueError(f"priority_mode={mode!r}: expected one of {PRIORITY_MODES}")
    td_abs = np.asarray(td_abs, dtype=np.float64)
    returns = None
    if kappa:
        if rewards_scaled is None or discounts is None:
            raise ValueError("kappa > 0 needs rewards_scaled and discounts")
        returns = np.abs(fragment_return(rewards_scaled, discounts))
    if mode == "trajectory":
        return float(td_abs.sum() + (kappa * returns.mean() if returns is not None else 0.0))
    if mode == "step":
        return td_abs + (kappa * returns if returns is not None else 0.0)
    return 1.0


@dataclass
class Collector:
    """Steps a vector env with a policy and emits fragments with initial priorities.

    `step()` advances every env once and returns the fragments completed by that step;
    finished episodes accumulate in `episodes` as (raw return, length) for the caller to drain.
    The policy is a `NumpyPolicy` (numpy only); `set_policy` swaps in a newer one.
    All envs' steps are written into preallocated [num_envs, T] buffers with one numpy
    operation per field, so the per-step cost barely grows with the number of envs.
    """

    envs: object
    policy: NumpyPolicy
    fragment_len: int
    gamma: float
    action_low: np.ndarray
    action_high: np.ndarray
    seed: int = 0
    actor_id: int = 0
    incarnation: int = 0  # the actor process's run, stamped on every fragment (de-duplication)
    same_step_autoreset: bool = True
    policy_version: int = 0
    episodes: list = field(default_factory=list)

    def __post_init__(self):
        self.num_envs = n = int(self.envs.num_envs)
        obs, _ = self.envs.reset(seed=[self.seed + i for i in range(n)])
        self.obs = np.asarray(obs, dtype=np.float32)
        self.rng = np.random.default_rng(self.seed)
        T, obs_dim, act_dim = self.fragment_len, self.obs.shape[1], self.policy.act_dim
        # [num_envs, T, …] per recorded field (obs too: its bootstrap row is added at the end)
        self.buf = {name: np.zeros((n, T, *spec.shape(T=T, obs_dim=obs_dim, act_dim=act_dim)[1:]),
                                   spec.dtype) for name, spec in _RECORDED.items()}
        self.buf["values"] = np.zeros((n, T), np.float32)  # V(s_t), for td_abs only
        self.pos = np.zeros(n, np.int64)  # steps recorded in each env's current fragment
        self.version = np.zeros(n, np.int64)  # policy version at each fragment's first step
        self.trunc: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
        self.disc_return = np.zeros(n, dtype=np.float64)
        self.episode_return = np.zeros(n, dtype=np.float64)
        self.episode_length = np.zeros(n, dtype=np.int64)
        self.pending_reset = np.zeros(n, dtype=bool)  # NEXT_STEP autoreset ahead
        self.seq = 0
        self.env_steps = 0  # steps recorded into fragments (autoreset steps excluded)

    def set_policy(self, policy: NumpyPolicy, version: int) -> None:
        """Act with `policy` (parameter version `version`) from the next step on."""
        self.policy = policy
        self.policy_version = int(version)

    def step(self) -> list[Fragment]:
        out = self.policy.act(self.obs, self.rng)
        env_action = np.clip(out["action"], self.action_low, self.action_high)
        next_obs, rewards, terminated, truncated, info = self.envs.step(env_action)
        next_obs = np.asarray(next_obs, dtype=np.float32)
        rewards = np.asarray(rewards, np.float64)
        terminated, truncated = np.asarray(terminated, bool), np.asarray(truncated, bool)
        # gymnasium NEXT_STEP mode: a step that only reset an env has nothing to learn from.
        live = np.flatnonzero(~self.pending_reset)
        self.pending_reset[:] = False
        t = self.pos[live]
        self.version[live[t == 0]] = self.policy_version
        self.disc_return[live] = self.disc_return[live] * self.gamma + rewards[live]
        row = {
            "obs": self.obs, "actions": out["action"], "rewards": rewards,
            "terminated": terminated, "truncated": truncated, "behaviour_mean": out["mean"],
            "behaviour_log_std": out["log_std"], "behaviour_logp": out["logp"],
            "values": out["value"], "disc_returns": self.disc_return,
        }
        if len(live) == self.num_envs and (t == t[0]).all():  # the usual case: plain slices
            for key, values in row.items():
                self.buf[key][:, t[0]] = values
        else:
            for key, values in row.items():
                self.buf[key][live, t] = values[live]
        self.pos[live] += 1
        self.env_steps += len(live)
        self.episode_return[live] += rewards[live]
        self.episode_length[live] += 1
        final_obs = info.get("final_obs") if self.same_step_autoreset else None
        for i in live[(terminated | truncated)[live]]:
            self.episodes.append((float(self.episode_return[i]), int(self.episode_length[i])))
            self.episode_return[i] = self.disc_return[i] = 0.0
            self.episode_length[i] = 0
            if truncated[i] and not terminated[i]:
                last = final_obs[i] if final_obs is not None else next_obs[i]
                self.trunc[i].append((int(self.pos[i]) - 1, np.asarray(last, dtype=np.float32)))
            self.pending_reset[i] = not self.same_step_autoreset
        full = live[self.pos[live] == self.fragment_len]
        fragments = self._emit(full, next_obs) if len(full) else []
        self.obs = next_obs
        return fragments

    def _emit(self, env_indices: np.ndarray, next_obs: np.ndarray) -> list[Fragment]:
        boot_values = self.policy.values_of(next_obs[env_indices])
        scale = self.policy.reward_scale()
        obs_dim = self.obs.shape[1]
        fragments = []
        for j, i in enumerate(env_indices.tolist()):
            b = {key: buf[i].copy() for key, buf in self.buf.items()}
            values = np.append(b.pop("values"), np.float32(boot_values[j]))
            trunc = self.trunc[i]
            trunc_index = np.array([t for t, _ in trunc], dtype=np.int32)
            trunc_obs = (np.stack([o for _, o in trunc]).astype(np.float32) if trunc
                         else np.zeros((0, obs_dim), np.float32))
            next_values = values[1:].astype(np.float64)
            if trunc:
                next_values[trunc_index] = self.policy.values_of(trunc_obs)
            td = scale * b["rewards"] + self.gamma * (~b["terminated"]) * next_values \
                - values[:-1]
            b["obs"] = np.concatenate([b["obs"], next_obs[i][None]])
            fragments.append(Fragment(
                **b, trunc_index=trunc_index, trunc_obs=trunc_obs,
                td_abs=np.abs(td).astype(np.float32), policy_version=int(self.version[i]),
                reward_scale=float(scale), actor_id=self.actor_id, env_index=i, seq=self.seq,
                incarnation=self.incarnation))
            self.seq += 1
            self.pos[i] = 0
            self.trunc[i] = []
        return fragments
