"""The loss of `tpdeb_core/loss.py` with its gradient derived by hand: a fast path, not the
definition (DESIGN §2 "The loss"; tests/test_loss.py holds every term and every parameter
gradient to the autograd loss over each configuration it accepts).

The loss is a function of three network outputs — the policy mean [T, B, A], the values
[T+1, B] and the global log-std [A] — whose gradient with respect to them has a closed form.
It is computed in numpy and handed to autograd for the networks' backward pass only: at 64×64
each torch operation costs more in dispatch than in arithmetic, and the loss's ~45 elementwise
ops and their backward nodes cost more than the few numpy expressions that replace them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tpdeb.tpdeb_core.loss import LossTerms, Targets
from tpdeb.tpdeb_core.loss_config import LossConfig
from tpdeb.tpdeb_core.policy import LOG_2PI


@dataclass
class Gradients:
    """∂L/∂(mean [T, B, A], values [T+1, B], log-std [A]), float32."""

    mean: np.ndarray
    values: np.ndarray
    log_std: np.ndarray


def loss_and_gradients(cfg: LossConfig, kl_coef: float, batch, t: Targets, mean: np.ndarray,
                       log_std: np.ndarray, values: np.ndarray,
                       logp: np.ndarray) -> tuple[Gradients, LossTerms]:
    """With d = a − m, σ⁻² = exp(−2 log σ) and r = exp(log r):
      pg = −Σ w·min(r·A, clip(r, 1−ε, 1+ε)·A) = −Σ w·A·clamp(r, lo, hi), where hi = 1+ε for
           A > 0 (else ∞) and lo = 1−ε for A < 0 (else −∞): the same value and gradient;
      value = ½ Σ w (V − v)²;  entropy = Σ_a log σ_a + A/2 (1 + log 2π);
      KL(μ‖π) = Σ w ½ Σ_a [σ_μ²/σ² + (m_μ − m)²/σ² − 1 − 2 (log σ_μ − log σ)].
    ∂log r/∂m = d σ⁻², ∂log r/∂log σ = d² σ⁻² − 1 per action dimension, ∂r/∂log r = r.
    `logp` is log π_θ(a|s) of these outputs (the learner has it already)."""
    w, adv, act_dim = t.weights, t.advantages, log_std.size
    inv_var = np.exp(-2.0 * log_std)
    d = batch.actions - mean
    log_ratio = logp - batch.behaviour_logp + t.log_is
    r = np.exp(log_ratio)
    positive = adv > 0
    lo = np.where(positive, -np.inf, 1.0 - cfg.clip_coef)
    hi = np.where(positive, 1.0 + cfg.clip_coef, np.inf)
    weighted_adv = w * adv
    pg_loss = -float((weighted_adv * np.clip(r, lo, hi)).sum())
    # d pg / d log r: zero where the clamp holds r (torch.clamp's gradient passes at its bounds)
    g_logp = -weighted_adv * ((r >= lo) & (r <= hi)) * r  # [T, B]
    v_error = values[:-1] - t.vs
    w3 = w[..., None]
    mu_gap = batch.behaviour_mean - mean  # [T, B, A]
    spread = (w3 * (np.exp(2.0 * batch.behaviour_log_std) + mu_gap * mu_gap)).sum((0, 1))
    mu_log_std = float((w3 * batch.behaviour_log_std).sum())
    kl = 0.5 * float((inv_var * spread).sum() - act_dim - 2.0 * (mu_log_std - log_std.sum()))
    g_pg = g_logp[..., None] * d  # [T, B, A], times σ⁻² below
    grad_values = np.zeros_like(values, dtype=np.float32)
    grad_values[:-1] = cfg.vf_coef * w * v_error
    grads = Gradients(
        mean=((g_pg - kl_coef * w3 * mu_gap) * inv_var).astype(np.float32),
        values=grad_values,
        log_std=((g_pg * d).sum((0, 1)) * inv_var - g_logp.sum() - cfg.ent_coef
                 + kl_coef * (1.0 - inv_var * spread)).astype(np.float32))
    terms = LossTerms(pg_loss, 0.5 * float((w * v_error * v_error).sum()),
                      float(log_std.sum() + 0.5 * (1.0 + LOG_2PI) * act_dim), kl, log_ratio)
    return grads, terms
