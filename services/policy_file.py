"""A trained policy outside training: `policy.npz`, the acting path as plain arrays, and
`Policy`, which acts with numpy alone (no torch import), for a user's control loop.

`policy.npz` (numpy's zip of .npy arrays, read with allow_pickle=False: loading never runs code
from the file) holds the mean network's layers and the log-std as the model's state_dict names
them, the observation normaliser's moments, the action bounds, and `meta`, a JSON text: format,
env id and keyword arguments, dims, obs_clip, the policy's std kind. The learner writes one into
its run dir beside each final checkpoint; `tpdeb-export` writes one from any checkpoint.

    policy = load_policy("runs/Hopper-v5__tpdeb__1__1700000000")   # a run dir, .npz or .pt
    action = policy.act(obs, deterministic=True)    # [obs_dim] → [act_dim], or a batch
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from tpdeb.tpdeb_core.moments import inverse_std
from tpdeb.tpdeb_core.policy import (
    LOG_STD,
    LOG_STD_HEAD,
    MEAN_NET,
    NUMPY,
    dims_of,
    gaussian,
    normalize,
    numpy_layer,
    numpy_layers,
    policy_std_of,
    sample,
)

FORMAT, FORMAT_VERSION = "tpdeb-policy", 1
POLICY_FILE = "policy.npz"


class PolicyError(ValueError):
    """A policy file or checkpoint that cannot be used, or an observation it cannot take: one
    line saying which and why."""


def acting_arrays(model: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays of a model state that acting needs: the mean network, the log-std (parameter
    or head) and the observation normaliser."""
    keep = (f"{MEAN_NET}.", LOG_STD, f"{LOG_STD_HEAD}.", "obs_rms.")
    return {k: np.asarray(v) for k, v in model.items() if k.startswith(keep)}


def policy_meta(env_id: str, env_kwargs: str, obs_dim: int, act_dim: int, obs_clip: float,
                policy_std: str) -> dict:
    return {"format": FORMAT, "version": FORMAT_VERSION, "env_id": env_id,
            "env_kwargs": env_kwargs, "obs_dim": int(obs_dim), "act_dim": int(act_dim),
            "obs_clip": float(obs_clip), "policy_std": policy_std}


def policy_bytes(arrays: Mapping[str, np.ndarray], low, high, meta: dict) -> bytes:
    """A policy file's contents."""
    out = io.BytesIO()
    np.savez(out, **{k: np.asarray(v) for k, v in arrays.items()},
             action_low=np.asarray(low, np.float32), action_high=np.asarray(high, np.float32),
             meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    return out.getvalue()


class Policy:
    """A trained Gaussian policy in numpy: observations normalised by the run's statistics,
    a sample (or the mean action) clipped to the action bounds.

    `act(obs)` takes one observation [obs_dim] or a batch [N, obs_dim] and returns [act_dim]
    or [N, act_dim] float32. `rng` is the policy's own generator for the samples, seeded 0 at
    load: a script that loads and acts the same way gets the same actions."""

    def __init__(self, arrays: Mapping[str, np.ndarray], meta: dict, source: str = "policy"):
        self.meta, self.source = dict(meta), source
        self.rng = np.random.default_rng(0)
        # What a policy file holds of it, besides the bounds and meta (to write one back).
        self.file_arrays = {k: np.asarray(v) for k, v in arrays.items()
                            if k not in ("action_low", "action_high")}
        self.env_id, self.env_kwargs = meta["env_id"], meta.get("env_kwargs", "")
        self.obs_dim, self.act_dim = int(meta["obs_dim"]), int(meta["act_dim"])
        try:
            self.mean_layers = numpy_layers(arrays, MEAN_NET)
            self.log_std = (numpy_layer(arrays, LOG_STD_HEAD) if policy_std_of(arrays) == "state"
                            else np.asarray(arrays[LOG_STD], np.float32).copy())
            self.obs_mean = np.asarray(arrays["obs_rms.mean"], np.float32).copy()
            self.obs_inv_std = inverse_std(float(arrays["obs_rms.count"]),
                                           np.asarray(arrays["obs_rms.m2"])).astype(np.float32)
            self.low = np.asarray(arrays["action_low"], np.float32).copy()
            self.high = np.asarray(arrays["action_high"], np.float32).copy()
        except KeyError as exc:
            raise PolicyError(f"{source}: no array {exc.args[0]!r}: not a whole policy") from None
        self.obs_clip = float(meta["obs_clip"])
        first, last = self.mean_layers[0][0], self.mean_layers[-1][0]
        if (first.shape[0], last.shape[1]) != (self.obs_dim, self.act_dim) or (
                self.low.shape != (self.act_dim,) or self.obs_mean.shape != (self.obs_dim,)):
            raise PolicyError(f"{source}: its arrays do not fit obs_dim {self.obs_dim}, act_dim "
                              f"{self.act_dim}")

    def __repr__(self) -> str:
        return (f"Policy({self.env_id}, obs_dim={self.obs_dim}, act_dim={self.act_dim}, "
                f"from {self.source})")

    def _batch(self, obs) -> tuple[np.ndarray, bool]:
        x = np.asarray(obs, dtype=np.float32)
        if x.ndim == 1 and x.shape[0] == self.obs_dim:
            return x[None], True
        if x.ndim == 2 and x.shape[1] == self.obs_dim:
            return x, False
        raise PolicyError(f"an observation of shape {x.shape}, but this policy ({self.env_id}) "
                          f"takes ({self.obs_dim},) or (N, {self.obs_dim})")

    def act(self, obs, deterministic: bool = False,
            rng: np.random.Generator | None = None) -> np.ndarray:
        """The action for `obs`, clipped to the action bounds. As Stable-Baselines3's
        `predict(obs, deterministic=False)`, by default a sample from the Gaussian (noise from
        `rng`, else the policy's own generator); `deterministic=True`: its mean, what tpdeb-eval
        and the ONNX export act with."""
        x, single = self._batch(obs)
        x = normalize(x, self.obs_mean, self.obs_inv_std, self.obs_clip, NUMPY)
        mean, log_std = gaussian(self.mean_layers, self.log_std, x, NUMPY)
        if not deterministic:
            rng = rng if rng is not None else self.rng
            noise = rng.standard_normal(mean.shape, dtype=np.float32)
            mean = sample(mean, log_std, noise, NUMPY)[0]
        action = np.clip(mean, self.low, self.high).astype(np.float32)
        return action[0] if single else action


def read_policy_file(path: Path) -> Policy:
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise PolicyError(f"{path}: not a policy file ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0][:120] if str(exc) else ''})") from None
    try:
        meta = json.loads(arrays.pop("meta").tobytes().decode())
    except (KeyError, ValueError, UnicodeDecodeError):
        raise PolicyError(f"{path}: not a policy file (no readable meta)") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise PolicyError(f"{path}: not a policy file (format {meta.get('format')!r})"
                          if isinstance(meta, dict) else f"{path}: not a policy file")
    if meta.get("version") != FORMAT_VERSION:
        raise PolicyError(f"{path}: policy file version {meta.get('version')}; this TPDEB "
                          f"reads version {FORMAT_VERSION}")
    return Policy(arrays, meta, str(path))


def from_checkpoint(path: Path) -> Policy:
    """A policy from a learner checkpoint (this imports torch, to read the file)."""
    from tpdeb.services.store.checkpoint import read_checkpoint
    from tpdeb.tpdeb_core.model import state_arrays

    try:
        state = read_checkpoint(path)
    except ValueError as exc:
        raise PolicyError(f"{path}: {exc}") from None
    config, spec = state.get("config") or {}, state.get("spec") or {}
    model = state_arrays(state["model"])
    env_id = spec.get("env_id") or config.get("env_id")
    if not env_id:
        raise PolicyError(f"{path}: the checkpoint does not say which env it was trained on")
    obs_dim, act_dim, _ = dims_of(model)
    low, high = spec.get("action_low"), spec.get("action_high")
    if low is None or high is None:  # checkpoints from before they were recorded
        low, high = env_bounds(env_id, config.get("env_kwargs", ""), path)
    meta = policy_meta(env_id, config.get("env_kwargs", ""), obs_dim, act_dim,
                       config.get("obs_clip", 10.0), policy_std_of(model))
    arrays = {**acting_arrays(model), "action_low": np.asarray(low, np.float32),
              "action_high": np.asarray(high, np.float32)}
    return Policy(arrays, meta, str(path))


def env_bounds(env_id: str, env_kwargs: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    from tpdeb.services.config import ConfigError
    from tpdeb.services.envs import make_vector_env

    try:
        envs = make_vector_env(env_id, 1, env_kwargs)
    except ConfigError as exc:
        raise PolicyError(f"{path} records no action bounds, and its env cannot be made here "
                          f"to read them: {exc}") from None
    space = envs.single_action_space
    envs.close()
    return space.low, space.high


def find_checkpoint(run_dir: Path) -> Path:
    """A run dir's final checkpoint, else its newest one."""
    from tpdeb.services.store.checkpoint import FINAL, checkpoint_dir, list_checkpoints

    found = list_checkpoints(checkpoint_dir(run_dir))
    if not found:
        raise PolicyError(f"{run_dir}: no checkpoints in {checkpoint_dir(run_dir)} (has the "
                          "learner written one yet?)")
    finals = [c for c in found if c.tag == FINAL]
    return (finals or found)[-1].path


def load_policy(target: str | Path | Policy, env_id: str | None = None) -> Policy:
    """A run dir (its policy.npz, else its final checkpoint), a policy file or a checkpoint, as
    a numpy `Policy` (a `Policy` as it is); `env_id` refuses one trained on another env. Only a
    checkpoint needs torch, to read it."""
    if isinstance(target, Policy):
        policy = target
    else:
        target = Path(target)
        if target.is_dir():
            found = target / POLICY_FILE
            target = found if found.is_file() else find_checkpoint(target)
        elif not target.is_file():
            raise PolicyError(f"{target}: no such run directory, policy file or checkpoint")
        policy = read_policy_file(target) if target.suffix == ".npz" else from_checkpoint(target)
    if env_id is not None and env_id != policy.env_id:
        raise PolicyError(f"{policy.source} was trained on {policy.env_id}, not {env_id}")
    return policy
