"""The acting side of a HAMMER team, shared by the in-process trainer and the runtime.

One `Team` holds the shared local policy and (variant hammer) the central agent, and knows how
each variant wires them:
  hammer       local input = o_i ⊕ u_i, u from the central agent (rl: Gaussian sample, backprop: mean)
  random       local input = o_i ⊕ u_i, u uniform in [-1, 1] from the central stream
  il           local input = o_i
  centralized  local input = o_1 ⊕ … ⊕ o_N ⊕ one-hot(i)
All acting randomness goes through `learning.sampling.ActingStreams` (the randomness contract).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from hammer.envs.base import EnvSpec
from hammer.envs.local_view import local_view_from_config
from hammer.learning.central_acting import CentralActing, CentralOut, encode_actions, zero_prev_actions
from hammer.learning.config import ConfigError, RunConfig
from hammer.learning.fused_acting import FusedActing
from hammer.learning.networks import CentralAgent, LocalPolicy, SetCentralAgent, make_central
from hammer.learning.numpy_policy import gaussian_logp_of_draw, numpy_central, softmax, take_last
from hammer.learning.precision import check_precision
from hammer.learning.run_env import check_env_fits
from hammer.learning.sampling import ActingStreams, categorical_draw

# (message_mean, values): state (K, S) -> (K, N, M) message means, (K, N) central values
_CentralForward = tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray]]


def torch_device(cfg: RunConfig) -> torch.device:
    """The device of `cfg.device`, refused up front where torch cannot use it: a run asked for a GPU
    must not silently train on the CPU, nor fail half-built at its first tensor. Also refuses
    `precision=bf16` where the device has no native bfloat16 (`learning.precision`)."""
    dev = torch.device(cfg.device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"config field 'device': device={cfg.device}: torch sees no CUDA device "
                              "(torch.cuda.is_available() is False; this torch build is CPU-only or no GPU is "
                              "visible); fix: --set device=cpu")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"config field 'device': device={cfg.device}: torch sees only "
                              f"{torch.cuda.device_count()} CUDA device(s); fix: --set device=cuda:0")
    check_precision(cfg.precision, dev)
    return dev


class Team:
    """Networks + variant wiring; numpy in, numpy out on the acting path."""

    def __init__(self, cfg: RunConfig, spec: EnvSpec) -> None:
        self.device = torch_device(cfg)
        torch.manual_seed(cfg.seed)
        self.cfg, self.spec = cfg, spec
        if cfg.site_missing_prob > 0 and spec.local_obs_dim in (None, spec.obs_dim):
            raise ConfigError(f"site_missing_prob: {spec.name} has no site feed (every robot observes its whole "
                              "row); fix: leave it at 0 (it is for envs with central-only columns, e.g. rware)")
        self.n, self.obs_dim = spec.n_agents, spec.obs_dim
        self.discrete = spec.discrete
        self.act_dim = spec.action_dim  # one-hot width (discrete) or vector length (continuous)
        self.msg_dim = cfg.effective_msg_dim
        self.state_dim = self.n * self.obs_dim + (self.n * self.act_dim if cfg.use_prev_actions else 0)
        self.wiring = cfg.wiring
        self.local_in_dim = self.wiring.local_input_dim(self.obs_dim)
        image = tuple(cfg.obs_conv) if cfg.obs_conv else None
        check_env_fits(cfg, spec)
        # Built and initialised on the CPU, then moved: one seed gives the same initial weights on
        # every device (the CPU and CUDA generators differ).
        with torch.device("cpu"):
            self.local = LocalPolicy(self.local_in_dim, self.act_dim, self.discrete, cfg.actor_hidden,
                                     cfg.critic_hidden, cfg.log_std_init, image=image)
            self.central: CentralAgent | SetCentralAgent | None = None
            if self.wiring.has_central_network:
                self.central = make_central(self.wiring, self.obs_dim, self.act_dim if cfg.use_prev_actions else 0,
                                            cfg.central_hidden, cfg.critic_hidden)
        self.local.to(self.device)
        if self.central is not None:
            self.central.to(self.device)
        # every tensor of the central network (buffers too, as export_numpy writes them), by name
        self._central_tensors = list(self.central.state_dict(keep_vars=True).items()) if self.central else []
        self._eye = torch.eye(self.n, device=self.device)
        self.acting = CentralActing.from_config(cfg)
        # What a local agent may see of the full observation (identity unless env_kwargs asks):
        # applied to every local-policy input here, never to the global state.
        self.local_view = local_view_from_config(cfg, spec)
        self.fused = FusedActing(self) if cfg.compile else None

    def act(self, obs: np.ndarray, state: np.ndarray, streams: ActingStreams, dropout: float = 0.0
            ) -> tuple[CentralOut, np.ndarray, np.ndarray, np.ndarray]:
        """One vector step of the whole team: the central messages, then every local agent's
        (action, logp, value) on them. compile=true: one compiled graph (`learning.fused_acting`);
        otherwise `central_messages` then `local_act`."""
        if self.fused is not None:
            return self.fused.act(obs, state, streams, dropout)
        c = self.central_messages(state, streams, dropout)
        return (c, *self.local_act(obs, c.sent, streams))

    @property
    def central_rl(self) -> bool:
        return self.wiring.central_rl

    # ----- global state -------------------------------------------------------------------------
    def encode_actions(self, actions: np.ndarray, active: np.ndarray) -> np.ndarray:
        return encode_actions(self.spec, actions, active)

    def zero_prev_actions(self, k: int) -> np.ndarray:
        return zero_prev_actions(self.spec, k)

    def global_state(self, obs: np.ndarray, prev_actions: np.ndarray, step: int | None = None,
                     env_idx: np.ndarray | None = None) -> np.ndarray:
        """The central agent's state; at vector `step` of training (of copies `env_idx`, default all),
        with the robots that `missing_prob` and the site feed that `site_missing_prob` take away at
        that step zeroed (CentralActing.training_state)."""
        if step is None:
            return self.acting.global_state(obs, prev_actions)
        return self.acting.training_state(obs, prev_actions, step,
                                          np.arange(obs.shape[0]) if env_idx is None else env_idx,
                                          self.spec.local_obs_dim)

    # ----- host <-> device ----------------------------------------------------------------------
    def tensor(self, a: np.ndarray) -> torch.Tensor:
        """A host array as a tensor on the team's device (no copy on the CPU)."""
        return torch.from_numpy(a).to(self.device)

    @staticmethod
    def host(t: torch.Tensor) -> np.ndarray:
        """A tensor as a host array (no copy on the CPU): envs and acting draws are numpy."""
        return t.detach().cpu().numpy()

    # ----- central agent ------------------------------------------------------------------------
    def central_forward(self) -> _CentralForward:
        """The central network's forward on host arrays: (message_mean, values).

        On the CPU it is the central server's own (`numpy_policy.numpy_central`, what `hammer up`
        runs) over views of this team's current weights, taken at each call (so always the weights
        of now: updated in place, loaded or swapped): the messages, their log-densities and the
        critic values the trainer acts and learns on are then the very numbers the central server
        of a `hammer up` run sends and records, on any CPU. torch computes the same function with
        other kernels (MKL's, its own tanh): the two agree to ~1e-7, and PPO's clipping turns such
        a difference into a different update now and then (tests/test_exactness.py). On a GPU the
        torch forward runs on the device."""
        if self.device.type == "cpu":
            net = numpy_central({name: t.detach().cpu().numpy() for name, t in self._central_tensors})
            return net.message_mean, net.values
        return (lambda s: self.host(self.central.message_mean(self.tensor(s))),
                lambda s: self.host(self.central.values(self.tensor(s))))

    def _message_mean(self, state: np.ndarray) -> np.ndarray:
        return self.central_forward()[0](state)

    def _values(self, state: np.ndarray) -> np.ndarray:
        return self.central_forward()[1](state)

    @torch.inference_mode()
    def central_messages(self, state: np.ndarray, streams: ActingStreams, dropout: float = 0.0) -> CentralOut:
        """Messages for every agent of every copy from the global state (K, S): the central
        network's forward (`central_forward`: the central server's on the CPU), then the sampling
        the central server runs after it (`CentralActing`)."""
        if self.central is None:
            return self.acting.messages(state, streams, dropout, None, None)
        mean, values = self.central_forward()
        return self.acting.messages(state, streams, dropout, mean, values if self.central_rl else None)

    @torch.inference_mode()
    def bootstrap_messages(self, state: np.ndarray) -> np.ndarray:
        """Messages used only to value a state (no stream draws): central mean, zeros for random."""
        if self.central is not None:
            return self._message_mean(state)
        return np.zeros((state.shape[0], self.n, self.msg_dim), dtype=np.float32)

    @torch.inference_mode()
    def central_values(self, state: np.ndarray) -> np.ndarray:
        if not self.central_rl:
            return np.zeros((state.shape[0], self.n), dtype=np.float32)
        return self._values(state)

    # ----- local agents -------------------------------------------------------------------------
    def local_input(self, obs: torch.Tensor, msg: torch.Tensor) -> torch.Tensor:
        """(B, N, D) obs and (B, N, M) messages → (B, N, in) local policy input."""
        if self.wiring.joint_obs:
            b = obs.shape[0]
            joint = obs.reshape(b, 1, -1).expand(b, self.n, self.n * self.obs_dim)
            return torch.cat([joint, self._eye.expand(b, self.n, self.n)], dim=-1)
        if self.msg_dim == 0:
            return obs
        return torch.cat([obs, msg], dim=-1)

    @torch.inference_mode()
    def local_act(self, obs: np.ndarray, msg: np.ndarray, streams: ActingStreams
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All K×N local agents in one forward pass → (action, logp, value).

        Discrete: int64 (K, N) sampled by inverse CDF. Continuous: float32 (K, N, A) unclipped
        Gaussian sample (its logp is what PPO trains; `env_action` clips it for the env).
        """
        x = self.local_input(self.tensor(self.local_view(obs)), self.tensor(msg))
        return self.sample_local(self.host(self.local.actor_out(x)), self.host(self.local.value(x)), streams)

    def sample_local(self, out: np.ndarray, value: np.ndarray, streams: ActingStreams
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """`local_act` after the forward pass: the stream draws and the sampling from the actor's
        output (K, N, A) (the seed-batched trainer runs the forward for many seeds at once)."""
        k = out.shape[0]
        if self.discrete:
            u = streams.local_uniforms(k)
            action, probs = categorical_draw(out, u)  # float64, as the randomness contract specifies
            logp = np.log(take_last(probs, action)).astype(np.float32)
            return action, logp, value
        z = streams.local_normals(k, self.act_dim)
        log_std = self.host(self.local.log_std)
        action = (out + np.exp(log_std) * z).astype(np.float32)
        return action, gaussian_logp_of_draw(z, log_std), value

    @torch.inference_mode()
    def local_evaluate(self, obs: np.ndarray, msg: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(logp, value) of given actions, computed as `local_act` computes them: the distributed
        learner uses this to rebuild exactly the trainer's rollout from remote actions."""
        x = self.local_input(self.tensor(self.local_view(obs)), self.tensor(msg))
        out = self.host(self.local.actor_out(x))
        value = self.host(self.local.value(x))
        if self.discrete:
            probs = softmax(out)
            return np.log(take_last(probs, action)).astype(np.float32), value
        log_std = self.host(self.local.log_std)
        z = (action - out) / np.exp(log_std)  # the Gaussian draw behind the action (to float precision)
        return gaussian_logp_of_draw(z, log_std), value

    @torch.inference_mode()
    def local_values(self, obs: np.ndarray, msg: np.ndarray) -> np.ndarray:
        x = self.local_input(self.tensor(self.local_view(obs)), self.tensor(msg))
        return self.host(self.local.value(x))

    def env_action(self, action: np.ndarray) -> np.ndarray:
        return self.spec.env_action(action)
