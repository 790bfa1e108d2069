"""tpdeb_core.adam against torch.optim.Adam: the same steps, and state dicts that load across."""

import pytest
import torch

from tpdeb.tpdeb_core.adam import Adam, _fused_kernel_works


def params(seed=0):
    gen = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(5, 3, generator=gen)),
            torch.nn.Parameter(torch.randn(3, generator=gen))]


def run(optimizer, ps, steps, seed=1, lr_change_at=None):
    gen = torch.Generator().manual_seed(seed)
    for t in range(steps):
        if t == lr_change_at:
            optimizer.param_groups[0]["lr"] = 3e-3
        for p in ps:
            p.grad = torch.randn(p.shape, generator=gen)
        optimizer.step()


FUSED = _fused_kernel_works()


@pytest.mark.parametrize("fused", [
    pytest.param(True, marks=pytest.mark.skipif(not FUSED, reason="this torch has no fused CPU "
                                                "Adam kernel; the foreach path is tested")),
    False])
def test_the_same_updates_as_torch_adam_also_after_a_learning_rate_change(fused, monkeypatch):
    monkeypatch.setattr(Adam, "fused", fused)  # each of the two kernels
    mine, reference = params(), params()
    run(Adam(mine, lr=1e-2, eps=1e-5), mine, 30, lr_change_at=10)
    run(torch.optim.Adam(reference, lr=1e-2, eps=1e-5), reference, 30, lr_change_at=10)
    for a, b in zip(mine, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_state_dicts_load_either_way_and_continue_identically():
    ps_torch, ps_mine = params(), params()
    reference = torch.optim.Adam(ps_torch, lr=1e-2, eps=1e-5)
    run(reference, ps_torch, 7)
    mine = Adam(ps_mine, lr=1.0)
    with torch.no_grad():
        for a, b in zip(ps_mine, ps_torch, strict=True):
            a.copy_(b)
    mine.load_state_dict(reference.state_dict())
    assert mine.steps == 7 and mine.param_groups[0]["lr"] == 1e-2
    run(reference, ps_torch, 5, seed=2)
    run(mine, ps_mine, 5, seed=2)
    for a, b in zip(ps_mine, ps_torch, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    back = torch.optim.Adam(params())
    back.load_state_dict(mine.state_dict())
    assert back.state_dict()["state"][0]["step"] == 12


def test_state_of_another_model_is_refused():
    saved = Adam(params()[:1]).state_dict()
    with pytest.raises(ValueError, match="parameters"):
        Adam(params()).load_state_dict(saved)
    with pytest.raises(ValueError, match="no parameters"):
        Adam([])
