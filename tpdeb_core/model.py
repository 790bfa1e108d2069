"""Networks, diagonal-Gaussian helpers and the running normalisers (DESIGN §2 "Policy").

The normaliser state lives inside the model (as buffers), so it travels with the parameters to
the actors and is saved in every checkpoint: a policy evaluated without its normaliser is a
different policy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from tpdeb.tpdeb_core.moments import NORM_EPSILON, batch_moments, inverse_std, merge_moments
from tpdeb.tpdeb_core.numpy_policy import LOG_2PI, NumpyPolicy

# --- diagonal Gaussian ---------------------------------------------------------------------------


def gaussian_log_prob(
    mean: torch.Tensor, log_std: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """log N(action; mean, exp(log_std)²), summed over the last (action) dimension."""
    z = (action - mean) * torch.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * LOG_2PI).sum(-1)


def state_arrays(state: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """A state dict as numpy arrays (views of the tensors: copy before they change)."""
    return {k: v.detach().cpu().numpy() for k, v in state.items()}


# --- running moments -----------------------------------------------------------------------------


class RunningMeanStd(nn.Module):
    """Running mean/variance, merged with Chan et al.'s parallel update.

    Actors compute the moments of the data they collect; the learner merges them and ships the
    merged state with the parameters. Stored in float64 buffers so long runs do not drift.
    """

    def __init__(self, shape: Sequence[int] | int = (), epsilon: float = NORM_EPSILON):
        super().__init__()
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        self.epsilon = epsilon
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(shape, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(shape, dtype=torch.float64))

    @property
    def var(self) -> torch.Tensor:
        if self.count.item() < 2:
            return torch.ones_like(self.mean)
        return self.m2 / self.count

    @torch.no_grad()
    def merge(self, count: float, mean, m2) -> None:
        """Fold in the moments (count, mean, M2) of another sample set."""
        n, mean_ab, m2_ab = merge_moments(
            self.moments(), (count, np.asarray(mean).reshape(self.mean.shape),
                             np.asarray(m2).reshape(self.m2.shape)))
        self.count.fill_(n)
        self.mean.copy_(torch.as_tensor(mean_ab))
        self.m2.copy_(torch.as_tensor(m2_ab))

    def update(self, x: np.ndarray) -> None:
        self.merge(*batch_moments(x))

    def moments(self) -> tuple[float, np.ndarray, np.ndarray]:
        return float(self.count.item()), self.mean.numpy().copy(), self.m2.numpy().copy()

    def normalize(self, x: torch.Tensor, clip: float | None = None) -> torch.Tensor:
        y = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.epsilon)
        return y.clamp(-clip, clip) if clip is not None else y


# --- networks ------------------------------------------------------------------------------------


def mlp(sizes: Sequence[int], out_gain: float) -> nn.Sequential:
    """Tanh MLP with orthogonal init; the last layer's gain sets the initial output scale."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        last = i == len(sizes) - 2
        linear = nn.Linear(sizes[i], sizes[i + 1])
        nn.init.orthogonal_(linear.weight, out_gain if last else math.sqrt(2.0))
        nn.init.zeros_(linear.bias)
        layers.append(linear)
        if not last:
            layers.append(nn.Tanh())
    return nn.Sequential(*layers)


class GaussianPolicy(nn.Module):
    """Mean from an MLP, state-independent learned log-std (DESIGN §2)."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int], init_log_std: float):
        super().__init__()
        # Gain 0.01 starts every action near 0 with the full exploration of log_std.
        self.mean = mlp([obs_dim, *hidden, act_dim], out_gain=0.01)
        self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))

    def forward(self, obs_norm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean = self.mean(obs_norm)
        return mean, self.log_std.expand_as(mean)


class ActorCritic(nn.Module):
    """Policy, value and both normalisers: everything an actor needs to act and to prioritise.

    `obs_rms` normalises observations; `ret_rms` tracks the discounted return whose std scales
    rewards at learn time (rewards are stored raw and scaled with current statistics).
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (64, 64),
        init_log_std: float = 0.0,
        obs_clip: float = 10.0,
    ):
        super().__init__()
        self.obs_dim, self.act_dim, self.obs_clip = obs_dim, act_dim, obs_clip
        self.policy = GaussianPolicy(obs_dim, act_dim, hidden, init_log_std)
        self.value_net = mlp([obs_dim, *hidden, 1], out_gain=1.0)
        self.obs_rms = RunningMeanStd(obs_dim)
        self.ret_rms = RunningMeanStd(())

    def norm_obs(self, obs_raw: torch.Tensor) -> torch.Tensor:
        return self.obs_rms.normalize(obs_raw, self.obs_clip).to(torch.float32)

    def reward_scale(self) -> float:
        """Multiplier for raw rewards: 1 / std of the discounted return."""
        rms = self.ret_rms  # in numpy: the torch ops of `var` cost more than the arithmetic
        return float(inverse_std(float(rms.count), rms.m2.numpy(), rms.epsilon))

    def value(self, obs_norm: torch.Tensor) -> torch.Tensor:
        return self.value_net(obs_norm).squeeze(-1)

    @torch.no_grad()
    def act(self, obs_raw: np.ndarray, generator: torch.Generator | None = None) -> dict:
        """Sample raw Gaussian actions for a batch of raw observations (numpy in, numpy out)."""
        obs = self.norm_obs(torch.as_tensor(obs_raw, dtype=torch.float32))
        mean, log_std = self.policy(obs)
        noise = torch.randn(mean.shape, generator=generator)
        action = mean + noise * torch.exp(log_std)
        return {
            "action": action.numpy(),
            "mean": mean.numpy(),
            "log_std": log_std.numpy(),
            "logp": gaussian_log_prob(mean, log_std, action).numpy(),
            "value": self.value(obs).numpy(),
        }

    @torch.no_grad()
    def act_deterministic(self, obs_raw: np.ndarray) -> np.ndarray:
        mean, _ = self.policy(self.norm_obs(torch.as_tensor(obs_raw, dtype=torch.float32)))
        return mean.numpy()

    @torch.no_grad()
    def values_of(self, obs_raw: np.ndarray) -> np.ndarray:
        return self.value(self.norm_obs(torch.as_tensor(obs_raw, dtype=torch.float32))).numpy()

    def arrays(self) -> dict[str, np.ndarray]:
        """The state (parameters and normalisers) as numpy arrays, by state_dict name."""
        return state_arrays(self.state_dict())

    def numpy_policy(self) -> NumpyPolicy:
        """A torch-free copy of the acting path; it does not follow later changes."""
        return NumpyPolicy(self.arrays(), self.obs_clip)
