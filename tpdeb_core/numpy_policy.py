"""The acting path in numpy: the policy's Gaussian sample, mean, log-prob and value from the
model's parameters as plain arrays (the `Params` message's, named as `ActorCritic.state_dict()`
names them).

Actors act and compute initial priorities with it, so they never import torch (about 200 MiB
and ~0.8 s of imports per process); for an actor's small batches numpy is also faster than
torch's per-call overhead. `tests/test_model.py` holds it to the torch model's outputs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from tpdeb.tpdeb_core.moments import inverse_std

LOG_2PI = math.log(2.0 * math.pi)
MEAN_NET, VALUE_NET = "policy.mean", "value_net"


def param_shapes(obs_dim: int, act_dim: int, hidden: Sequence[int]) -> dict[str, tuple]:
    """Every array of the model's state with its shape: what a parameter message must hold."""
    shapes: dict[str, tuple] = {}
    for net, out_dim in ((MEAN_NET, act_dim), (VALUE_NET, 1)):
        sizes = [obs_dim, *hidden, out_dim]
        for i in range(len(sizes) - 1):  # Linear layers sit at even indices (tanh between)
            shapes[f"{net}.{2 * i}.weight"] = (sizes[i + 1], sizes[i])
            shapes[f"{net}.{2 * i}.bias"] = (sizes[i + 1],)
    shapes["policy.log_std"] = (act_dim,)
    for rms, dim in (("obs_rms", (obs_dim,)), ("ret_rms", ())):
        shapes.update({f"{rms}.count": (), f"{rms}.mean": dim, f"{rms}.m2": dim})
    return shapes


def _layers(arrays: Mapping[str, np.ndarray], net: str) -> list[tuple[np.ndarray, np.ndarray]]:
    indices = sorted(int(name.split(".")[-2]) for name in arrays
                     if name.startswith(f"{net}.") and name.endswith(".weight"))
    # x @ Wᵀ with Wᵀ stored contiguous: one matmul per layer on row-major activations
    return [(np.ascontiguousarray(np.asarray(arrays[f"{net}.{i}.weight"], np.float32).T),
             np.asarray(arrays[f"{net}.{i}.bias"], np.float32).copy()) for i in indices]


def _forward(layers, x: np.ndarray) -> np.ndarray:
    for i, (weight, bias) in enumerate(layers):
        x = x @ weight
        x += bias
        if i < len(layers) - 1:
            np.tanh(x, out=x)
    return x


class NumpyPolicy:
    """Acts like `ActorCritic.act` / `values_of` on raw observations, from its state's arrays
    (float16 weights, as a reduced-precision broadcast sends them, are widened)."""

    def __init__(self, arrays: Mapping[str, np.ndarray], obs_clip: float | None):
        self.mean_layers = _layers(arrays, MEAN_NET)
        self.value_layers = _layers(arrays, VALUE_NET)
        self.log_std = np.asarray(arrays["policy.log_std"], np.float32).copy()
        self.obs_mean = np.asarray(arrays["obs_rms.mean"], np.float32).copy()
        self.obs_inv_std = inverse_std(float(arrays["obs_rms.count"]),
                                       arrays["obs_rms.m2"]).astype(np.float32)
        self._reward_scale = float(inverse_std(float(arrays["ret_rms.count"]),
                                               arrays["ret_rms.m2"]))
        self.obs_clip = obs_clip
        self.std = np.exp(self.log_std)
        self.log_norm = float(-self.log_std.sum() - 0.5 * LOG_2PI * self.log_std.size)

    @property
    def act_dim(self) -> int:
        return int(self.log_std.size)

    def reward_scale(self) -> float:
        """Multiplier for raw rewards: 1 / std of the discounted return."""
        return self._reward_scale

    def _norm(self, obs_raw: np.ndarray) -> np.ndarray:
        x = (np.asarray(obs_raw, np.float32) - self.obs_mean) * self.obs_inv_std
        return np.clip(x, -self.obs_clip, self.obs_clip, out=x) if self.obs_clip is not None \
            else x

    def act(self, obs_raw: np.ndarray, rng: np.random.Generator) -> dict:
        """A raw Gaussian sample per row with its mean, log-std, log-prob and value."""
        obs = self._norm(obs_raw)
        mean = _forward(self.mean_layers, obs)
        noise = rng.standard_normal(mean.shape, dtype=np.float32)
        return {
            "action": mean + noise * self.std,
            "mean": mean,
            "log_std": np.broadcast_to(self.log_std, mean.shape),
            # log N(a; m, σ) with a = m + σ·z is −z²/2 − Σ log σ − d/2 log 2π
            "logp": (-0.5 * np.square(noise).sum(-1) + self.log_norm).astype(np.float32),
            "value": _forward(self.value_layers, obs)[:, 0],
        }

    def act_deterministic(self, obs_raw: np.ndarray) -> np.ndarray:
        return _forward(self.mean_layers, self._norm(obs_raw))

    def values_of(self, obs_raw: np.ndarray) -> np.ndarray:
        return _forward(self.value_layers, self._norm(obs_raw))[:, 0]
