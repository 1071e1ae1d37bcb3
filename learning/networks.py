"""The two networks of HAMMER (torch).

`LocalPolicy`: one actor-critic shared by all local agents (parameter sharing). Input is
own obs ⊕ message (il: own obs; centralized: joint obs ⊕ one-hot agent index).
`CentralAgent`: shared encoder over the global state + one linear decoder head per local agent,
tanh → message mean in [-1, 1]; in rl mode also a critic with one value per agent.

Layer names are part of the contract with `learning.numpy_policy`, which reruns the forward pass
in numpy from `export_numpy()`; keep the two in step.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch
from torch import nn


def _init(layer: nn.Linear, std: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.zeros_(layer.bias)
    return layer


class TanhMLP(nn.Module):
    """Linear layers with tanh between them (and after the last one if final_tanh)."""

    def __init__(self, sizes: list[int], out_std: float, final_tanh: bool = False) -> None:
        super().__init__()
        n = len(sizes) - 1
        self.layers = nn.ModuleList(
            _init(nn.Linear(a, b), out_std if i == n - 1 else math.sqrt(2)) for i, (a, b) in
            enumerate(itertools.pairwise(sizes))
        )
        self.final_tanh = final_tanh

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i < last or self.final_tanh:
                x = torch.tanh(x)
        return x


class _Exportable(nn.Module):
    def export_numpy(self) -> dict[str, np.ndarray]:
        """All weights as a flat {name: float32 array} dict (what edge devices load)."""
        return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in self.state_dict().items()}

    def load_numpy(self, params: dict[str, np.ndarray]) -> None:
        self.load_state_dict({k: torch.as_tensor(np.asarray(v)) for k, v in params.items()})


class LocalPolicy(_Exportable):
    """Shared local actor-critic: categorical head (discrete) or Gaussian with a free log-std."""

    def __init__(self, in_dim: int, action_dim: int, discrete: bool, actor_hidden: list[int],
                 critic_hidden: list[int], log_std_init: float = -0.5) -> None:
        super().__init__()
        self.in_dim, self.action_dim, self.discrete = in_dim, action_dim, discrete
        self.actor = TanhMLP([in_dim, *actor_hidden, action_dim], out_std=0.01)
        self.critic = TanhMLP([in_dim, *critic_hidden, 1], out_std=1.0)
        if not discrete:
            self.log_std = nn.Parameter(torch.full((action_dim,), float(log_std_init)))

    def actor_out(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (discrete) or the Gaussian mean (continuous)."""
        return self.actor(x)

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def logp_entropy(self, x: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """log π(a|x) and the policy entropy, for stored actions (unclipped samples if continuous)."""
        out = self.actor(x)
        if self.discrete:
            logp_all = torch.log_softmax(out, dim=-1)
            logp = logp_all.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
            entropy = -(logp_all.exp() * logp_all).sum(-1)
            return logp, entropy
        return gaussian_logp(action, out, self.log_std), gaussian_entropy(self.log_std).expand(out.shape[:-1])


def gaussian_logp(x: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Diagonal Gaussian log-density summed over the last axis."""
    z = (x - mean) * torch.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    return (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)


class CentralAgent(_Exportable):
    """Encoder over the global state, one linear head per local agent, tanh message means.

    The heads are stored as one (N, H, M) weight tensor so all N messages come out of one einsum
    instead of a Python loop over agents.
    """

    def __init__(self, state_dim: int, n_agents: int, msg_dim: int, hidden: list[int],
                 critic_hidden: list[int] | None) -> None:
        super().__init__()
        self.state_dim, self.n_agents, self.msg_dim = state_dim, n_agents, msg_dim
        self.encoder = TanhMLP([state_dim, *hidden], out_std=math.sqrt(2), final_tanh=True)
        h = hidden[-1]
        w = torch.empty(n_agents, msg_dim, h)
        for i in range(n_agents):
            nn.init.orthogonal_(w[i], 1.0)
        self.head_weight = nn.Parameter(w.transpose(1, 2).contiguous())  # (N, H, M)
        self.head_bias = nn.Parameter(torch.zeros(n_agents, msg_dim))
        self.critic = TanhMLP([state_dim, *critic_hidden, n_agents], out_std=1.0) if critic_hidden else None

    def message_mean(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) → (..., N, M) message means in [-1, 1]."""
        h = self.encoder(state)
        return torch.tanh(torch.einsum("...h,nhm->...nm", h, self.head_weight) + self.head_bias)

    def values(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) → (..., N): value of the message stream to each agent (rl mode only)."""
        if self.critic is None:
            raise RuntimeError("this CentralAgent was built without a critic (backprop mode)")
        return self.critic(state)
