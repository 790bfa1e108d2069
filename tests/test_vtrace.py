import numpy as np
import pytest
import torch

from tpdeb.tpdeb_core.vtrace import discounted_sums, vtrace, vtrace_terms


def reference_vtrace(b_logp, t_logp, rewards, values, bootstrap, discounts, rho_bar, c_bar,
                     rho_pg_bar):
    """The textbook reverse loop (Espeholt et al. 2018, eq. 1 and the recursion of §4.1)."""
    T, B = rewards.shape
    ratios = np.exp(t_logp - b_logp)
    rhos, cs = np.minimum(rho_bar, ratios), np.minimum(c_bar, ratios)
    vs = np.zeros((T, B))
    next_v, next_vs_minus_v = bootstrap.copy(), np.zeros(B)
    for t in reversed(range(T)):
        delta = rhos[t] * (rewards[t] + discounts[t] * next_v - values[t])
        vs_minus_v = delta + discounts[t] * cs[t] * next_vs_minus_v
        vs[t] = values[t] + vs_minus_v
        next_v, next_vs_minus_v = values[t], vs_minus_v
    next_vs = np.concatenate([vs[1:], bootstrap[None]], axis=0)
    adv = np.minimum(rho_pg_bar, ratios) * (rewards + discounts * next_vs - values)
    return vs, adv


def random_case(rng, T, B):
    b_logp = rng.normal(size=(T, B))
    t_logp = b_logp + rng.normal(scale=0.7, size=(T, B))
    rewards = rng.normal(size=(T, B))
    values = rng.normal(size=(T, B))
    bootstrap = rng.normal(size=B)
    terminated = rng.random((T, B)) < 0.1
    discounts = 0.99 * (~terminated)
    return b_logp, t_logp, rewards, values, bootstrap, discounts


def test_vtrace_matches_reference_loop_with_terminations():
    rng = np.random.default_rng(0)
    for T, B in [(1, 1), (5, 3), (64, 8), (17, 2)]:
        for rho_bar, c_bar, rho_pg_bar in [(1.0, 1.0, 1.0), (2.0, 0.9, 1.5), (1e9, 1e9, 1e9)]:
            case = random_case(rng, T, B)
            expected_vs, expected_adv = reference_vtrace(*case, rho_bar, c_bar, rho_pg_bar)
            vs, adv = vtrace(*[torch.as_tensor(x, dtype=torch.float64) for x in case],
                             rho_bar=rho_bar, c_bar=c_bar, rho_pg_bar=rho_pg_bar)
            np.testing.assert_allclose(vs.numpy(), expected_vs, rtol=1e-9, atol=1e-9)
            np.testing.assert_allclose(adv.numpy(), expected_adv, rtol=1e-9, atol=1e-9)


def test_on_policy_without_clipping_gives_n_step_returns():
    # With π = μ and no termination, v_s is the discounted return bootstrapped at T.
    T, B, gamma = 6, 2, 0.9
    rng = np.random.default_rng(1)
    rewards, values = rng.normal(size=(T, B)), rng.normal(size=(T, B))
    bootstrap = rng.normal(size=B)
    logp = rng.normal(size=(T, B))
    vs, _ = vtrace(*[torch.as_tensor(x) for x in (logp, logp, rewards, values, bootstrap,
                                                  np.full((T, B), gamma))])
    ret = bootstrap.copy()
    for t in reversed(range(T)):
        ret = rewards[t] + gamma * ret
        np.testing.assert_allclose(vs[t].numpy(), ret, rtol=1e-12)


def test_termination_stops_the_trace():
    T, B = 4, 1
    rewards = torch.tensor([[1.0], [2.0], [3.0], [4.0]])
    values = torch.zeros(T, B)
    discounts = torch.tensor([[1.0], [0.0], [1.0], [1.0]])
    logp = torch.zeros(T, B)
    terms = vtrace_terms(logp, logp, rewards, values, torch.tensor([10.0]), discounts)
    # steps 0-1 form an episode that terminates after step 1; steps 2-3 bootstrap on 10
    np.testing.assert_allclose(terms.vs[:, 0].numpy(), [3.0, 2.0, 17.0, 14.0])
    np.testing.assert_allclose(terms.deltas[:, 0].numpy(), [1.0, 2.0, 3.0, 14.0])


@pytest.mark.parametrize("steps", [1, 2, 5, 64, 65, 100])
def test_the_doubling_scan_equals_the_backward_loop(steps):
    rng = np.random.default_rng(steps)
    x = rng.normal(size=(steps, 3)).astype(np.float32)
    decay = (rng.uniform(0, 1, size=(steps, 3)) * (rng.uniform(size=(steps, 3)) > 0.1)
             ).astype(np.float32)  # with zeros, as at terminations
    expected, acc = np.zeros_like(x), np.zeros(3, np.float32)
    for t in range(steps - 1, -1, -1):
        acc = x[t] + decay[t] * acc
        expected[t] = acc
    np.testing.assert_allclose(discounted_sums(torch.from_numpy(x), torch.from_numpy(decay)),
                               expected, rtol=1e-5, atol=1e-6)
