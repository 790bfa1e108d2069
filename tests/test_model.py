import numpy as np
import pytest
import torch
from torch.distributions import Independent, Normal, kl_divergence

from tpdeb.services.net.wire import check_params
from tpdeb.tpdeb_core import policy
from tpdeb.tpdeb_core.model import TORCH, ActorCritic, RunningMeanStd
from tpdeb.tpdeb_core.moments import batch_moments
from tpdeb.tpdeb_core.policy import NUMPY, NumpyPolicy, param_shapes

STDS = policy.POLICY_STDS


def normal(mean, log_std):
    return Independent(Normal(mean, log_std.exp()), 1)


@pytest.mark.parametrize("shared", [False, True], ids=["state-log-std", "global-log-std"])
def test_the_gaussians_functions_match_torch_distributions_on_both_backends(shared):
    """log-prob, sample, entropy and KL: one definition, numpy's and torch's backends."""
    g = torch.Generator().manual_seed(0)
    mean_p, mean_q = torch.randn(2, 32, 6, generator=g)
    log_std_p, log_std_q = torch.randn(2, 32, 6, generator=g) * 0.5
    if shared:  # a global log-std: one row [A] for all, broadcast by the functions
        log_std_q = log_std_q[0]
    action, noise = torch.randn(2, 32, 6, generator=g) * 3
    p, q = normal(mean_p, log_std_p), normal(mean_q, log_std_q.expand_as(mean_q))
    for ops, cast in ((TORCH, lambda x: x), (NUMPY, lambda x: x.numpy().copy())):
        def close(mine, theirs):
            np.testing.assert_allclose(np.asarray(mine), theirs.numpy(), rtol=1e-5, atol=1e-5)
        close(policy.log_prob(cast(mean_q), cast(log_std_q), cast(action), ops),
              q.log_prob(action))
        close(np.broadcast_to(policy.entropy(cast(log_std_q), ops), (32,)), q.entropy())
        close(policy.kl(cast(mean_p), cast(log_std_p), cast(mean_q), cast(log_std_q), ops),
              kl_divergence(p, q))
        sampled, logp = policy.sample(cast(mean_q), cast(log_std_q), cast(noise), ops)
        close(sampled, mean_q + noise * log_std_q.exp())
        close(logp, q.log_prob(mean_q + noise * log_std_q.exp()))


def test_normaliser_merge_matches_numpy_on_concatenated_data():
    rng = np.random.default_rng(0)
    chunks = [rng.normal(loc=3.0, scale=s, size=(n, 5)) for s, n in [(1, 1), (2, 17), (0.1, 300),
                                                                     (5, 2)]]
    rms = RunningMeanStd(5)
    for chunk in chunks:
        rms.merge(*batch_moments(chunk))
    data = np.concatenate(chunks)
    np.testing.assert_allclose(rms.mean.numpy(), data.mean(0), rtol=1e-12)
    np.testing.assert_allclose(rms.var.numpy(), data.var(0), rtol=1e-10)
    assert rms.count.item() == len(data)
    # merging two normalisers (actor A and actor B) equals one over everything
    a, b = RunningMeanStd(5), RunningMeanStd(5)
    a.update(data[:100])
    b.update(data[100:])
    a.merge(*b.moments())
    np.testing.assert_allclose(a.var.numpy(), data.var(0), rtol=1e-10)


@pytest.mark.parametrize("policy_std", STDS)
def test_normaliser_state_travels_with_the_model(policy_std):
    model = ActorCritic(3, 2, policy_std=policy_std)
    model.obs_rms.update(np.random.default_rng(0).normal(5.0, 2.0, size=(100, 3)))
    copy = ActorCritic(3, 2, policy_std=policy_std)
    copy.load_state_dict(model.state_dict())
    obs = np.ones((4, 3))
    np.testing.assert_array_equal(copy.act_deterministic(obs), model.act_deterministic(obs))
    torch.testing.assert_close(copy.obs_rms.mean, model.obs_rms.mean)


@pytest.mark.parametrize("policy_std", STDS)
def test_act_logp_is_of_the_raw_sample(policy_std):
    model = ActorCritic(4, 3, policy_std=policy_std)
    out = model.act(np.random.default_rng(0).normal(size=(16, 4)), torch.Generator().manual_seed(1))
    expected = normal(torch.as_tensor(out["mean"]), torch.as_tensor(out["log_std"])).log_prob(
        torch.as_tensor(out["action"]))
    np.testing.assert_allclose(out["logp"], expected.numpy(), rtol=1e-5)


@pytest.mark.parametrize("policy_std", STDS)
def test_numpy_policy_matches_the_torch_model_to_float32_tolerance(policy_std):
    torch.manual_seed(0)
    model = ActorCritic(5, 3, (16, 16), init_log_std=-0.3, policy_std=policy_std)
    model.obs_rms.update(np.random.default_rng(1).normal(2.0, 3.0, (100, 5)))
    model.ret_rms.update(np.random.default_rng(4).normal(0.0, 7.0, 100))
    with torch.no_grad():  # a log-std that differs by dimension (and, with a head, by state)
        for p in model.policy.parameters():
            if p.shape[0] == 3:
                p.add_(0.3 * torch.randn_like(p))
    fast = NumpyPolicy(model.arrays(), model.obs_clip)
    obs = np.random.default_rng(2).normal(2.0, 3.0, (7, 5)).astype(np.float32)
    obs[0, 0] = 1e3  # beyond the observation clip
    out = fast.act(obs, np.random.default_rng(3))
    with torch.no_grad():
        mean, log_std = model.policy(model.norm_obs(torch.as_tensor(obs)))
        logp = normal(mean, log_std.expand_as(mean)).log_prob(torch.as_tensor(out["action"]))
    np.testing.assert_allclose(out["mean"], mean.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out["log_std"], log_std.detach().expand_as(mean).numpy(), rtol=1e-5,
                               atol=1e-6)
    assert (np.ptp(out["log_std"], axis=0) > 1e-3).all() == (policy_std == "state")
    np.testing.assert_allclose(out["logp"], logp.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out["value"], model.values_of(obs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast.values_of(obs), model.values_of(obs), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(fast.act_deterministic(obs), model.act_deterministic(obs),
                               rtol=1e-5, atol=1e-6)
    assert fast.reward_scale() == pytest.approx(model.reward_scale(), rel=1e-6)
    with torch.no_grad():  # a copy: it does not follow later changes of the model
        model.value_net[0].bias.add_(1.0)
    assert not np.allclose(fast.values_of(obs), model.values_of(obs))
    np.testing.assert_allclose(model.numpy_policy().values_of(obs), model.values_of(obs),
                               rtol=1e-5, atol=1e-6)


def test_numpy_policy_of_a_fresh_model_does_not_normalise():
    """Before any moments arrive (count 0) the normaliser passes observations through."""
    model = ActorCritic(4, 2)
    obs = np.random.default_rng(0).normal(size=(3, 4)).astype(np.float32)
    np.testing.assert_allclose(model.numpy_policy().values_of(obs), model.values_of(obs),
                               rtol=1e-5, atol=1e-6)
    assert model.numpy_policy().reward_scale() == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("policy_std", STDS)
@pytest.mark.parametrize("hidden", [(64, 64), (256, 256), (32, 16, 8)])
def test_param_shapes_are_the_torch_models_state(hidden, policy_std):
    """Actors check parameters against these shapes without building the torch model."""
    model = ActorCritic(11, 3, hidden, policy_std=policy_std)
    state = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    shapes = param_shapes(11, 3, hidden, policy_std)
    assert shapes == state
    check_params(model_params(model), shapes)  # dtypes fit as well
    assert policy.policy_std_of(shapes) == policy_std
    assert policy.dims_of(model.arrays()) == (11, 3, hidden)


def test_the_state_log_std_starts_at_its_initial_value_and_stays_bounded():
    model = ActorCritic(4, 2, init_log_std=-0.5, policy_std="state")
    obs = torch.randn(64, 4)
    _, log_std = model.policy(obs)
    np.testing.assert_allclose(log_std.detach().numpy(), -0.5, atol=0.05)
    with torch.no_grad():
        model.policy.log_std_head.bias.fill_(50.0)
    assert model.policy(obs)[1].max().item() == policy.LOG_STD_MAX
    with pytest.raises(ValueError, match="policy_std='tanh'"):
        ActorCritic(4, 2, policy_std="tanh")


def model_params(model):
    from tpdeb.protocol import Params

    return Params(version=0, arrays=model.arrays())
