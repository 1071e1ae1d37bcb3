"""The conv encoder option for image observations (cfg.obs_conv): the torch network and its numpy
twin (what a local agent runs, without torch) agree; a run on real images (pistonball) trains with it."""

import numpy as np
import pytest
import torch
from hammer.learning.config import ConfigError, merge_config
from hammer.learning.networks import LocalPolicy
from hammer.learning.numpy_policy import NumpyLocalPolicy
from typer.testing import CliRunner

from hammer.cli import app

PISTONBALL = "pettingzoo.butterfly.pistonball_v6:parallel_env"


@pytest.mark.parametrize("discrete", [True, False])
def test_numpy_twin_matches_torch_with_a_conv_encoder(discrete):
    torch.manual_seed(0)
    image, rest = (12, 10, 2), 5  # an image plus a message / agent id beside it
    in_dim = int(np.prod(image)) + rest
    net = LocalPolicy(in_dim, 3, discrete, [32], [16], image=image)
    x = np.random.default_rng(0).uniform(0, 1, (4, 3, in_dim)).astype(np.float32)
    twin = NumpyLocalPolicy(net.export_numpy())
    with torch.no_grad():
        want_a, want_v = net.actor_out(torch.from_numpy(x)).numpy(), net.value(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(twin.actor_out(x), want_a, atol=1e-5)
    np.testing.assert_allclose(twin.value(x), want_v, atol=1e-5)
    assert twin.in_dim == in_dim
    x2 = x.copy()
    x2[..., in_dim - rest:] += 1.0  # the values beside the image reach the output too
    assert not np.allclose(twin.actor_out(x2), twin.actor_out(x))


def test_obs_conv_config_errors_name_the_fix():
    with pytest.raises(ConfigError, match="obs_conv"):
        merge_config("cn3", overrides=["obs_conv=[32, 32]"])
    with pytest.raises(ConfigError, match="centralized"):
        merge_config("cn3", overrides=["obs_conv=[32, 32, 1]", "variant=centralized"])
    with pytest.raises(ValueError, match="too small"):
        LocalPolicy(6 * 6 + 4, 3, True, [8], [8], image=(6, 6, 1))


def test_a_short_pistonball_run_with_the_conv_encoder(tmp_path):
    res = CliRunner().invoke(app, [
        "train", "--set", f"env={PISTONBALL}", "--set", "n_agents=3", "--set", "env_kwargs.n_pistons=3",
        "--set", "env_kwargs.max_cycles=20", "--set", "env_adapters=[gray,resize:16x16,flatten]",
        "--set", "obs_conv=[16, 16, 1]", "--set", "num_envs=2", "--set", "rollout_steps=10",
        "--set", "minibatches=1", "--set", "epochs=1", "--episodes", "4", "--run-dir", str(tmp_path / "r"),
        "--quiet"])
    assert res.exit_code == 0, res.output
    from safetensors.numpy import load_file

    params = load_file(str(tmp_path / "r" / "final" / "local.safetensors"))
    assert "actor_enc.convs.0.weight" in params and "critic_enc.convs.1.weight" in params


def test_an_image_shape_larger_than_the_observation_is_refused_before_any_file(tmp_path):
    res = CliRunner().invoke(app, ["train", "--set", "obs_conv=[32, 32, 1]", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "obs_conv" in res.output and "resize:32x32" in " ".join(res.output.split())
    assert not any(tmp_path.iterdir())
