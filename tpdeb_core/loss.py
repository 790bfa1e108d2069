"""The TPDEB loss, the definition (DESIGN §2 "The loss"): written once, in torch, differentiated
by autograd. To change the algorithm, change this file; a fast path (`tpdeb_core/closed_form.py`)
is held to it by tests/test_loss.py and refuses what it does not implement.

Notation as DESIGN §2: π_θ the policy being trained, π_θ̄ the target policy, μ the behaviour
policy that acted (its log-prob, mean and log-std are stored in the batch), w the replay's
importance weights. Arrays are time-major [T, B] (actions [T, B, A]; values [T+1, B]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.model import TORCH
from tpdeb.tpdeb_core.vtrace import vtrace_arrays


@dataclass
class Targets:
    """What an update regresses to and weighs by: constants of the loss (no gradient), numpy."""

    weights: np.ndarray  # w [T, B], Σ w = 1: E_w[ℓ] = Σ w·ℓ
    vs: np.ndarray  # V-trace value targets v_t
    advantages: np.ndarray  # A_t, normalised per batch when norm_adv
    log_is: np.ndarray | float  # log is_t = log min(μ/π_θ̄, ρ̄_target); 0 when the clip is PPO's
    rhos: np.ndarray  # ρ_t = min(ρ̄, π_θ̄/μ)
    deltas: np.ndarray  # δ_t = r_t + γ_t V(s_{t+1}) − V(s_t), for the new priorities


@dataclass
class LossTerms:
    """One update's loss terms (floats, for the metrics) and its log-ratio log r [T, B]."""

    policy: float
    value: float
    entropy: float
    kl: float
    log_ratio: np.ndarray


def replay_weights(weights: np.ndarray, step_weights: np.ndarray | None, steps: int) -> np.ndarray:
    """w [T, B] with Σ w = 1 from the replay's importance weights: one per fragment [B], or one
    per step [B, T] (step-level PER). Normalising by Σ w rather than by the count keeps the
    terms in proportion whatever the weights' scale: step-level PER's (p/p_min)^(−β) can all
    sit far below 1, and a count-normalised surrogate would vanish beside the entropy bonus."""
    if step_weights is not None:
        w = np.asarray(step_weights, np.float32)[:, :steps].T.copy()
    else:
        w = np.broadcast_to(np.asarray(weights, np.float32), (steps, len(weights))).copy()
    w /= max(float(w.sum()), 1e-12)
    return w


def targets(cfg: LossConfig, w: np.ndarray, behaviour_logp: np.ndarray, target_logp: np.ndarray,
            rewards: np.ndarray, values: np.ndarray, discounts: np.ndarray) -> Targets:
    """Step 1, V-trace toward π_θ̄ (or toward π_θ when the clip is PPO's: `target_logp` is then
    the current policy's): ρ_t = min(ρ̄, π_θ̄/μ), c_t = λ·min(c̄, π_θ̄/μ),
    v_s − V(s_s) = ρ_s δ_s + γ_s c_s (v_{s+1} − V(s_{s+1})), A_t = min(ρ̄_pg, π_θ̄/μ)·(r_t +
    γ_t v_{t+1} − V(s_t)); and step 2's is_t = min(μ/π_θ̄, ρ̄_target)."""
    vs, adv, rhos, deltas = vtrace_arrays(
        behaviour_logp, target_logp, rewards, values[:-1], values[-1], discounts, cfg.rho_bar,
        cfg.c_bar, cfg.rho_pg_bar, cfg.vtrace_lambda)
    if cfg.norm_adv:
        adv = adv - mean_of(adv)
        adv /= sample_std(adv) + 1e-8
    log_is = (np.minimum(behaviour_logp - target_logp, math.log(cfg.rho_target_bar))
              if cfg.clip_anchor == "target" else 0.0)
    return Targets(w, vs, adv, log_is, rhos, deltas)


def loss(cfg: LossConfig, kl_coef: float, batch, t: Targets, mean: torch.Tensor,
         log_std: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, LossTerms]:
    """L = L_pg + c_v·L_v − c_ent·H + λ_kl·L_kl on the networks' outputs (mean [T, B, A],
    log-std [A] or [T, B, A], values [T+1, B]); returns (L with its graph, the terms)."""
    def on(x) -> torch.Tensor:  # an array of the batch, where the networks are
        return torch.as_tensor(x).to(mean.device)

    w = on(t.weights)
    E = lambda x: (w * x).sum()  # noqa: E731  the weighted mean E_w[·] of every per-step term
    ops = TORCH
    logp = policy.log_prob(mean, log_std, on(batch.actions), ops)
    # 2. r_t = is_t · π_θ/μ: the clip is centred on the target policy (IMPACT) or on μ (PPO)
    log_ratio = logp - on(batch.behaviour_logp) + on(t.log_is)
    ratio = torch.exp(log_ratio)
    adv = on(t.advantages)
    clipped = torch.clamp(ratio, 1.0 - cfg.clip_coef, 1.0 + cfg.clip_coef)
    policy_loss = -E(torch.min(ratio * adv, clipped * adv))
    # 3. KL(μ ‖ π_θ) from the stored behaviour mean and log-std
    kl = E(policy.kl(on(batch.behaviour_mean), on(batch.behaviour_log_std), mean, log_std, ops))
    # 4. the value regression to the V-trace targets, and the entropy
    value_loss = 0.5 * E((values[:-1] - on(t.vs)) ** 2)
    entropy = E(policy.entropy(log_std, ops))
    total = policy_loss + cfg.vf_coef * value_loss - cfg.ent_coef * entropy + kl_coef * kl
    return total, LossTerms(policy_loss.item(), value_loss.item(), entropy.item(), kl.item(),
                            log_ratio.numpy(force=True))


def mean_of(x: np.ndarray) -> float:
    """The mean of all elements (np.mean's Python layers cost ~15 µs a call; a reduction alone
    a few)."""
    return float(np.add.reduce(x, axis=None)) / x.size


def sample_std(centred: np.ndarray) -> float:
    """The unbiased standard deviation of already centred values (for a [64, 8] batch a dot
    product, 0.6 µs, where np.std takes 7.5 µs)."""
    flat = centred.ravel()
    return math.sqrt(float(flat @ flat) / max(flat.size - 1, 1))
