"""Fragments: T-step slices of one env's stream, built from a gymnasium vector env (SPEC §2).

A fragment holds obs[T+1] (the last one is the bootstrap observation), raw actions[T],
rewards[T] (raw, scaled at learn time), terminated/truncated[T], the behaviour policy's
mean/log-std/log-prob[T], the actor's value estimates V[T+1], and for every truncated step the
real final observation (`trunc_index`, `trunc_obs`): truncation bootstraps from it, termination
does not. The step in which a NEXT_STEP-mode vector env resets an env is never recorded.

The env is injected (anything with gymnasium's vector API); this module imports neither
gymnasium nor anything that does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from tpdeb_core.model import ActorCritic
from tpdeb_core.replay import PRIORITY_MODES


@dataclass
class Fragment:
    obs: np.ndarray  # float32 [T+1, obs_dim], raw
    actions: np.ndarray  # float32 [T, act_dim], raw Gaussian samples (before clipping)
    rewards: np.ndarray  # float32 [T], raw
    terminated: np.ndarray  # bool [T]
    truncated: np.ndarray  # bool [T]
    behaviour_mean: np.ndarray  # float32 [T, act_dim]
    behaviour_log_std: np.ndarray  # float32 [T, act_dim]
    behaviour_logp: np.ndarray  # float32 [T]
    values: np.ndarray  # float32 [T+1], the actor's V on normalised obs
    trunc_index: np.ndarray  # int32 [K], steps that were truncated
    trunc_obs: np.ndarray  # float32 [K, obs_dim], their real final observations
    disc_returns: np.ndarray  # float32 [T], running discounted return (reward-scale moments)
    td_abs: np.ndarray  # float32 [T], |δ_t| under the actor's value net (initial priority)
    policy_version: int = 0
    actor_id: int = 0
    env_index: int = 0
    seq: int = 0

    @property
    def num_steps(self) -> int:
        return int(self.rewards.shape[0])

    def discounts(self, gamma: float) -> np.ndarray:
        """γ_t: zero where the episode ended (truncation bootstraps through the reward)."""
        return gamma * ~(self.terminated | self.truncated)

    def initial_priority(self, mode: str, kappa: float, gamma: float, reward_scale: float):
        return fragment_priority(self.td_abs, mode, kappa, self.rewards * reward_scale,
                                 self.discounts(gamma))


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
    """Replay priority of a fragment from its per-step |δ_t| (SPEC §2, "Initial priority").

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


class _EnvStream:
    """Accumulates one env's steps until a fragment of T steps is complete."""

    def __init__(self, fragment_len: int):
        self.fragment_len = fragment_len
        self.reset()

    def reset(self) -> None:
        self.steps: dict[str, list] = {k: [] for k in (
            "obs", "actions", "rewards", "terminated", "truncated", "mean", "log_std", "logp",
            "values", "disc_returns")}
        self.trunc: list[tuple[int, np.ndarray]] = []
        self.policy_version: int | None = None

    def __len__(self) -> int:
        return len(self.steps["rewards"])


@dataclass
class Collector:
    """Steps a vector env with an ActorCritic and emits fragments with initial priorities.

    `step()` advances every env once and returns the fragments completed by that step;
    finished episodes accumulate in `episodes` as (raw return, length) for the caller to drain.
    """

    envs: object
    model: ActorCritic
    fragment_len: int
    gamma: float
    action_low: np.ndarray
    action_high: np.ndarray
    seed: int = 0
    actor_id: int = 0
    same_step_autoreset: bool = True
    policy_version: int = 0
    episodes: list = field(default_factory=list)

    def __post_init__(self):
        self.num_envs = int(self.envs.num_envs)
        obs, _ = self.envs.reset(seed=[self.seed + i for i in range(self.num_envs)])
        self.obs = np.asarray(obs, dtype=np.float32)
        self.generator = torch.Generator().manual_seed(self.seed)
        self.streams = [_EnvStream(self.fragment_len) for _ in range(self.num_envs)]
        self.disc_return = np.zeros(self.num_envs, dtype=np.float64)
        self.episode_return = np.zeros(self.num_envs, dtype=np.float64)
        self.episode_length = np.zeros(self.num_envs, dtype=np.int64)
        self.pending_reset = np.zeros(self.num_envs, dtype=bool)  # NEXT_STEP autoreset ahead
        self.seq = 0
        self.env_steps = 0  # steps recorded into fragments (autoreset steps excluded)

    def set_parameters(self, state_dict: dict, version: int) -> None:
        self.model.load_state_dict(state_dict)
        self.policy_version = int(version)

    def step(self) -> list[Fragment]:
        out = self.model.act(self.obs, self.generator)
        env_action = np.clip(out["action"], self.action_low, self.action_high)
        next_obs, rewards, terminated, truncated, info = self.envs.step(env_action)
        next_obs = np.asarray(next_obs, dtype=np.float32)
        final_obs = info.get("final_obs") if self.same_step_autoreset else None
        done_streams = []
        for i in range(self.num_envs):
            if self.pending_reset[i]:
                # gymnasium NEXT_STEP mode: this step only reset env i; nothing to learn from.
                self.pending_reset[i] = False
                continue
            stream = self.streams[i]
            if stream.policy_version is None:
                stream.policy_version = self.policy_version
            r = float(rewards[i])
            self.disc_return[i] = self.disc_return[i] * self.gamma + r
            row = {
                "obs": self.obs[i], "actions": out["action"][i], "rewards": r,
                "terminated": bool(terminated[i]), "truncated": bool(truncated[i]),
                "mean": out["mean"][i], "log_std": out["log_std"][i], "logp": out["logp"][i],
                "values": out["value"][i], "disc_returns": self.disc_return[i],
            }
            for key, value in row.items():
                stream.steps[key].append(value)
            self.env_steps += 1
            self.episode_return[i] += r
            self.episode_length[i] += 1
            if terminated[i] or truncated[i]:
                self.episodes.append((float(self.episode_return[i]), int(self.episode_length[i])))
                self.episode_return[i] = 0.0
                self.episode_length[i] = 0
                self.disc_return[i] = 0.0
                if truncated[i] and not terminated[i]:
                    last = final_obs[i] if final_obs is not None else next_obs[i]
                    stream.trunc.append((len(stream) - 1, np.asarray(last, dtype=np.float32)))
                self.pending_reset[i] = not self.same_step_autoreset
            if len(stream) == self.fragment_len:
                done_streams.append(i)
        fragments = self._emit(done_streams, next_obs) if done_streams else []
        self.obs = next_obs
        return fragments

    def _emit(self, env_indices: list[int], next_obs: np.ndarray) -> list[Fragment]:
        boot_values = self.model.values_of(next_obs[env_indices])
        scale = self.model.reward_scale()
        fragments = []
        for j, i in enumerate(env_indices):
            s = self.streams[i].steps
            trunc = self.streams[i].trunc
            obs_dim = self.obs.shape[1]
            trunc_index = np.array([t for t, _ in trunc], dtype=np.int32)
            trunc_obs = (np.stack([o for _, o in trunc]).astype(np.float32) if trunc
                         else np.zeros((0, obs_dim), np.float32))
            values = np.append(np.asarray(s["values"], np.float32), np.float32(boot_values[j]))
            terminated = np.asarray(s["terminated"], bool)
            rewards = np.asarray(s["rewards"], np.float32)
            next_values = values[1:].astype(np.float64)
            if len(trunc):
                next_values[trunc_index] = self.model.values_of(trunc_obs)
            td = scale * rewards + self.gamma * (~terminated) * next_values - values[:-1]
            fragments.append(Fragment(
                obs=np.concatenate([np.asarray(s["obs"], np.float32), next_obs[i][None]]),
                actions=np.asarray(s["actions"], np.float32),
                rewards=rewards,
                terminated=terminated,
                truncated=np.asarray(s["truncated"], bool),
                behaviour_mean=np.asarray(s["mean"], np.float32),
                behaviour_log_std=np.asarray(s["log_std"], np.float32),
                behaviour_logp=np.asarray(s["logp"], np.float32),
                values=values,
                trunc_index=trunc_index,
                trunc_obs=trunc_obs,
                disc_returns=np.asarray(s["disc_returns"], np.float32),
                td_abs=np.abs(td).astype(np.float32),
                policy_version=int(self.streams[i].policy_version),
                actor_id=self.actor_id,
                env_index=i,
                seq=self.seq,
            ))
            self.seq += 1
            self.streams[i].reset()
        return fragments
