"""`central_net=set`: the permutation-invariant central network (learning/networks.py SetCentralAgent).

Its numpy twin (the central server's forward) equals torch, it is permutation-equivariant, its size
does not grow with N², both central modes train it through the right graph, it learns on cn3, a
seed batch trains it like solo runs, and config errors name the field.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch
from hammer.envs.registry import make_vec_env
from hammer.learner.worker import weights_blob
from hammer.learning.config import ConfigError, merge_config
from hammer.learning.networks import SetCentralAgent, make_central
from hammer.learning.numpy_policy import NumpyCentralAgent, NumpySetCentralAgent, numpy_central
from hammer.learning.rundir import RunDir
from hammer.learning.trainer import Trainer, train
from safetensors.numpy import load as load_safetensors


def _net(n: int, obs_dim: int, act_dim: int, rl: bool) -> SetCentralAgent:
    """A set net with every weight perturbed (fresh biases are zero: a bias bug would hide)."""
    torch.manual_seed(n)
    net = SetCentralAgent(n, obs_dim, act_dim, 8, [64, 64], [64, 32] if rl else None)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn(p.shape))
    return net


def _state(n: int, obs_dim: int, act_dim: int, batch: int = 6) -> np.ndarray:
    rng = np.random.default_rng(n)
    obs = rng.normal(size=(batch, n * obs_dim))
    acts = np.eye(act_dim)[rng.integers(0, act_dim, (batch, n))].reshape(batch, -1) if act_dim else np.zeros((batch, 0))
    return np.concatenate([obs, acts], axis=1).astype(np.float32)


@pytest.mark.parametrize(("n", "act_dim", "rl"), [(3, 5, True), (10, 5, True), (5, 0, False)])
def test_numpy_twin_equals_torch_through_the_safetensors_blob(n, act_dim, rl):
    obs_dim = 6 * n
    net = _net(n, obs_dim, act_dim, rl)
    npn = numpy_central(load_safetensors(weights_blob(net.export_numpy())))
    assert isinstance(npn, NumpySetCentralAgent) and npn.kind == "set"
    assert (npn.n_agents, npn.obs_dim, npn.act_dim, npn.msg_dim) == (n, obs_dim, act_dim, 8)
    assert npn.state_dim == net.state_dim == n * (obs_dim + act_dim)
    s = _state(n, obs_dim, act_dim)
    with torch.no_grad():
        mean = net.message_mean(torch.from_numpy(s)).numpy()
    got = npn.message_mean(s)
    assert got.dtype == np.float32 and got.shape == mean.shape == (6, n, 8)
    np.testing.assert_allclose(got, mean, atol=2e-6, rtol=0)
    assert np.abs(mean).max() > 0.1 and not np.allclose(mean[:, 0], mean[:, 1])  # real, per-agent messages
    if rl:
        with torch.no_grad():
            v = net.values(torch.from_numpy(s)).numpy()
        assert v.shape == (6, n)
        np.testing.assert_allclose(npn.values(s), v, atol=2e-6, rtol=0)
    else:
        assert npn.critic is None
        with pytest.raises(AttributeError, match="no critic"):
            npn.values(s)


def test_permuting_the_agents_permutes_the_messages_and_values():
    n, d, a = 6, 36, 5
    net = _net(n, d, a, rl=True)
    npn = NumpySetCentralAgent(net.export_numpy())
    s = _state(n, d, a)
    perm = np.array([3, 0, 5, 1, 4, 2])
    obs, acts = s[:, : n * d].reshape(6, n, d), s[:, n * d:].reshape(6, n, a)
    s_perm = np.concatenate([obs[:, perm].reshape(6, -1), acts[:, perm].reshape(6, -1)], axis=1)
    with torch.no_grad():
        m, m_p = (net.message_mean(torch.from_numpy(x)).numpy() for x in (s, s_perm))
        v, v_p = (net.values(torch.from_numpy(x)).numpy() for x in (s, s_perm))
    np.testing.assert_allclose(m_p, m[:, perm], atol=1e-6)
    np.testing.assert_allclose(v_p, v[:, perm], atol=1e-6)
    np.testing.assert_allclose(npn.message_mean(s_perm), npn.message_mean(s)[:, perm], atol=1e-6)
    # the concat net is not: its heads are per agent slot
    cfg = merge_config("cn5", overrides=[f"n_agents={n}"])
    concat = make_central(cfg.wiring, d, a, [64, 64], [64, 32])
    with torch.no_grad():
        c, c_p = (concat.message_mean(torch.from_numpy(x)).numpy() for x in (s, s_perm))
    assert not np.allclose(c_p, c[:, perm], atol=1e-3)


def test_the_set_net_grows_with_n_not_n_squared():
    """On cn (obs 6N, 5 actions) the concat net's parameters grow ~N², the set net's ~N."""
    def size(net_kind: str, n: int) -> int:
        cfg = merge_config("cn5", overrides=[f"n_agents={n}", f"central_net={net_kind}"])
        return sum(p.numel() for p in make_central(cfg.wiring, 6 * n, 5, [64, 64], [64, 32]).parameters())

    concat = [size("concat", n) for n in (5, 10, 20)]
    sets = [size("set", n) for n in (5, 10, 20)]
    # N = 5 -> 10 -> 20: a linear size grows twice as much over the second step, a quadratic one 4x
    assert concat[2] - concat[1] > 3 * (concat[1] - concat[0])
    assert sets[2] - sets[1] == pytest.approx(2 * (sets[1] - sets[0]), rel=1e-9)
    assert sets[2] < concat[2] / 5


def test_wiring_builds_the_net_the_config_names():
    spec = make_vec_env("cn", 3, 1).spec
    for kind, cls in (("concat", "CentralAgent"), ("set", "SetCentralAgent")):
        cfg = merge_config("cn3", overrides=[f"central_net={kind}"])
        assert cfg.wiring.set_central == (kind == "set")
        net = make_central(cfg.wiring, spec.obs_dim, spec.action_dim, cfg.central_hidden, cfg.critic_hidden)
        assert type(net).__name__ == cls
        npn = numpy_central(net.export_numpy())
        assert npn.kind == kind and isinstance(npn, NumpySetCentralAgent if kind == "set" else NumpyCentralAgent)
    assert merge_config("cn3").central_net == "concat"  # the paper's network stays the default
    assert merge_config("cn3", overrides=["central_net=set"]).wiring.label == "hammer-rl-set"
    assert merge_config("cn3").wiring.label == "hammer-rl"


@pytest.mark.parametrize("variant", ["il", "random", "centralized"])
def test_set_without_a_central_network_is_a_config_error(variant):
    with pytest.raises(ConfigError, match=r"config field 'central_net': variant .* has no central network.*fix:"):
        merge_config("cn3", overrides=["central_net=set"], extra={"variant": variant})
    with pytest.raises(ConfigError, match=r"config field 'central_net'.*fix: use concat"):
        merge_config("cn3", overrides=["central_net=attention"])


def _first_batch(tmp_path, mode: str):
    cfg = merge_config("cn3", overrides=[f"central_mode={mode}", "central_net=set", "num_envs=4", "episodes=100"])
    env = make_vec_env("cn", 3, 4)
    tr = Trainer(cfg, RunDir.create(tmp_path / mode, cfg), env=env, tensorboard=False)
    obs, _ = env.reset(0)
    tr._t0 = 0.0
    obs, prev, _ = tr._collect(obs, tr.team.zero_prev_actions(4))
    return tr, tr.learner.batch(obs, prev)[0]  # the fields; every masking op (the default) is right for any slice


def test_each_central_mode_trains_the_set_net_through_its_own_graph(tmp_path):
    """backprop: the local loss reaches every weight of the set net; rl: only the central loss does."""
    tr, b = _first_batch(tmp_path, "backprop")
    assert tr.team.central.critic is None
    local, central, _ = tr.learner.losses({k: v[:100] for k, v in b.items()})
    assert central is None
    local.backward()
    assert all(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in tr.team.central.parameters())
    tr, b = _first_batch(tmp_path, "rl")
    local, central, _ = tr.learner.losses({k: v[:100] for k, v in b.items()})
    local.backward(retain_graph=True)
    assert all(p.grad is None for p in tr.team.central.parameters())
    tr.team.local.zero_grad(set_to_none=True)
    central.backward()
    assert all(p.grad is not None and float(p.grad.abs().sum()) > 0 for p in tr.team.central.parameters())
    assert all(p.grad is None for p in tr.team.local.parameters())


def _metric(path):
    with open(path / "metrics.csv", newline="") as f:
        return np.array([float(r["paper_metric"]) for r in csv.DictReader(f)])


@pytest.mark.parametrize("mode", ["rl", "backprop"])
def test_hammer_with_the_set_net_improves_on_cn3(tmp_path, mode):
    """The same budget and bar as tests/test_trainer_learning.py's concat test (its docstring says why 1,000 episodes)."""
    cfg = merge_config("cn3", overrides=["variant=hammer", f"central_mode={mode}", "central_net=set",
                                         "episodes=1000", "seed=0"])
    train(cfg, RunDir.create(tmp_path / mode, cfg), tensorboard=False)
    m = _metric(tmp_path / mode)
    assert m[-200:].mean() > m[:200].mean() + 1.0, (mode, m[:200].mean(), m[-200:].mean())
    final = load_safetensors((tmp_path / mode / "final" / "central.safetensors").read_bytes())
    assert "layout" in final and numpy_central(final).kind == "set"
