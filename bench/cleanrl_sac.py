"""SAC as CleanRL's single-file `sac_continuous_action.py` runs it, for the race (bench/peers.py
`--system cleanrl-sac`): one env, a 1M-step uniform replay, 256×256 ReLU actor and twin Q
networks, the tanh-squashed Gaussian with its log-std squashed into [-5, 2], Q learning rate 1e-3,
policy and temperature 3e-4 / 1e-3, the policy updated every second step twice (TD3's delay with
its compensation), Polyak τ = 0.005 every step, the temperature tuned toward −|A|, 5,000 random
steps first, batch 256, γ = 0.99. The same task settings for every task, as CleanRL's script has.

Written here from that description (not imported: CleanRL is a set of scripts, not a package).
Per env step it does the script's work — one action, one Q update on a batch of 256, every second
step two policy and two temperature updates, one Polyak step — with a numpy replay and one
fused Polyak call in place of the script's per-parameter loop, so its pace is that of a lean
single-process SAC here and its returns compare with CleanRL's published curves. Truncated
episodes bootstrap from their final observation (the script's `real_next_obs`), terminated
ones do not.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


@dataclass(frozen=True)
class Settings:
    buffer_size: int = 1_000_000
    gamma: float = 0.99
    tau: float = 0.005
    batch_size: int = 256
    learning_starts: int = 5_000
    policy_lr: float = 3e-4
    q_lr: float = 1e-3
    policy_frequency: int = 2
    target_network_frequency: int = 1
    hidden: int = 256


def networks(obs_dim: int, act_dim: int, low: np.ndarray, high: np.ndarray, hidden: int):
    """(actor, q1, q2) as torch modules; the actor's `sample` gives (action, log π, mean action)."""
    import torch
    import torch.nn as nn

    def mlp(inputs: int, outputs: int) -> nn.Sequential:
        return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden),
                             nn.ReLU(), nn.Linear(hidden, outputs))

    class Actor(nn.Module):
        def __init__(self):
            super().__init__()
            self.trunk = mlp(obs_dim, 2 * act_dim)
            self.register_buffer("scale", torch.as_tensor((high - low) / 2.0, dtype=torch.float32))
            self.register_buffer("bias", torch.as_tensor((high + low) / 2.0, dtype=torch.float32))

        def forward(self, obs):
            mean, log_std = self.trunk(obs).chunk(2, dim=-1)
            log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)
            return mean, log_std

        def sample(self, obs):
            mean, log_std = self(obs)
            std = log_std.exp()
            pre = mean + std * torch.randn_like(mean)
            squashed = torch.tanh(pre)
            # log N(pre; mean, std) minus the log-determinant of the squash and the rescaling
            logp = (-0.5 * ((pre - mean) / std) ** 2 - log_std - 0.5 * np.log(2 * np.pi)
                    - torch.log(self.scale * (1 - squashed.pow(2)) + 1e-6)).sum(-1)
            return (squashed * self.scale + self.bias, logp,
                    torch.tanh(mean) * self.scale + self.bias)

    class Q(nn.Module):
        def __init__(self):
            super().__init__()
            self.net = mlp(obs_dim + act_dim, 1)

        def forward(self, obs, act):
            return self.net(torch.cat([obs, act], -1)).squeeze(-1)

    return Actor(), Q(), Q()


class Replay:
    """Uniform circular replay of (obs, action, reward, next obs, terminated)."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, rng: np.random.Generator):
        self.obs = np.zeros((capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((capacity, obs_dim), np.float32)
        self.act = np.zeros((capacity, act_dim), np.float32)
        self.rew = np.zeros(capacity, np.float32)
        self.term = np.zeros(capacity, np.float32)
        self.capacity, self.size, self.at, self.rng = capacity, 0, 0, rng

    def add(self, obs, act, rew, next_obs, term) -> None:
        i = self.at
        self.obs[i], self.act[i], self.rew[i], self.next_obs[i], self.term[i] = (
            obs, act, rew, next_obs, term)
        self.at = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, n: int):
        import torch

        idx = self.rng.integers(0, self.size, n)
        return tuple(torch.from_numpy(a[idx]) for a in
                     (self.obs, self.act, self.rew, self.next_obs, self.term))


def train(env_id: str, seed: int, seconds: float, marks: list[float], say,
          settings: Settings = Settings()) -> dict:
    """Trains for `seconds` of wall-clock (from the first step): episodes as (seconds, steps,
    return), a copy of the actor at each mark, the steps made and the seconds spent."""
    import gymnasium as gym
    import torch
    import torch.nn.functional as F

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    env = gym.make(env_id)
    env.action_space.seed(seed)
    obs_dim = int(np.prod(env.observation_space.shape))
    act_dim = int(np.prod(env.action_space.shape))
    actor, q1, q2 = networks(obs_dim, act_dim, env.action_space.low, env.action_space.high,
                             settings.hidden)
    q1_target, q2_target = networks(obs_dim, act_dim, env.action_space.low,
                                    env.action_space.high, settings.hidden)[1:]
    q1_target.load_state_dict(q1.state_dict())
    q2_target.load_state_dict(q2.state_dict())
    q_params = [*q1.parameters(), *q2.parameters()]
    target_params = [*q1_target.parameters(), *q2_target.parameters()]
    q_opt = torch.optim.Adam(q_params, lr=settings.q_lr)
    pi_opt = torch.optim.Adam(actor.parameters(), lr=settings.policy_lr)
    target_entropy = -float(act_dim)
    log_alpha = torch.zeros(1, requires_grad=True)
    alpha_opt = torch.optim.Adam([log_alpha], lr=settings.q_lr)
    alpha = 1.0
    replay = Replay(settings.buffer_size, obs_dim, act_dim, rng)

    episodes, snapshots, pending = [], [], sorted(marks)
    obs, _ = env.reset(seed=seed)
    ret, step = 0.0, 0
    start = last_say = time.monotonic()
    while True:
        now = time.monotonic()
        t = now - start
        while pending and t >= pending[0]:
            snapshots.append({"mark": pending.pop(0), "t_s": round(t, 2), "steps": step,
                              "actor": {k: v.clone() for k, v in actor.state_dict().items()}})
        if t >= seconds:
            break
        if now - last_say >= 30:
            recent = [r for _, _, r in episodes[-10:]]
            say(f"{t:6.0f}/{seconds:.0f} s | {step:,} steps | return "
                f"{np.mean(recent) if recent else float('nan'):,.1f}")
            last_say = now
        if step < settings.learning_starts:
            action = env.action_space.sample()
        else:
            with torch.no_grad():
                action = actor.sample(torch.as_tensor(obs, dtype=torch.float32)[None])[0][0]
            action = action.numpy()
        next_obs, reward, terminated, truncated, _ = env.step(action)
        replay.add(obs, action, reward, next_obs, float(terminated))
        ret += float(reward)
        step += 1
        if terminated or truncated:
            episodes.append((round(time.monotonic() - start, 2), step, ret))
            (next_obs, _), ret = env.reset(), 0.0
        obs = next_obs
        if step <= settings.learning_starts:
            continue
        b_obs, b_act, b_rew, b_next, b_term = replay.sample(settings.batch_size)
        with torch.no_grad():
            next_act, next_logp, _ = actor.sample(b_next)
            soft = torch.min(q1_target(b_next, next_act), q2_target(b_next, next_act))
            target = b_rew + (1 - b_term) * settings.gamma * (soft - alpha * next_logp)
        q_loss = F.mse_loss(q1(b_obs, b_act), target) + F.mse_loss(q2(b_obs, b_act), target)
        q_opt.zero_grad()
        q_loss.backward()
        q_opt.step()
        if step % settings.policy_frequency == 0:
            for _ in range(settings.policy_frequency):
                act, logp, _ = actor.sample(b_obs)
                pi_loss = (alpha * logp - torch.min(q1(b_obs, act), q2(b_obs, act))).mean()
                pi_opt.zero_grad()
                pi_loss.backward()
                pi_opt.step()
                with torch.no_grad():
                    logp = actor.sample(b_obs)[1]
                alpha_loss = (-log_alpha.exp() * (logp + target_entropy)).mean()
                alpha_opt.zero_grad()
                alpha_loss.backward()
                alpha_opt.step()
                alpha = log_alpha.exp().item()
        if step % settings.target_network_frequency == 0:
            with torch.no_grad():
                torch._foreach_lerp_(target_params, q_params, settings.tau)
    env.close()
    return {"episodes": episodes, "snapshots": snapshots, "steps": step,
            "train_s": time.monotonic() - start, "actor": actor}


def evaluate(actor, snapshot: dict, env_id: str, seed: int, episodes: int) -> dict:
    """The snapshot's deterministic return (the squashed mean action) over fresh episodes."""
    import torch
    from peers import rollouts

    actor.load_state_dict(snapshot["actor"])

    def act(obs):
        with torch.no_grad():
            return actor.sample(torch.as_tensor(obs, dtype=torch.float32)[None])[2][0].numpy()

    return rollouts(act, env_id, seed, episodes)
