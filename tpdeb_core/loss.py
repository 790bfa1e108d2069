"""The TPDEB loss, the definition (DESIGN §2 "The loss"): written once, in torch, differentiated
by autograd and compiled with the rest of the update (`tpdeb_core/learner.py`). To change the
algorithm, change this file.

Notation as DESIGN §2: π_θ the policy being trained, π_θ̄ the target policy, μ the behaviour
policy that acted (its log-prob, mean and log-std are stored in the batch), w the replay's
importance weights. Tensors are time-major [T, B] (actions [T, B, A]; values [T+1, B]) and live
on the learner's device; nothing here reads a value back to the host.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.model import TORCH
from tpdeb.tpdeb_core.vtrace import vtrace_terms


@dataclass
class Targets:
    """What an update regresses to and weighs by: constants of the loss (no gradient)."""

    weights: torch.Tensor  # w [T, B], Σ w = 1: E_w[ℓ] = Σ w·ℓ
    vs: torch.Tensor  # V-trace value targets v_t
    advantages: torch.Tensor  # A_t, normalised per batch when norm_adv
    log_is: torch.Tensor | float  # log is_t = log min(μ/π_θ̄, ρ̄_target); 0 when the clip is PPO's
    rhos: torch.Tensor  # ρ_t = min(ρ̄, π_θ̄/μ)
    deltas: torch.Tensor  # δ_t = r_t + γ_t V(s_{t+1}) − V(s_t), for the new priorities


@dataclass
class LossTerms:
    """One update's loss terms (0-d tensors, detached, for the metrics) and its log-ratio
    log r [T, B]."""

    policy: torch.Tensor
    value: torch.Tensor
    entropy: torch.Tensor
    kl: torch.Tensor
    log_ratio: torch.Tensor


def replay_weights(weights: torch.Tensor) -> torch.Tensor:
    """w [T, B] with Σ w = 1 from the replay's importance weights, one per step (a fragment's
    weight repeated over its steps, or step-level PER's own). Normalising by Σ w rather than by
    the count keeps the terms in proportion whatever the weights' scale: step-level PER's
    (p/p_min)^(−β) can all sit far below 1, and a count-normalised surrogate would vanish
    beside the entropy bonus."""
    return weights / weights.sum().clamp(min=1e-12)


def targets(cfg: LossConfig, w: torch.Tensor, behaviour_logp: torch.Tensor,
            target_logp: torch.Tensor, rewards: torch.Tensor, values: torch.Tensor,
            discounts: torch.Tensor) -> Targets:
    """Step 1, V-trace toward π_θ̄ (or toward π_θ when the clip is PPO's: `target_logp` is then
    the current policy's): ρ_t = min(ρ̄, π_θ̄/μ), c_t = λ·min(c̄, π_θ̄/μ),
    v_s − V(s_s) = ρ_s δ_s + γ_s c_s (v_{s+1} − V(s_{s+1})), A_t = min(ρ̄_pg, π_θ̄/μ)·(r_t +
    γ_t v_{t+1} − V(s_t)); and step 2's is_t = min(μ/π_θ̄, ρ̄_target). `values` [T+1, B]."""
    vs, adv, rhos, deltas = vtrace_terms(
        behaviour_logp, target_logp, rewards, values[:-1], values[-1], discounts, cfg.rho_bar,
        cfg.c_bar, cfg.rho_pg_bar, cfg.vtrace_lambda)
    if cfg.norm_adv:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    log_is = (torch.clamp(behaviour_logp - target_logp, max=math.log(cfg.rho_target_bar))
              if cfg.clip_anchor == "target" else 0.0)
    return Targets(w, vs, adv, log_is, rhos, deltas)


def loss(cfg: LossConfig, kl_coef: float, batch, t: Targets, mean: torch.Tensor,
         log_std: torch.Tensor, values: torch.Tensor) -> tuple[torch.Tensor, LossTerms]:
    """L = L_pg + c_v·L_v − c_ent·H + λ_kl·L_kl on the networks' outputs (mean [T, B, A],
    log-std [A] or [T, B, A], values [T+1, B]); returns (L with its graph, the terms)."""
    w = t.weights
    E = lambda x: (w * x).sum()  # noqa: E731  the weighted mean E_w[·] of every per-step term
    ops = TORCH
    logp = policy.log_prob(mean, log_std, batch.actions, ops)
    # 2. r_t = is_t · π_θ/μ: the clip is centred on the target policy (IMPACT) or on μ (PPO)
    log_ratio = logp - batch.behaviour_logp + t.log_is
    ratio = torch.exp(log_ratio)
    adv = t.advantages
    clipped = torch.clamp(ratio, 1.0 - cfg.clip_coef, 1.0 + cfg.clip_coef)
    policy_loss = -E(torch.min(ratio * adv, clipped * adv))
    # 3. KL(μ ‖ π_θ) from the stored behaviour mean and log-std
    kl = E(policy.kl(batch.behaviour_mean, batch.behaviour_log_std, mean, log_std, ops))
    # 4. the value regression to the V-trace targets, and the entropy
    value_loss = 0.5 * E((values[:-1] - t.vs) ** 2)
    entropy = E(policy.entropy(log_std, ops))
    total = policy_loss + cfg.vf_coef * value_loss - cfg.ent_coef * entropy + kl_coef * kl
    return total, LossTerms(policy_loss.detach(), value_loss.detach(), entropy.detach(),
                            kl.detach(), log_ratio.detach())

