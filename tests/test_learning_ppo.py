"""PPO pieces against values computed by hand."""

import numpy as np
import pytest
import torch
from hammer.learning.ppo import (
    PPOUpdater,
    clipped_surrogate,
    gae,
    minibatch_indices,
    next_values,
    normalize_advantages,
    value_loss,
)

GAMMA, LAM = 0.9, 0.8


def _one_agent(x):
    return np.array(x, dtype=np.float32)[:, None]  # (T, 1)


def test_gae_truncation_bootstraps_from_final_obs_value():
    # t=1 ends by the time limit (copy reset); V(final_obs_1) = 1.0; after the rollout V = 0.2.
    r, v = _one_agent([1, 2, 3]), _one_agent([0.5, 0.4, 0.3])
    reset = _one_agent([0, 1, 0]).astype(bool)
    nv = next_values(v, np.array([0.2], np.float32), _one_agent([0, 1.0, 0]), reset)
    np.testing.assert_allclose(nv[:, 0], [0.4, 1.0, 0.2])
    adv, ret = gae(r, v, nv, terminated=np.zeros_like(reset), dones=reset, gamma=GAMMA, lam=LAM)
    # A2 = 3 + .9*.2 - .3 = 2.88 ; A1 = 2 + .9*1 - .4 = 2.5 (episode ends: no carry)
    # A0 = (1 + .9*.4 - .5) + .9*.8*2.5 = 0.86 + 1.8 = 2.66
    np.testing.assert_allclose(adv[:, 0], [2.66, 2.5, 2.88], rtol=1e-6)
    np.testing.assert_allclose(ret[:, 0], [3.16, 2.9, 3.18], rtol=1e-6)


def test_gae_termination_does_not_bootstrap():
    r, v = _one_agent([1, 2, 3]), _one_agent([0.5, 0.4, 0.3])
    term = _one_agent([0, 1, 0]).astype(bool)
    nv = next_values(v, np.array([0.2], np.float32), _one_agent([0, 7.0, 0]), term)
    adv, _ = gae(r, v, nv, terminated=term, dones=term, gamma=GAMMA, lam=LAM)
    # A1 = 2 - 0.4 = 1.6 (the 7.0 must be ignored); A0 = 0.86 + 0.72*1.6 = 2.012
    np.testing.assert_allclose(adv[:, 0], [2.012, 1.6, 2.88], rtol=1e-6)


def test_gae_masks_absent_agents():
    # Two agents; agent 1 terminates at t=0 and is absent afterwards (its later rewards/values are junk).
    r = np.array([[1.0, 1.0], [1.0, 50.0], [1.0, 50.0]], np.float32)
    v = np.array([[0.0, 0.5], [0.0, 9.0], [0.0, 9.0]], np.float32)
    term = np.array([[0, 1], [0, 0], [0, 0]], bool)
    mask = np.array([[1, 1], [1, 0], [1, 0]], bool)
    nv = next_values(v, np.zeros(2, np.float32), np.zeros_like(v), np.zeros_like(term))
    adv, ret = gae(r, v, nv, term, term, GAMMA, LAM, mask)
    np.testing.assert_allclose(adv[:, 1], [0.5, 0.0, 0.0])  # 1 - 0.5, nothing leaks from absent steps
    np.testing.assert_allclose(ret[1:, 1], [0.0, 0.0])
    # agent 0 is a plain 3-step chain with zero values: A2 = 1, A1 = 1 + .72, A0 = 1 + .72*1.72
    np.testing.assert_allclose(adv[:, 0], [1 + 0.72 * 1.72, 1.72, 1.0], rtol=1e-6)


def test_clipped_surrogate_tiny_example():
    new = torch.log(torch.tensor([1.5, 0.5]))
    old = torch.zeros(2)
    adv = torch.tensor([1.0, -1.0])
    # r=1.5, A=1: min(1.5, 1.2) = 1.2 ; r=0.5, A=-1: min(-0.5, -0.8) = -0.8 ; loss = -mean = -(1.2-0.8)/2
    loss, _, clipfrac = clipped_surrogate(new, old, adv, 0.2, torch.ones(2))
    assert loss.item() == pytest.approx(-0.2)
    assert clipfrac.item() == pytest.approx(1.0)
    loss_masked, _, _ = clipped_surrogate(new, old, adv, 0.2, torch.tensor([1.0, 0.0]))
    assert loss_masked.item() == pytest.approx(-1.2)
    # inside the clip range the loss is just -r*A
    inside, _, _ = clipped_surrogate(torch.log(torch.tensor([1.1])), torch.zeros(1), torch.tensor([2.0]), 0.2,
                                     torch.ones(1))
    assert inside.item() == pytest.approx(-2.2)


def test_value_loss_and_normalisation_respect_mask():
    m = torch.tensor([1.0, 1.0, 0.0])
    assert value_loss(torch.tensor([1.0, 3.0, 100.0]), torch.tensor([0.0, 1.0, 0.0]), m).item() == pytest.approx(1.25)
    a = normalize_advantages(torch.tensor([1.0, 3.0, 100.0]), m)
    np.testing.assert_allclose(a.numpy(), [-1.0, 1.0, 0.0], atol=1e-6)


def test_minibatches_partition_rows():
    parts = minibatch_indices(10, 3, np.random.default_rng(0))
    assert sorted(np.concatenate(parts).tolist()) == list(range(10))
    assert [len(p) for p in parts] == [4, 3, 3]


def test_updater_equals_torch_fused_adam_with_clip():
    """PPOUpdater's clip and direct fused-Adam call are bit-identical to clip_grad_norm_ +
    Adam(fused=True).step()."""

    def net():
        torch.manual_seed(0)
        return torch.nn.Sequential(torch.nn.Linear(5, 7), torch.nn.Tanh(), torch.nn.Linear(7, 2))

    ours, ref = net(), net()
    upd = PPOUpdater(ours.parameters(), 1e-2, 0.5)
    opt = torch.optim.Adam(ref.parameters(), lr=1e-2, eps=1e-5, fused=True)
    x = torch.randn(64, 5)
    for i in range(5):
        for m in (ours, ref):
            m.zero_grad(set_to_none=True)
            (m(x) ** 2).sum().mul(1 + i).backward()
        norm = upd.clip_and_step()
        ref_norm = torch.nn.utils.clip_grad_norm_(ref.parameters(), 0.5)
        opt.step()
        assert float(norm) == float(ref_norm) > 0.5  # the clip was active
        assert all(torch.equal(p, q) for p, q in zip(ours.parameters(), ref.parameters(), strict=True))
    st = upd.optimizer.state_dict()["state"]
    assert float(st[0]["step"]) == 5 and torch.equal(st[0]["exp_avg"], opt.state_dict()["state"][0]["exp_avg"])
