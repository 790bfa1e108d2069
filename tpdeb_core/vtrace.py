"""V-trace targets (Espeholt et al. 2018), SPEC §2 step 1, vectorised over time.

The reverse recursion  a_s = ρ_s δ_s + γ_s c_s a_{s+1}  is a linear recurrence, so
a_s = Σ_{t≥s} (Π_{k=s}^{t-1} γ_k c_k) ρ_t δ_t. We build the [T, T, B] matrix of those products
with one cumprod (no division, so terminations, γ_k c_k = 0, stay exact) and contract it with
ρδ. For T = 64 this is ~30× faster than a Python loop over T and agrees with it to float rounding.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class VTraceTerms(NamedTuple):
    vs: torch.Tensor  # [T, B] value targets v_s
    pg_advantages: torch.Tensor  # [T, B] ρ^pg_t (r_t + γ_t v_{t+1} − V(x_t))
    clipped_rhos: torch.Tensor  # [T, B] ρ_t
    deltas: torch.Tensor  # [T, B] δ_t = r_t + γ_t V(x_{t+1}) − V(x_t)


def discounted_products(decay: torch.Tensor) -> torch.Tensor:
    """M[s, t, b] = Π_{k=s}^{t-1} decay[k, b] for t ≥ s, else 0 (decay is [T, B])."""
    T = decay.shape[0]
    # A[s, t] = decay[t-1] above the diagonal, 1 on and below it; cumprod along t gives the
    # products, then the strictly-lower part is masked out.
    shifted = torch.cat([torch.ones_like(decay[:1]), decay[:-1]], dim=0)  # [T, B]: decay[t-1]
    upper = torch.ones(T, T, dtype=torch.bool, device=decay.device).triu(1)
    a = torch.where(upper.unsqueeze(-1), shifted.unsqueeze(0).expand(T, T, -1), 1.0)
    products = torch.cumprod(a, dim=1)
    lower = torch.ones(T, T, dtype=torch.bool, device=decay.device).tril(-1)
    return products.masked_fill(lower.unsqueeze(-1), 0.0)


@torch.no_grad()
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
    """V-trace with the intermediate terms the learner also needs (priorities use ρδ).
    `lambda_` scales the traces, c_t = λ·min(c̄, π/μ) (as rlax's and Sample Factory's V-trace):
    λ < 1 trades the targets' variance for bias, like GAE's λ."""
    ratios = torch.exp(target_logp - behaviour_logp)
    rhos = ratios.clamp(max=rho_bar)
    cs = lambda_ * ratios.clamp(max=c_bar)
    next_values = torch.cat([values[1:], bootstrap_value.unsqueeze(0)], dim=0)
    deltas = rewards + discounts * next_values - values
    corrections = torch.einsum("stb,tb->sb", discounted_products(discounts * cs), rhos * deltas)
    vs = values + corrections
    next_vs = torch.cat([vs[1:], bootstrap_value.unsqueeze(0)], dim=0)
    pg_advantages = ratios.clamp(max=rho_pg_bar) * (rewards + discounts * next_vs - values)
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
