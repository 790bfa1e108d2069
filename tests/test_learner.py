import copy
import dataclasses
import math

import numpy as np
import pytest
import torch
from torch.distributions import Independent, Normal, kl_divergence

from tests.fakes import ScriptedVectorEnv
from tpdeb.tpdeb_core.fragments import Collector, stack_fragments
from tpdeb.tpdeb_core.learner import Learner, LossConfig
from tpdeb.tpdeb_core.model import ActorCritic
from tpdeb.tpdeb_core.vtrace import vtrace_terms


def impact_surrogate(logp, behaviour_logp, target_logp, advantages, clip_coef, rho_target_bar):
    """The IMPACT surrogate written plainly in torch, an independent reference: per step
    −min(r·A, clip(r, 1−ε, 1+ε)·A) with r = is · π_θ/μ, is = min(μ/π_θ̄, ρ̄_target) (the clip
    centred on the target policy), and log r."""
    log_ratio = logp - behaviour_logp
    if target_logp is not None:
        log_is = torch.clamp(behaviour_logp - target_logp, max=math.log(rho_target_bar))
        log_ratio = log_ratio + log_is.detach()
    ratio = torch.exp(log_ratio)
    clipped = ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef)
    return -torch.min(ratio * advantages, clipped * advantages), log_ratio


def fragments_and_model(n=6, seed=0, policy_std="global"):
    torch.manual_seed(seed)
    model = ActorCritic(3, 1, policy_std=policy_std)
    envs = ScriptedVectorEnv([5, 7, 9], [True, False, False])
    collector = Collector(envs, model.numpy_policy(), 8, 0.99, np.array([-1.0], np.float32),
                          np.array([1.0], np.float32), seed=seed)
    fragments = []
    while len(fragments) < n:
        fragments += collector.step()
    return fragments[:n], model


def test_impact_surrogate_matches_hand_computation():
    logp = torch.tensor([0.0, 0.2, -0.3, 0.1])
    behaviour = torch.tensor([0.0, 0.0, 0.0, 0.5])
    target = torch.tensor([0.0, 0.1, 0.0, -1.0])  # last: μ/π̄ = e^1.5 > 2, so is is clipped
    adv = torch.tensor([1.0, 1.0, -1.0, 1.0])
    loss, log_ratio = impact_surrogate(logp, behaviour, target, adv, 0.2, 2.0)
    is_ = np.minimum(np.exp((behaviour - target).numpy()), 2.0)
    r = is_ * np.exp((logp - behaviour).numpy())
    expected = -np.minimum(r * adv.numpy(), np.clip(r, 0.8, 1.2) * adv.numpy())
    np.testing.assert_allclose(loss.numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(log_ratio.exp().numpy(), r, rtol=1e-6)
    # with π̄ = μ the surrogate is PPO's clipped objective on π_θ/μ
    ppo, _ = impact_surrogate(logp, behaviour, behaviour, adv, 0.2, 2.0)
    ratio = np.exp((logp - behaviour).numpy())
    np.testing.assert_allclose(
        ppo.numpy(), -np.minimum(ratio * adv.numpy(), np.clip(ratio, 0.8, 1.2) * adv.numpy()),
        rtol=1e-6)


def test_gradient_flows_only_through_the_learner_policy():
    logp = torch.tensor([0.1, -0.1], requires_grad=True)
    target = torch.tensor([0.0, 0.0], requires_grad=True)
    loss, _ = impact_surrogate(logp, torch.zeros(2), target, torch.ones(2), 0.2, 2.0)
    loss.sum().backward()
    assert target.grad is None and logp.grad is not None


def test_first_update_is_on_policy_and_target_moves_by_tau():
    fragments, model = fragments_and_model()
    cfg = LossConfig(tau=0.05)
    learner = Learner(model, cfg)
    before = [p.detach().clone() for p in learner.target_policy.parameters()]
    keys = np.arange(len(fragments))
    prioritized = np.array([True, False] * 3)
    result = learner.step(stack_fragments(fragments), keys, np.ones(len(fragments)), prioritized)
    m = result.metrics
    # the actor acted with exactly this model: μ = π_θ = π_θ̄, nothing clipped, no KL yet
    assert m["losses/kl_behaviour"] == pytest.approx(0.0, abs=1e-6)
    assert m["losses/clipfrac"] == 0.0 and m["losses/approx_kl"] == pytest.approx(0.0, abs=1e-6)
    assert all(math.isfinite(v) for v in m.values())
    assert learner.updates == 1
    for old, target, new in zip(before, learner.target_policy.parameters(),
                                model.policy.parameters(), strict=True):
        torch.testing.assert_close(target, old + 0.05 * (new.detach() - old))
    # new priorities only for the prioritized samples, positive
    np.testing.assert_array_equal(result.priority_keys, keys[prioritized])
    assert len(result.priorities) == 3 and all(p > 0 for p in result.priorities)


def test_step_mode_priorities_are_per_step_and_sum_to_trajectory_priorities():
    fragments, model = fragments_and_model()
    state = {k: v.clone() for k, v in model.state_dict().items()}
    results = {}
    for mode in ("trajectory", "step"):
        model.load_state_dict(state)
        learner = Learner(model, LossConfig(priority_mode=mode))
        results[mode] = learner.step(stack_fragments(fragments), np.arange(6), np.ones(6),
                                     np.ones(6, bool), step_weights=np.ones((6, 8), np.float32))
    for total, per_step in zip(results["trajectory"].priorities, results["step"].priorities,
                               strict=True):
        assert per_step.shape == (8,)
        assert total == pytest.approx(per_step.sum(), rel=1e-5)


def test_adaptive_kl_coefficient_moves_toward_target():
    fragments, model = fragments_and_model()
    learner = Learner(model, LossConfig(kl_coef=0.1, kl_target=1.0))
    learner.step(stack_fragments(fragments), np.arange(6), np.ones(6), np.zeros(6, bool))
    assert learner.kl_coef == pytest.approx(0.05)  # KL ≈ 0 < target/1.5: halved


def test_a_log_std_ceiling_holds_the_global_log_std_after_every_step():
    fragments, model = fragments_and_model()
    learner = Learner(model, LossConfig(ent_coef=10.0))  # the loss pushes the log-std up
    batch = (stack_fragments(fragments), np.arange(6), np.ones(6), np.zeros(6, bool))
    learner.step(*batch)
    assert float(model.policy.log_std.detach().max()) > 0.0  # free, it rises above its start
    learner.log_std_ceiling = -0.5
    learner.step(*batch)
    assert float(model.policy.log_std.detach().max()) == pytest.approx(-0.5)
    for _ in range(3):
        learner.step(*batch)
        assert float(model.policy.log_std.detach().max()) <= -0.5


def test_under_a_ceiling_the_kl_term_reads_the_behaviour_std_under_it_too():
    fragments, model = fragments_and_model()  # behaviour log-std 0
    batch = stack_fragments(fragments)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    cfg = LossConfig(kl_coef=1.0)
    with torch.no_grad():  # π moved away from μ: narrower, and its means shifted
        model.policy.log_std.fill_(-1.0)
        model.policy.mean[-1].bias.add_(0.3)
    ceiled = Learner(model, cfg)
    ceiled.log_std_ceiling = -1.0
    got = ceiled.step(batch, np.arange(6), np.ones(6), np.zeros(6, bool)).metrics
    after = {k: v.clone() for k, v in model.state_dict().items()}
    model.load_state_dict(state)
    with torch.no_grad():  # π moved away from μ: narrower, and its means shifted
        model.policy.log_std.fill_(-1.0)
        model.policy.mean[-1].bias.add_(0.3)
    narrow = dataclasses.replace(batch, behaviour_log_std=np.minimum(batch.behaviour_log_std,
                                                                      np.float32(-1.0)))
    plain = Learner(model, cfg).step(narrow, np.arange(6), np.ones(6), np.zeros(6, bool)).metrics
    assert got["losses/kl_behaviour"] == pytest.approx(plain["losses/kl_behaviour"], rel=1e-6)
    assert got["losses/kl_behaviour"] > 0  # the means differ, only the stds agree
    for name in after:
        if name != "policy.log_std":
            torch.testing.assert_close(after[name], model.state_dict()[name])


def test_learner_state_round_trip():
    fragments, model = fragments_and_model()
    learner = Learner(model, LossConfig())
    learner.step(stack_fragments(fragments), np.arange(6), np.ones(6), np.zeros(6, bool))
    other = Learner(ActorCritic(3, 1), LossConfig())
    other.load_state_dict(learner.state_dict())
    assert other.updates == 1
    for a, b in zip(other.target_policy.parameters(), learner.target_policy.parameters(),
                    strict=True):
        torch.testing.assert_close(a, b)


def reference_update(model, target_policy, batch, weights, cfg: LossConfig, kl_coef: float):
    """The loss written plainly (torch.distributions, the tensors' own ops, torch.optim.Adam):
    what Learner.step's reduced terms must equal. Returns the loss terms after one Adam step."""
    obs = model.norm_obs(torch.tensor(batch.obs))
    actions = torch.tensor(batch.actions)
    mean, log_std = model.policy(obs[:-1])
    dist = Independent(Normal(mean, log_std.exp().expand_as(mean)), 1)
    logp = dist.log_prob(actions)
    values = model.value(obs)
    with torch.no_grad():
        t_mean, t_log_std = target_policy(obs[:-1])
        target_logp = Independent(Normal(t_mean, t_log_std.exp().expand_as(t_mean)),
                                  1).log_prob(actions)
        rewards = torch.tensor(batch.rewards) * model.reward_scale()
        discounts = cfg.gamma * torch.tensor(~(batch.terminated | batch.truncated)).float()
        for t, b, o in zip(batch.trunc_t, batch.trunc_b, batch.trunc_obs, strict=True):
            if not batch.terminated[t, b]:
                rewards[t, b] += cfg.gamma * model.value(model.norm_obs(torch.tensor(o)))
        behaviour_logp = torch.tensor(batch.behaviour_logp)
        vt = vtrace_terms(behaviour_logp, target_logp, rewards, values[:-1].detach(),
                          values[-1].detach(), discounts, lambda_=cfg.vtrace_lambda)
        adv = (vt.pg_advantages - vt.pg_advantages.mean()) / (vt.pg_advantages.std() + 1e-8)
    w = torch.tensor(weights, dtype=torch.float32).expand_as(rewards)
    w = w / w.sum()
    surrogate, _ = impact_surrogate(logp, behaviour_logp, target_logp, adv, cfg.clip_coef,
                                    cfg.rho_target_bar)
    behaviour = Independent(Normal(torch.tensor(batch.behaviour_mean),
                                   torch.tensor(batch.behaviour_log_std).exp()), 1)
    terms = {"pg": (surrogate * w).sum(), "value": 0.5 * ((values[:-1] - vt.vs) ** 2 * w).sum(),
             "entropy": (dist.entropy() * w).sum(),
             "kl": (kl_divergence(behaviour, dist) * w).sum()}
    loss = (terms["pg"] + cfg.vf_coef * terms["value"] - cfg.ent_coef * terms["entropy"]
            + kl_coef * terms["kl"])
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate, eps=cfg.adam_eps)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
    optimizer.step()
    return {k: v.item() for k, v in terms.items()}


@pytest.mark.parametrize("policy_std", ["global", "state"])
def test_step_equals_the_plainly_written_loss_off_policy_with_truncations_and_weights(
        policy_std):
    fragments, model = fragments_and_model(n=6, seed=3, policy_std=policy_std)
    batch = stack_fragments(fragments)
    assert len(batch.trunc_t) and batch.terminated.any()  # both episode ends are in the batch
    model.obs_rms.update(np.random.default_rng(0).normal(size=(50, 3)))
    model.ret_rms.update(np.random.default_rng(1).normal(0, 3, size=50))
    cfg = LossConfig(kl_coef=0.3, ent_coef=0.01, vtrace_lambda=0.95, learning_rate=1e-3)
    learner = Learner(model, cfg)
    with torch.no_grad():  # π_θ, π_θ̄ and μ all differ
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
        for p in learner.target_policy.parameters():
            p.add_(0.05 * torch.randn_like(p))
    reference_model = copy.deepcopy(model)
    target = copy.deepcopy(learner.target_policy)
    weights = np.array([0.2, 1.0, 0.5, 1.0, 0.7, 1.0], np.float32)
    expected = reference_update(reference_model, target, batch, weights, cfg, cfg.kl_coef)
    m = learner.step(batch, np.arange(6), weights, np.zeros(6, bool)).metrics
    assert m["losses/policy_loss"] == pytest.approx(expected["pg"], rel=1e-4, abs=1e-6)
    assert m["losses/value_loss"] == pytest.approx(expected["value"], rel=1e-4)
    assert m["losses/entropy"] == pytest.approx(expected["entropy"], rel=1e-5)
    assert m["losses/kl_behaviour"] == pytest.approx(expected["kl"], rel=1e-4)
    assert expected["kl"] > 1e-3 and m["losses/clipfrac"] > 0  # the terms were exercised
    for mine, theirs in zip(model.parameters(), reference_model.parameters(), strict=True):
        # the (clipped) gradients: Adam's first step alone would only compare their signs
        torch.testing.assert_close(mine.grad, theirs.grad, rtol=1e-3, atol=1e-6)
        torch.testing.assert_close(mine, theirs, rtol=1e-4, atol=1e-6)
