"""What differs between TPDEB, IMPACT and PPO+PER, in the loss and in the buffer, each shown on
the same data through the same code path (`--algo`)."""

import copy

import numpy as np
import pytest
import torch
from torch.distributions import Independent, Normal, kl_divergence

from tests.test_learner import fragments_and_model
from tpdeb.services.config import resolve
from tpdeb.services.config.train import TrainConfig
from tpdeb.tpdeb_core.fragments import stack_fragments
from tpdeb.tpdeb_core.learner import Learner


def config(algo: str, **flags) -> TrainConfig:
    argv = ["--algo", algo, "--env-id", "InvertedPendulum-v5"]
    for key, value in flags.items():
        argv += [f"--{key.replace('_', '-')}", str(value)]
    return resolve(TrainConfig, argv, "test", "test")


def stale_batch(seed=0):
    """Fragments collected by a policy that the learner has since moved away from, so that
    μ ≠ π_θ and the KL term, the target policy and the clip all matter."""
    fragments, model = fragments_and_model(seed=seed)
    with torch.no_grad():
        model.policy.log_std.add_(0.3)
        for p in model.policy.mean.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return fragments, model


def one_step(algo: str, **flags):
    fragments, model = stale_batch()
    learner = Learner(model, config(algo, **flags).loss_config())
    with torch.no_grad():  # a target policy between μ and π_θ
        for t, p in zip(learner.target_policy.parameters(), model.policy.parameters(),
                        strict=True):
            t.mul_(0.5)
            t.add_(0.5 * p)
    target_before = copy.deepcopy(learner.target_policy.state_dict())
    n = len(fragments)
    result = learner.step(stack_fragments(fragments), np.arange(n), np.ones(n), np.zeros(n, bool))
    return learner, target_before, result


def test_impact_has_no_kl_term_tpdeb_does():
    tpdeb_cfg, impact_cfg = config("tpdeb", kl_coef=0.5), config("impact")
    assert tpdeb_cfg.loss_config().kl_coef == 0.5 and impact_cfg.loss_config().kl_coef == 0.0
    fragments, model = stale_batch()
    grads = {}
    for name, cfg in (("tpdeb", tpdeb_cfg), ("impact", impact_cfg)):
        learner = Learner(copy.deepcopy(model), cfg.loss_config())
        learner.config.max_grad_norm = 1e9  # compare raw gradients
        learner.step(stack_fragments(fragments), np.arange(6), np.ones(6), np.zeros(6, bool))
        grads[name] = learner.model.policy.log_std.grad.clone()
    # The difference is exactly λ_kl ∂KL(μ‖π_θ)/∂θ at the same parameters.
    probe = copy.deepcopy(model)
    mean_b = torch.tensor(np.stack([f.behaviour_mean for f in fragments], 1))
    log_std_b = torch.tensor(np.stack([f.behaviour_log_std for f in fragments], 1))
    obs = probe.norm_obs(torch.tensor(np.stack([f.obs[:-1] for f in fragments], 1)))
    mean, log_std = probe.policy(obs)
    kl = kl_divergence(Independent(Normal(mean_b, log_std_b.exp()), 1),
                       Independent(Normal(mean, log_std.exp()), 1))
    (0.5 * kl.mean()).backward()
    torch.testing.assert_close(grads["tpdeb"] - grads["impact"], probe.policy.log_std.grad,
                               rtol=1e-4, atol=1e-6)


def test_tpdeb_and_impact_clip_around_the_target_ppo_per_around_the_behaviour_policy():
    _, _, tpdeb = one_step("tpdeb")
    _, _, impact = one_step("impact")
    _, _, ppo = one_step("ppo-per")
    # Same surrogate for TPDEB and IMPACT (the KL term is separate); PPO's ratio is π_θ/μ.
    assert tpdeb.metrics["losses/policy_loss"] == pytest.approx(
        impact.metrics["losses/policy_loss"], rel=1e-6)
    assert ppo.metrics["losses/policy_loss"] != pytest.approx(
        impact.metrics["losses/policy_loss"], rel=1e-3)
    assert ppo.metrics["losses/target_is_clipfrac"] == 0.0  # no target: nothing to clip


def test_ppo_per_has_no_target_policy_to_update():
    for algo, moves in (("tpdeb", True), ("impact", True), ("ppo-per", False)):
        learner, before, _ = one_step(algo)
        after = learner.target_policy.state_dict()
        changed = any(not torch.equal(before[k], after[k]) for k in before)
        assert changed == moves, algo


def test_impact_buffer_is_one_uniform_fifo():
    replay = config("impact", uniform_capacity_steps=256, fragment_len=64).make_replay()
    for key in range(6):
        replay.insert(key, float(10 * key), 64)  # priorities play no part
    assert replay._prioritized_keys() == set() and replay._uniform_keys() == [2, 3, 4, 5]
    batch = replay.sample(32)
    assert set(batch.items) <= {2, 3, 4, 5} and not batch.from_prioritized.any()
    assert np.all(batch.weights == 1.0) and batch.step_weights is None


def test_tpdeb_buffer_keeps_the_highest_priority_fragments_apart():
    replay = config("tpdeb", prioritized_capacity=2, uniform_capacity_steps=256,
                    fragment_len=64, zeta=0.5, learning_starts_fragments=2).make_replay()
    for key, priority in enumerate([1.0, 9.0, 5.0, 0.5, 7.0]):
        replay.insert(key, priority, 64)
    assert replay._prioritized_keys() == {1, 4}  # the two highest
    batch = replay.sample(8)
    assert batch.from_prioritized.sum() == 4 and set(batch.items[:4]) <= {1, 4}


def test_ppo_per_buffer_holds_three_batches_and_samples_single_steps_by_priority():
    cfg = config("ppo-per", batch_fragments=2, fragment_len=4, learning_starts_fragments=2)
    replay = cfg.make_replay()
    rng = np.random.default_rng(0)
    for key in range(8):
        replay.insert(key, rng.uniform(0.1, 2.0, 4), 4)
    assert replay._prioritized_keys() == {2, 3, 4, 5, 6, 7}  # FIFO of 3 × 2 fragments
    batch = replay.sample(cfg.batch_fragments, beta=0.0)
    assert batch.from_prioritized.all() and batch.steps_drawn == 2 * 4
    assert batch.step_weights.sum() == 8  # β = 0: B·T single transitions, counted per step
    assert len(set(batch.items)) == len(batch.items)  # one row per distinct fragment


def test_ppo_per_replaces_a_third_of_its_buffer_per_update_whatever_the_preset():
    # Walker2d's preset asks for more sampled steps per inserted step; PPO+PER is made of 1.
    assert config("tpdeb", env_id="Walker2d-v5", preset="auto").replay_ratio > 1.0
    cfg = config("ppo-per", env_id="Walker2d-v5", preset="auto")
    assert cfg.replay_ratio == 1.0
    limiter = cfg.rate_limiter()
    inserted = updates = 0
    for _ in range(3000):  # a greedy actor and a greedy learner, in steady state
        if limiter.can_sample(cfg.batch_steps):
            limiter.on_sample(cfg.batch_steps)
            updates += 1
        elif limiter.can_insert(cfg.fragment_len):
            limiter.on_insert(cfg.fragment_len)
            inserted += 1
    buffer_fragments = cfg.prioritized_capacity
    assert inserted / updates / buffer_fragments == pytest.approx(1 / 3, rel=0.05)


def test_step_weights_weigh_single_transitions_in_the_loss():
    fragments, model = stale_batch()
    n = len(fragments)
    weights = np.zeros((n, 8), np.float32)
    weights[2, 3] = 4.0  # four draws of one transition: the whole batch
    learner = Learner(copy.deepcopy(model), config("ppo-per").loss_config())
    result = learner.step(stack_fragments(fragments), np.arange(n), np.ones(n), np.ones(n, bool),
                          weights)
    only = [fragments[2]]
    learner2 = Learner(copy.deepcopy(model), config("ppo-per").loss_config())
    mask = np.zeros((1, 8), np.float32)
    mask[0, 3] = 1.0
    second = learner2.step(stack_fragments(only), np.arange(1), np.ones(1), np.ones(1, bool), mask)
    # The losses of the one transition do not depend on the rest of the batch: the KL term too.
    for tag in ("losses/value_loss", "losses/kl_behaviour"):
        assert result.metrics[tag] == pytest.approx(second.metrics[tag], rel=1e-5)


def test_loss_terms_keep_their_proportions_whatever_the_scale_of_the_weights():
    """Step-level PER's weights (p / p_min)^(−β) can all be ≪ 1: the update must be the one
    their relative sizes ask for, not a vanishing surrogate beside a full entropy bonus."""
    fragments, model = stale_batch()
    n = len(fragments)
    rng = np.random.default_rng(3)
    weights = rng.uniform(0.5, 2.0, (n, 8)).astype(np.float32)
    cfg = config("ppo-per", ent_coef=0.01).loss_config()
    steps = []
    for scale in (1.0, 1e-4):
        learner = Learner(copy.deepcopy(model), cfg)
        result = learner.step(stack_fragments(fragments), np.arange(n), np.ones(n),
                              np.ones(n, bool), weights * scale)
        steps.append((result.metrics, torch.nn.utils.parameters_to_vector(
            learner.model.parameters()).detach()))
    (big, after_big), (small, after_small) = steps
    for tag in ("losses/policy_loss", "losses/value_loss", "losses/kl_behaviour"):
        assert big[tag] == pytest.approx(small[tag], rel=1e-4)
    assert torch.allclose(after_big, after_small, atol=1e-6)
