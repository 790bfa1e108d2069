"""V-trace targets (Espeholt et al. 2018): step 1 of the learner loss, written once, in torch.

The reverse recursion  a_s = ρ_s δ_s + γ_s c_s a_{s+1}  is a linear recurrence: it runs as a
doubling scan, log2(T) rounds of whole-tensor operations instead of T steps of a loop, exact at
terminations (γ_k c_k = 0) with no division. Every shape is static, so a compiled update fuses
the rounds with the rest of the targets. The learner (`tpdeb_core/learner.py`) and `vtrace`, the
public form, run this same code.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class VTraceTerms(NamedTuple):
    vs: torch.Tensor  # [T, B] value targets v_s
    pg_advantages: torch.Tensor  # [T, B] ρ^pg_t (r_t + γ_t v_{t+1} − V(x_t))
    clipped_rhos: torch.Tensor  # [T, B] ρ_t
    deltas: torch.Tensor  # [T, B] δ_t = r_t + γ_t V(x_{t+1}) − V(x_t)


def discounted_sums(x: torch.Tensor, decay: torch.Tensor) -> torch.Tensor:
    """a_s = x_s + decay_s · a_{s+1} backwards over axis 0 (a_T = 0), [T, ...] in and out.

    A doubling scan (Hillis & Steele; Blelloch's form for linear recurrences): after the round
    with stride k, a_s holds the 2k terms Σ_{j<2k} (Π_{i<j} decay_{s+i}) x_{s+j} and g_s the
    product of 2k decays. Only products and sums: exact at terminations (decay 0)."""
    a, g = x, decay
    k, steps = 1, x.shape[0]
    while k < steps:
        a = torch.cat([a[:-k] + g[:-k] * a[k:], a[-k:]])
        g = torch.cat([g[:-k] * g[k:], g[-k:]])
        k *= 2
    return a


def vtrace_terms(
    behaviour_logp: torch.Tensor,
    target_logp: torch.Tensor,
    rewards: torch.Tensor,
    values: torch.Tensor,
    bootstrap_value: torch.Tensor,
    discounts: torch.Tensor,
    rho_bar: float = 1.0,
    c_bar: float = 1.0,
    rho_pg_bar: float = 1.0,
    lambda_: float = 1.0,
) -> VTraceTerms:
    """V-trace with the intermediate terms the learner also needs (priorities use ρδ), all
    without gradient. `lambda_` scales the traces, c_t = λ·min(c̄, π/μ) (as rlax's and Sample
    Factory's V-trace): λ < 1 trades the targets' variance for bias, like GAE's λ."""
    with torch.no_grad():
        ratios = torch.exp(target_logp - behaviour_logp)
        rhos = torch.clamp(ratios, max=rho_bar)
        cs = lambda_ * torch.clamp(ratios, max=c_bar)
        next_values = torch.cat([values[1:], bootstrap_value[None]])
        deltas = rewards + discounts * next_values - values
        vs = values + discounted_sums(rhos * deltas, discounts * cs)
        next_vs = torch.cat([vs[1:], bootstrap_value[None]])
        pg_advantages = torch.clamp(ratios, max=rho_pg_bar) * (rewards + discounts * next_vs
                                                               - values)
    return VTraceTerms(vs, pg_advantages, rhos, deltas)


def vtrace(
    behaviour_logp: torch.Tensor,
    target_logp: torch.Tensor,
    rewards: torch.Tensor,
    values: torch.Tensor,
    bootstrap_value: torch.Tensor,
    discounts: torch.Tensor,
    rho_bar: float = 1.0,
    c_bar: float = 1.0,
    rho_pg_bar: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """V-trace value targets and policy-gradient advantages.

    All tensors time-major [T, B] except bootstrap_value [B]; `discounts` is γ_t, already zero
    where the episode terminated. Returns (vs, pg_advantages), both without gradient.
    """
    terms = vtrace_terms(
        behaviour_logp, target_logp, rewards, values, bootstrap_value, discounts,
        rho_bar, c_bar, rho_pg_bar,
    )
    return terms.vs, terms.pg_advantages
