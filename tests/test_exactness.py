"""The two exactness contracts under other CPUs' maths kernels (docs/learning.md "Determinism").

Each check runs in fresh interpreters under the settings of `runtime_helpers.DISPATCH` (glibc's
libm without FMA, numpy's SIMD loops at the baseline, OpenBLAS, ATen, MKL and oneDNN at older
kernels): the kernels another x86-64 CPU would run. A result that depends on which kernel ran
differs between them, so a CPU-dependent path coming back fails here, not on a user's machine:
- the draw: the numpy agent's (`sampling.categorical_draw`) and the lite agent's
  (`categorical.draw`) are one action on every setting, also for uniforms exactly on a CDF value,
  where an exp one ulp off flips the action;
- the central forward: the trainer's (`Team.central_messages`) is bit for bit what the central
  server computes from the weights the learner sends, for both central networks;
- `hammer up` reproduces `hammer train` bit for bit on each setting: tests/test_rware.py.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hammer.learning import categorical
from hammer.learning.sampling import categorical_draw

from tests.runtime_helpers import DISPATCH, ENV, ROOT

_DRAWS = r"""
import hashlib, json, sys
import numpy as np
from hammer.learning import categorical
from hammer.learning.sampling import categorical_draw

case = np.load(sys.argv[1])
z, u = case["logits"], case["u"]
ids = categorical_draw(z, u)[0]
lite = [categorical.draw(r, x) for r, x in zip(z.tolist(), u.tolist())]
e = np.exp(-np.abs(np.random.default_rng(0).standard_normal(100000)) * 4)
draws = {"draws": ids.tolist(), "lite_agrees": ids.tolist() == lite,
         "np_exp": hashlib.sha256(e.tobytes()).hexdigest()}
"""


def _boundary_case(path) -> None:
    """Rows of logits, each repeated once per CDF value, with the uniform exactly on that value:
    of the exact softmax, and of numpy's softmax here (where another exp's last bit decides)."""
    from hammer.learning.numpy_policy import softmax

    logits = (np.random.default_rng(5).standard_normal((10000, 5)) * 3).astype(np.float32)
    exact = np.cumsum([categorical.softmax(r) for r in logits.tolist()], axis=1)[:, :-1]
    here = np.cumsum(softmax(logits), axis=1)[:, :-1]
    np.savez(path, logits=np.repeat(logits, 8, axis=0), u=np.concatenate([exact, here], axis=1).reshape(-1))


_CENTRAL = r"""
import json
import numpy as np
import torch
from hammer.api import config
from hammer.learner.worker import weights_blob
from hammer.learning.central_acting import CentralActing
from hammer.learning.numpy_policy import numpy_central, params_from_blob
from hammer.learning.run_env import make_env
from hammer.learning.sampling import ActingStreams
from hammer.learning.team import Team

central = {}
for net in ("concat", "set"):
    cfg = config("cn3", variant="hammer", central_mode="rl", central_net=net, num_envs=8)
    spec = make_env(cfg).spec
    team = Team(cfg, spec)
    state = np.random.default_rng(1).standard_normal((8, team.state_dim)).astype(np.float32)
    same = []
    for round in range(2):
        if round:  # weights changed in place, as an update changes them: both sides see the new ones
            with torch.no_grad():
                for p in team.central.parameters():
                    p.add_(torch.randn_like(p) * 0.05)
        mine = team.central_messages(state, ActingStreams(3, cfg.n_agents))
        server = numpy_central(params_from_blob(weights_blob(team.central.export_numpy())))
        theirs = CentralActing.from_config(cfg).messages(state, ActingStreams(3, cfg.n_agents), 0.0,
                                                         server.message_mean, server.values)
        torch_mean = team.central.message_mean(torch.from_numpy(state)).detach().numpy()
        same.append({f: getattr(mine, f).tobytes() == getattr(theirs, f).tobytes()
                     for f in ("sent", "mean", "raw", "logp", "value", "keep")})
        same[-1]["torch_within_1e-5"] = bool(np.abs(torch_mean - mine.mean).max() < 1e-5)
    central[net] = same
"""


def _run(code: str, env: dict[str, str], *args: str) -> dict:
    r = subprocess.run([sys.executable, "-c", code, *args], check=False, capture_output=True, text=True, timeout=240,
                       cwd=ROOT, env={**ENV, **env})
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_exp_nonpositive_is_within_an_ulp():
    """The contract's exp against exp computed in 60 decimal digits (software arithmetic: the
    same everywhere), also into the subnormals and at the ends of its range."""
    from decimal import Decimal, getcontext

    getcontext().prec = 60
    rng = np.random.default_rng(0)
    xs = [*(-np.abs(rng.standard_normal(3000)) * 6).tolist(), *(-rng.random(1000) * 760).tolist(),
          0.0, -0.0, -1e-300, -708.39, -708.4, -744.4, -745.13, -745.14, -800.0]
    for x in xs:
        want = float(Decimal(x).exp())
        got = categorical.exp_nonpositive(x)
        assert abs(got - want) <= (max(want, 2.0 ** -1022) * 2.0 ** -52 if want else 0.0), (x, got, want)
    assert categorical.exp_nonpositive(float("-inf")) == 0.0 and categorical.exp_nonpositive(0.0) == 1.0
    assert categorical.exp_nonpositive(float("nan")) != categorical.exp_nonpositive(float("nan"))


def test_the_numpy_draw_is_the_exact_draw_also_on_a_boundary():
    """In this process: numpy's draw for rows of every shape, with the uniform on a CDF value of
    the exact softmax, on the next float below it, anywhere; a nan row and one action."""
    rng = np.random.default_rng(7)
    logits = (rng.standard_normal((3000, 6)) * 4).astype(np.float32)
    cdf = np.cumsum([categorical.softmax(r) for r in logits.tolist()], axis=1)
    col = rng.integers(0, 5, 3000)
    u = rng.random(3000)
    u[:1000] = cdf[np.arange(1000), col[:1000]]
    u[1000:2000] = np.nextafter(cdf[np.arange(1000, 2000), col[1000:2000]], 0)
    ids, probs = categorical_draw(logits.reshape(30, 100, 6), u.reshape(30, 100))
    assert ids.shape == (30, 100) and probs.shape == (30, 100, 6)
    assert ids.reshape(-1).tolist() == [categorical.draw(r, x) for r, x in zip(logits.tolist(), u.tolist())]
    assert categorical_draw(np.zeros((2, 1), np.float32), np.array([0.3, 0.9]))[0].tolist() == [0, 0]
    nan_row = np.array([[np.nan, 0.0, 1.0]], np.float32)
    assert categorical_draw(nan_row, np.array([0.5]))[0].tolist() == [categorical.draw(nan_row[0].tolist(), 0.5)]


@pytest.fixture(scope="module")
def under_every_dispatch(tmp_path_factory) -> dict[str, dict]:
    """Each setting's draws and central forwards, from one fresh interpreter per setting (the
    settings act at a process's start; an interpreter's start-up is most of a check's cost). The
    draws are made before the central script imports torch, as in an interpreter of their own."""
    case = tmp_path_factory.mktemp("draws") / "case.npz"
    _boundary_case(case)
    code = f"{_DRAWS}{_CENTRAL}print(json.dumps({{'draws': draws, 'central': central}}))"
    return {name: _run(code, env, str(case)) for name, env in DISPATCH.items()}


def test_draws_are_the_same_under_every_dispatch(under_every_dispatch):
    """80,000 draws on CDF values, numpy's and the lite agent's, under each setting: one list."""
    got = {name: r["draws"] for name, r in under_every_dispatch.items()}
    for name, r in got.items():
        assert r["lite_agrees"], f"{name}: the numpy agent's draw is not the lite agent's"
    ref = got["default"]["draws"]
    for name, r in got.items():
        differ = sum(a != b for a, b in zip(r["draws"], ref))
        assert differ == 0, (f"{name}: {differ} of {len(ref)} draws differ from the default kernels' "
                             f"(numpy's exp {'differs' if r['np_exp'] != got['default']['np_exp'] else 'agrees'})")


def test_the_trainers_central_forward_is_the_central_servers_under_every_dispatch(under_every_dispatch):
    """Both central networks, before and after an in-place weight change: the trainer's messages,
    samples, log-densities and critic values are the central server's, bit for bit (torch's
    forward, for comparison, is only close)."""
    for name, r in under_every_dispatch.items():
        for net, rounds in r["central"].items():
            for i, fields in enumerate(rounds):
                assert all(fields.values()), f"{name}, central_net={net}, round {i}: {fields}"
