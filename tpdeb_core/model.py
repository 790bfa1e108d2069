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

from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.moments import NORM_EPSILON, batch_moments, inverse_std, merge_moments
from tpdeb.tpdeb_core.policy import NumpyPolicy

# --- the torch backend of the policy's definition ----------------------------------------------


class TorchOps:
    """torch: a layer is (W, b) for the fused `linear`."""

    exp = staticmethod(torch.exp)
    clip = staticmethod(torch.clamp)

    @staticmethod
    def tanh(x):
        """tanh x = 2σ(2x) − 1, equal to torch.tanh within 2e-7: on the CPU torch's sigmoid
        kernel takes ~14 µs for a [512, 64] activation where its tanh takes ~84 µs (and
        compiled, ~30 against ~65), and the hidden layers' tanh were a third of an update."""
        return 2.0 * torch.sigmoid(2.0 * x) - 1.0

    @staticmethod
    def linear(x, layer):
        return torch.nn.functional.linear(x, *layer)


TORCH = TorchOps()


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


def linear_layers(net: nn.Sequential) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """A network's (weight, bias) pairs, read from the modules at each call: under
    `torch.func.functional_call` they are the tensors being differentiated."""
    return [(m.weight, m.bias) for m in net if isinstance(m, nn.Linear)]


class GaussianPolicy(nn.Module):
    """Mean from an MLP; the log-std a learned parameter (`policy_std="global"`) or a head on
    the mean network's last hidden layer (`"state"`), as `tpdeb_core.policy.gaussian` reads
    them."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: Sequence[int], init_log_std: float,
                 policy_std: str = "global"):
        super().__init__()
        if policy_std not in policy.POLICY_STDS:
            raise ValueError(f"policy_std={policy_std!r}: use one of {policy.POLICY_STDS}")
        # Gain 0.01 starts every action near 0 with the full exploration of log_std.
        self.mean = mlp([obs_dim, *hidden, act_dim], out_gain=0.01)
        self.policy_std = policy_std
        if policy_std == "global":
            self.log_std = nn.Parameter(torch.full((act_dim,), float(init_log_std)))
        else:  # starts at init_log_std everywhere, and moves with the state as it learns
            self.log_std_head = nn.Linear(hidden[-1], act_dim)
            nn.init.orthogonal_(self.log_std_head.weight, 0.01)
            nn.init.constant_(self.log_std_head.bias, float(init_log_std))

    @property
    def log_std_source(self):
        """What `policy.gaussian` takes: the parameter, or the head's layer."""
        if self.policy_std == "global":
            return self.log_std
        return (self.log_std_head.weight, self.log_std_head.bias)

    def forward(self, obs_norm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean, log-std); the global log-std is [A] and broadcasts against the mean."""
        return policy.gaussian(linear_layers(self.mean), self.log_std_source, obs_norm, TORCH)


class ActorCritic(nn.Module):
    """Policy, value and both normalisers: everything an actor needs to act and to prioritise.

    `obs_rms` normalises observations; `ret_rms` tracks the discounted return whose std scales
    rewards at learn time (rewards are stored raw and scaled with current statistics). The
    functions are `tpdeb_core.policy`'s on the torch backend; the module holds the parameters.
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: Sequence[int] = (64, 64),
        init_log_std: float = 0.0,
        obs_clip: float = 10.0,
        policy_std: str = "global",
    ):
        super().__init__()
        self.obs_dim, self.act_dim, self.obs_clip = obs_dim, act_dim, obs_clip
        self.policy = GaussianPolicy(obs_dim, act_dim, hidden, init_log_std, policy_std)
        self.value_net = mlp([obs_dim, *hidden, 1], out_gain=1.0)
        self.obs_rms = RunningMeanStd(obs_dim)
        self.ret_rms = RunningMeanStd(())

    @property
    def device(self) -> torch.device:
        """Where the networks are (the normalisers' moments always stay on the CPU)."""
        return self.value_net[0].weight.device

    def to_device(self, device: torch.device | str) -> ActorCritic:
        """Move the networks (policy and value) to `device`; the normalisers stay where they
        are, read and merged in numpy."""
        self.policy.to(device)
        self.value_net.to(device)
        return self

    def obs_affine(self) -> tuple[np.ndarray, np.ndarray]:
        """The observation normaliser's current (mean, 1/std) as float32 arrays."""
        rms = self.obs_rms
        return (rms.mean.numpy().astype(np.float32),
                inverse_std(float(rms.count), rms.m2.numpy(), rms.epsilon).astype(np.float32))

    def norm_obs(self, obs_raw: torch.Tensor) -> torch.Tensor:
        """Normalised observations on the networks' device."""
        mean, inv_std = (torch.from_numpy(x) for x in self.obs_affine())
        obs = policy.normalize(torch.as_tensor(obs_raw, dtype=torch.float32), mean, inv_std,
                               self.obs_clip, TORCH)
        return obs.to(self.device)

    def reward_scale(self) -> float:
        """Multiplier for raw rewards: 1 / std of the discounted return."""
        rms = self.ret_rms  # in numpy: the torch ops of `var` cost more than the arithmetic
        return float(inverse_std(float(rms.count), rms.m2.numpy(), rms.epsilon))

    def value(self, obs_norm: torch.Tensor) -> torch.Tensor:
        return policy.mlp(linear_layers(self.value_net), obs_norm, TORCH).squeeze(-1)

    @torch.no_grad()
    def act(self, obs_raw: np.ndarray, generator: torch.Generator | None = None) -> dict:
        """Sample raw Gaussian actions for a batch of raw observations (numpy in, numpy out)."""
        obs = self.norm_obs(obs_raw)
        mean, log_std = self.policy(obs)
        noise = torch.randn(mean.shape, generator=generator).to(mean.device)
        action, logp = policy.sample(mean, log_std, noise, TORCH)
        return {"action": action.numpy(force=True), "mean": mean.numpy(force=True),
                "log_std": log_std.detach().expand_as(mean).numpy(force=True),
                "logp": logp.numpy(force=True), "value": self.value(obs).numpy(force=True)}

    @torch.no_grad()
    def act_deterministic(self, obs_raw: np.ndarray) -> np.ndarray:
        return self.policy(self.norm_obs(obs_raw))[0].numpy(force=True)

    @torch.no_grad()
    def values_of(self, obs_raw: np.ndarray) -> np.ndarray:
        return self.value(self.norm_obs(obs_raw)).numpy(force=True)

    def arrays(self) -> dict[str, np.ndarray]:
        """The state (parameters and normalisers) as numpy arrays, by state_dict name."""
        return state_arrays(self.state_dict())

    def numpy_policy(self) -> NumpyPolicy:
        """A torch-free copy of the acting path; it does not follow later changes."""
        return NumpyPolicy(self.arrays(), self.obs_clip)
