"""Networks: numpy forward equals torch; sampling streams; which graph the central agent learns through."""

import subprocess
import sys

import numpy as np
import torch
from hammer.envs.registry import make_vec_env
from hammer.learning.config import merge_config
from hammer.learning.networks import CentralAgent, LocalPolicy, gaussian_logp
from hammer.learning.numpy_policy import NumpyCentralAgent, NumpyLocalPolicy, gaussian_logp_of_draw, softmax
from hammer.learning.rundir import RunDir
from hammer.learning.sampling import ActingStreams, categorical_inverse_cdf
from hammer.learning.trainer import Trainer


def test_numpy_forward_matches_torch():
    torch.manual_seed(0)
    x = np.random.default_rng(0).normal(size=(7, 3, 22)).astype(np.float32)
    for discrete in (True, False):
        net = LocalPolicy(22, 5, discrete, [64, 64], [64, 32])
        npn = NumpyLocalPolicy(net.export_numpy())
        with torch.no_grad():
            np.testing.assert_allclose(npn.actor_out(x), net.actor_out(torch.from_numpy(x)).numpy(), atol=1e-5)
            np.testing.assert_allclose(npn.value(x), net.value(torch.from_numpy(x)).numpy(), atol=1e-5)
        assert npn.discrete == discrete
    central = CentralAgent(69, 3, 4, [64, 64], [64, 32])
    npc = NumpyCentralAgent(central.export_numpy())
    s = np.random.default_rng(1).normal(size=(5, 69)).astype(np.float32)
    with torch.no_grad():
        mean = central.message_mean(torch.from_numpy(s)).numpy()
        np.testing.assert_allclose(npc.message_mean(s), mean, atol=1e-5)
        np.testing.assert_allclose(npc.values(s), central.values(torch.from_numpy(s)).numpy(), atol=1e-5)
    assert mean.shape == (5, 3, 4) and np.abs(mean).max() <= 1.0
    # export -> load round trip gives the same network
    other = CentralAgent(69, 3, 4, [64, 64], [64, 32])
    other.load_state_dict({k: torch.from_numpy(v) for k, v in central.export_numpy().items()})
    with torch.no_grad():
        assert torch.equal(other.message_mean(torch.from_numpy(s)), central.message_mean(torch.from_numpy(s)))


def test_gaussian_logp_numpy_from_the_draw_equals_torch_from_the_sample():
    rng = np.random.default_rng(3)
    mean, z = rng.normal(size=(4, 3, 2)), rng.standard_normal((4, 3, 2))
    log_std = np.array([-0.5, 0.3], np.float32)
    x = mean + np.exp(log_std) * z
    ours = gaussian_logp_of_draw(z, log_std)
    ref = gaussian_logp(torch.from_numpy(x), torch.from_numpy(mean), torch.from_numpy(log_std)).numpy()
    assert ours.dtype == np.float32 and ours.shape == (4, 3)
    np.testing.assert_allclose(ours, ref, rtol=1e-5)


def test_edge_modules_do_not_import_torch():
    code = ("import sys, learning, learning.numpy_policy, learning.sampling; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_streams_are_reproducible_and_independent_per_agent():
    a, b = ActingStreams(5, 3), ActingStreams(5, 3)
    ua, ub = a.local_uniforms(8), b.local_uniforms(8)
    np.testing.assert_array_equal(ua, ub)
    assert ua.shape == (8, 3) and not np.allclose(ua[:, 0], ua[:, 1])
    # agent i's column is exactly default_rng([seed, LOCAL, i]).random(K): a lone process can redraw it
    np.testing.assert_array_equal(ua[:, 2], np.random.default_rng([5, 1, 2]).random(8))
    state = a.state()
    first = a.central_normals(4, 3, 2)
    a.set_state(state)
    np.testing.assert_array_equal(a.central_normals(4, 3, 2), first)
    assert not np.array_equal(ActingStreams(6, 3).local_uniforms(8), ua)


def test_inverse_cdf_sampling_follows_the_probabilities():
    logits = np.array([[0.0, 1.0, -1.0, 2.0, 0.5]], dtype=np.float32)
    p = softmax(logits)[0]
    u = np.random.default_rng(0).random(200_000)
    idx = categorical_inverse_cdf(np.broadcast_to(p, (len(u), 5)), u)
    freq = np.bincount(idx, minlength=5) / len(u)
    np.testing.assert_allclose(freq, p, atol=0.005)
    assert categorical_inverse_cdf(np.array([[0.5, 0.5]]), np.array([0.0]))[0] == 0
    assert categorical_inverse_cdf(np.array([[0.5, 0.5]]), np.array([0.9999999]))[0] == 1


def _trainer(tmp_path, mode, **over):
    sets = [f"central_mode={mode}", "num_envs=4", "rollout_steps=25", "episodes=1000"]
    sets += [f"{k}={v}" for k, v in over.items()]
    cfg = merge_config("cn3", overrides=sets)
    rd = RunDir.create(tmp_path / mode, cfg)
    env = make_vec_env("cn", 3, 4)
    tr = Trainer(cfg, rd, env=env, tensorboard=False)
    obs, _ = env.reset(0)
    prev = tr.team.zero_prev_actions(4)
    tr._t0 = 0.0
    obs, prev, _ = tr._collect(obs, prev)
    return tr, tr.learner.batch(obs, prev)[0]  # the fields; every masking op (the default) is right for any slice


def _grads(module):
    return [p.grad for p in module.parameters()]


def test_backprop_mode_trains_the_central_net_through_the_local_loss(tmp_path):
    tr, b = _trainer(tmp_path, "backprop")
    assert tr.team.central.critic is None
    local_loss, central_loss, _ = tr.learner.losses({k: v[:100] for k, v in b.items()})
    assert central_loss is None
    local_loss.backward()
    grads = _grads(tr.team.central)
    assert all(g is not None for g in grads) and sum(float(g.abs().sum()) for g in grads) > 0
    before = {k: v.clone() for k, v in tr.team.central.state_dict().items()}
    tr.learner.learn(*_last(tr), 0)
    after = tr.team.central.state_dict()
    assert all(not torch.equal(before[k], after[k]) for k in before)


def _last(tr):
    env = tr.env
    obs, _ = env.reset(1)
    return obs, tr.team.zero_prev_actions(4)


def test_rl_mode_keeps_the_two_graphs_apart(tmp_path):
    tr, b = _trainer(tmp_path, "rl")
    local_loss, central_loss, _ = tr.learner.losses({k: v[:100] for k, v in b.items()})
    local_loss.backward(retain_graph=True)
    assert all(g is None for g in _grads(tr.team.central))
    assert any(g is not None for g in _grads(tr.team.local))
    tr.team.local.zero_grad(set_to_none=True)
    central_loss.backward()
    assert all(g is None for g in _grads(tr.team.local))
    assert all(g is not None for g in _grads(tr.team.central))


def test_message_dropout_zeroes_messages(tmp_path):
    _tr, b = _trainer(tmp_path, "rl", msg_dropout=0.5)
    keep = b["keep"].numpy().astype(bool)
    assert 0.35 < keep.mean() < 0.65
    msg = b["msg"].numpy()
    assert np.all(msg[~keep] == 0) and np.all(np.abs(msg[keep]).sum(-1) > 0)


def test_fast_tanh_matches_tanh_and_its_gradient():
    from hammer.learning.networks import tanh

    x = torch.linspace(-12, 12, 64 * 400).reshape(400, 64).requires_grad_(True)  # above the fast-path size
    y = tanh(x)
    torch.testing.assert_close(y, torch.tanh(x), atol=3e-7, rtol=0)
    g = torch.randn_like(x)
    (gx,) = torch.autograd.grad(y, x, g)
    (ref,) = torch.autograd.grad(torch.tanh(x), x, g)
    torch.testing.assert_close(gx, ref, atol=1e-6, rtol=1e-5)
    with torch.inference_mode():
        torch.testing.assert_close(tanh(x.detach()), torch.tanh(x.detach()), atol=3e-7, rtol=0)
