"""The learner's loss settings (DESIGN §2, "Learner loss"), apart from the learner itself so that
processes that only read a run's configuration (router, link, launcher) need no torch."""

from __future__ import annotations

from dataclasses import dataclass

from tpdeb.tpdeb_core.replay import PRIORITY_MODES

CLIP_ANCHORS = ("target", "behaviour")


@dataclass
class PriorityConfig:
    """What a fragment's return and priority are: what the replay server, which ranks the
    fragments and tells the actors how to score them, shares with the loss."""

    SECTION = "loss"  # the table of these settings in a TOML configuration

    gamma: float = 0.99
    """discount factor"""
    priority_mode: str = "trajectory"
    """trajectory (Σ|δ| per fragment) | step (PER on single transitions) | none"""
    priority_kappa: float = 0.0
    """weight of the fragment's mean |scaled return| added to its priority"""

    def __post_init__(self):
        more = getattr(super(), "__post_init__", None)
        if more is not None:  # the other groups of a configuration composed with this one
            more()
        if self.priority_mode not in PRIORITY_MODES:
            raise ValueError(f"priority_mode={self.priority_mode!r}: use one of {PRIORITY_MODES}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma={self.gamma}: must be in (0, 1]")


@dataclass
class LossConfig(PriorityConfig):
    """What the loss computes and how the optimiser steps (DESIGN §2), each setting declared and
    documented once: configurations that train extend this class."""

    rho_bar: float = 1.0
    """V-trace ρ̄ (truncation of the importance weight in the value target)"""
    c_bar: float = 1.0
    """V-trace c̄ (trace cutting)"""
    rho_pg_bar: float = 1.0
    """V-trace ρ̄ for the policy-gradient advantage"""
    rho_target_bar: float = 2.0
    """IMPACT: clip of μ/π_target in the surrogate ratio"""
    clip_coef: float = 0.2
    """surrogate clipping ε"""
    kl_coef: float = 0.01
    """λ_kl: weight of KL(μ ‖ π_θ) (0 switches the KL term off)"""
    kl_target: float = 0.0
    """if > 0, adapt kl_coef toward this KL value instead of keeping it fixed"""
    vf_coef: float = 0.5
    """value loss coefficient"""
    ent_coef: float = 0.0
    """entropy bonus coefficient"""
    max_grad_norm: float = 0.5
    """gradient-norm clip"""
    tau: float = 0.05
    """soft target-policy update rate per learner update"""
    learning_rate: float = 1e-3
    """Adam learning rate"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    norm_adv: bool = True
    """normalise advantages per batch"""
    clip_anchor: str = "target"
    """target: the surrogate's ratio is taken to the target policy (IMPACT, TPDEB) | behaviour:
    PPO's ratio π_θ/μ with V-trace toward the current policy (no target policy)"""
    vtrace_lambda: float = 1.0
    """λ of the V-trace traces c_t = λ·min(c̄, π/μ), like GAE's λ (1: plain V-trace)"""

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau={self.tau}: the soft target rate must be in (0, 1]")
        if self.clip_anchor not in CLIP_ANCHORS:
            raise ValueError(f"clip_anchor={self.clip_anchor!r}: use one of {CLIP_ANCHORS}")
        if not 0.0 <= self.vtrace_lambda <= 1.0:
            raise ValueError(f"vtrace_lambda={self.vtrace_lambda}: must be in [0, 1]")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate={self.learning_rate}: must be > 0")

