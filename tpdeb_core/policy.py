"""The policy, declared once (DESIGN §2 "Policy"): the layers and their names, observation
normalisation, the tanh MLPs, and the diagonal Gaussian's sample, log-prob, entropy and KL.

Every function takes `ops`, the few array operations the policy needs: `NUMPY` below for the
actors (which never import torch) and `TORCH` in `tpdeb_core/model.py` for the learner. Both
backends therefore compute the same function of the same parameters, and a change here changes
both. A five-method backend rather than the array-API standard: numpy and torch differ exactly
where speed lives at these sizes (torch's fused `linear`; numpy's matmul on weights held
transposed), and the backend keeps each one's fastest form without forking the math.

Parameters are named as the torch model's `state_dict()` names them; `param_shapes` is the
specification that a parameter message, a checkpoint and both backends are checked against.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from tpdeb.tpdeb_core.moments import inverse_std

LOG_2PI = math.log(2.0 * math.pi)
MEAN_NET, VALUE_NET = "policy.mean", "value_net"
LOG_STD, LOG_STD_HEAD = "policy.log_std", "policy.log_std_head"
# The policy's standard deviation: one learned log-std per action dimension (global), or a
# linear head on the mean network's last hidden layer (state), bounded so that a head driven
# far by one batch cannot make a Gaussian that is a point or spans the whole action space.
POLICY_STDS = ("global", "state")
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


def param_shapes(obs_dim: int, act_dim: int, hidden: Sequence[int],
                 policy_std: str = "global") -> dict[str, tuple]:
    """Every array of the model's state with its shape: the networks (Linear layers at even
    indices, tanh between), the policy's log-std (a parameter or a head) and the normalisers'
    moments."""
    if policy_std not in POLICY_STDS:
        raise ValueError(f"policy_std={policy_std!r}: use one of {POLICY_STDS}")
    shapes: dict[str, tuple] = {}
    for net, out_dim in ((MEAN_NET, act_dim), (VALUE_NET, 1)):
        sizes = [obs_dim, *hidden, out_dim]
        for i in range(len(sizes) - 1):
            shapes[f"{net}.{2 * i}.weight"] = (sizes[i + 1], sizes[i])
            shapes[f"{net}.{2 * i}.bias"] = (sizes[i + 1],)
    if policy_std == "global":
        shapes[LOG_STD] = (act_dim,)
    else:
        shapes[f"{LOG_STD_HEAD}.weight"] = (act_dim, hidden[-1])
        shapes[f"{LOG_STD_HEAD}.bias"] = (act_dim,)
    for rms, dim in (("obs_rms", (obs_dim,)), ("ret_rms", ())):
        shapes.update({f"{rms}.count": (), f"{rms}.mean": dim, f"{rms}.m2": dim})
    return shapes


def policy_std_of(names) -> str:
    """Which standard deviation a state with these array names has."""
    return "state" if f"{LOG_STD_HEAD}.weight" in names else "global"


def dims_of(arrays: Mapping[str, np.ndarray]) -> tuple[int, int, tuple[int, ...]]:
    """(obs_dim, act_dim, hidden sizes) of a model's state."""
    weights = [arrays[f"{MEAN_NET}.{i}.weight"] for i in layer_indices(arrays, MEAN_NET)]
    return (int(weights[0].shape[1]), int(weights[-1].shape[0]),
            tuple(int(w.shape[0]) for w in weights[:-1]))


def layer_indices(arrays, net: str) -> list[int]:
    return sorted(int(name.split(".")[-2]) for name in arrays
                  if name.startswith(f"{net}.") and name.endswith(".weight"))


# --- the backend -------------------------------------------------------------------------------


class NumpyOps:
    """numpy: a layer is (Wᵀ contiguous, b), so x @ Wᵀ is one matmul on row-major activations
    and the bias and tanh are applied in place."""

    exp = staticmethod(np.exp)

    @staticmethod
    def linear(x, layer):
        weight_t, bias = layer
        y = x @ weight_t
        y += bias
        return y

    @staticmethod
    def tanh(x):
        return np.tanh(x, out=x)

    @staticmethod
    def clip(x, low: float, high: float):
        return np.clip(x, low, high, out=x)  # every caller clips an array it just made


NUMPY = NumpyOps()


def numpy_layer(arrays: Mapping[str, np.ndarray], name: str) -> tuple[np.ndarray, np.ndarray]:
    """The layer `name` for `NUMPY` (float16 weights, as a reduced-precision broadcast sends
    them, are widened)."""
    return (np.ascontiguousarray(np.asarray(arrays[f"{name}.weight"], np.float32).T),
            np.asarray(arrays[f"{name}.bias"], np.float32).copy())


def numpy_layers(arrays: Mapping[str, np.ndarray], net: str) -> list:
    return [numpy_layer(arrays, f"{net}.{i}") for i in layer_indices(arrays, net)]


# --- the networks ------------------------------------------------------------------------------


def normalize(obs, mean, inv_std, clip: float | None, ops):
    """(obs − mean) / std of the running moments, clipped to ±clip."""
    x = (obs - mean) * inv_std
    return ops.clip(x, -clip, clip) if clip is not None else x


def features(layers, x, ops):
    """tanh(linear(·)) through `layers`: an MLP's hidden part."""
    for layer in layers:
        x = ops.tanh(ops.linear(x, layer))
    return x


def mlp(layers, x, ops):
    """The tanh MLP: hidden layers, then a linear output."""
    return ops.linear(features(layers[:-1], x, ops), layers[-1])


def gaussian(mean_layers, log_std, obs, ops):
    """The policy on normalised observations: (mean [..., A], log-std). `log_std` is the
    global parameter [A] (returned as it is: it broadcasts against the mean) or the state
    head's layer, applied to the mean network's last hidden features and bounded."""
    hidden = features(mean_layers[:-1], obs, ops)
    mean = ops.linear(hidden, mean_layers[-1])
    if isinstance(log_std, tuple):
        return mean, ops.clip(ops.linear(hidden, log_std), LOG_STD_MIN, LOG_STD_MAX)
    return mean, log_std


# --- the diagonal Gaussian (sums run over the last, action, axis) -------------------------------


def log_prob(mean, log_std, action, ops):
    """log N(action; mean, exp(log_std)²)."""
    z = (action - mean) * ops.exp(-log_std)
    return (-0.5 * z * z - log_std).sum(-1) - 0.5 * LOG_2PI * z.shape[-1]


def sample(mean, log_std, noise, ops):
    """(action, its log-prob) for standard normal `noise`: a = m + σ·z, whose log-prob is
    −z²/2 − log σ − log(2π)/2 per dimension (no division needed)."""
    action = mean + noise * ops.exp(log_std)
    return action, (-0.5 * noise * noise - log_std).sum(-1) - 0.5 * LOG_2PI * noise.shape[-1]


def entropy(log_std, ops):
    """H = Σ_a log σ_a + ½(1 + log 2π) per dimension."""
    return (log_std + 0.5 * (1.0 + LOG_2PI)).sum(-1)


def kl(mean_p, log_std_p, mean_q, log_std_q, ops):
    """KL(p ‖ q) of diagonal Gaussians:
    Σ_a log σ_q − log σ_p + (σ_p² + (m_p − m_q)²) / (2σ_q²) − ½."""
    gap = mean_p - mean_q
    spread = ops.exp(2.0 * log_std_p) + gap * gap
    return (log_std_q - log_std_p + 0.5 * spread * ops.exp(-2.0 * log_std_q) - 0.5).sum(-1)


# --- the actors' policy ------------------------------------------------------------------------


class NumpyPolicy:
    """The acting path in numpy, from a model state's arrays (the `Params` message's): a
    Gaussian sample per row with its mean, log-std, log-prob and value. Actors act and score
    their fragments with it, so they never import torch (~200 MiB and ~0.8 s per process); at
    an actor's batch sizes numpy is also faster than torch's per-call overhead."""

    def __init__(self, arrays: Mapping[str, np.ndarray], obs_clip: float | None):
        self.mean_layers = numpy_layers(arrays, MEAN_NET)
        self.value_layers = numpy_layers(arrays, VALUE_NET)
        self.policy_std = policy_std_of(arrays)
        self.log_std = (numpy_layer(arrays, LOG_STD_HEAD) if self.policy_std == "state"
                        else np.asarray(arrays[LOG_STD], np.float32).copy())
        self.act_dim = int(np.asarray(arrays[f"{LOG_STD_HEAD}.bias" if self.policy_std == "state"
                                             else LOG_STD]).size)
        self.obs_mean = np.asarray(arrays["obs_rms.mean"], np.float32).copy()
        self.obs_inv_std = inverse_std(float(arrays["obs_rms.count"]),
                                       arrays["obs_rms.m2"]).astype(np.float32)
        self._reward_scale = float(inverse_std(float(arrays["ret_rms.count"]),
                                               arrays["ret_rms.m2"]))
        self.obs_clip = obs_clip

    def reward_scale(self) -> float:
        """Multiplier for raw rewards: 1 / std of the discounted return."""
        return self._reward_scale

    def _norm(self, obs_raw: np.ndarray) -> np.ndarray:
        return normalize(np.asarray(obs_raw, np.float32), self.obs_mean, self.obs_inv_std,
                         self.obs_clip, NUMPY)

    def act(self, obs_raw: np.ndarray, rng: np.random.Generator) -> dict:
        obs = self._norm(obs_raw)
        mean, log_std = gaussian(self.mean_layers, self.log_std, obs, NUMPY)
        noise = rng.standard_normal(mean.shape, dtype=np.float32)
        action, logp = sample(mean, log_std, noise, NUMPY)
        return {"action": action, "mean": mean, "log_std": np.broadcast_to(log_std, mean.shape),
                "logp": logp.astype(np.float32), "value": mlp(self.value_layers, obs, NUMPY)[:, 0]}

    def act_deterministic(self, obs_raw: np.ndarray) -> np.ndarray:
        return gaussian(self.mean_layers, self.log_std, self._norm(obs_raw), NUMPY)[0]

    def values_of(self, obs_raw: np.ndarray) -> np.ndarray:
        return mlp(self.value_layers, self._norm(obs_raw), NUMPY)[:, 0]
