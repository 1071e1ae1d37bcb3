"""The two networks of HAMMER (torch).

`LocalPolicy`: one actor-critic shared by all local agents (parameter sharing). Input is
own obs ⊕ message (il: own obs; centralized: joint obs ⊕ one-hot agent index).
`CentralAgent` (`central_net=concat`, the paper's): shared encoder over the global state + one linear
decoder head per local agent, tanh → message mean in [-1, 1]; in rl mode also a critic with one
value per agent. `SetCentralAgent` (`central_net=set`): the same interface (global state in, N
message means and N values out) from a per-agent encoder shared by all agents and attention across
them, so its size does not grow with N² (`make_central` picks one from the run's wiring).

Layer names are part of the contract with `learning.numpy_policy`, which reruns the forward pass
in numpy from `export_numpy()`; keep the two in step.
"""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

if TYPE_CHECKING:
    from hammer.learning.variant import Wiring


def _init(layer: nn.Linear, std: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.zeros_(layer.bias)
    return layer


class _SigmoidTanh(torch.autograd.Function):
    """tanh(x) = 2σ(2x) − 1 with tanh's own backward (1 − y²)·g."""

    generate_vmap_rule = True  # the seed-batched trainer differentiates it under torch.func.vmap

    @staticmethod
    def forward(x: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        return (x * 2.0).sigmoid_().mul_(2.0).sub_(1.0)

    @staticmethod
    def setup_context(ctx, inputs: tuple[torch.Tensor], output: torch.Tensor) -> None:  # type: ignore[override]
        # A separate setup_context (not ctx in forward) is what torch.func.grad needs (compile=true).
        ctx.save_for_backward(output)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


# `_SigmoidTanh.apply` without `torch.autograd.Function.apply`'s Python wrapper, which binds the
# arguments to forward's signature by `inspect.signature` on every call (a noticeable part of an
# eager PPO update, hundreds of calls each) before calling this same C entry point. Only for plain
# tensors outside functorch transforms (the wrapper's other branch), which is where `tanh` uses it.
_sigmoid_tanh_apply = super(torch.autograd.Function, _SigmoidTanh).apply

_FAST_TANH_MIN = 8192  # elements; below this the plain kernel wins (call overhead dominates)


def tanh(x: torch.Tensor) -> torch.Tensor:
    """tanh for the hidden layers.

    torch's float32 tanh kernel is much slower than its sigmoid on x86 CPUs (docs/fast-envs.md),
    and tanh can be the most expensive op of a PPO update (more than the matmuls), so large tensors use 2σ(2x) − 1, which
    is tanh up to ~2e-7 absolute (float32 rounding; numpy_policy's np.tanh matches to 1e-6).
    """
    if torch.compiler.is_compiling():
        return _traced_tanh(x)
    if x.numel() < _FAST_TANH_MIN:
        return torch.tanh(x)
    if torch._C._are_functorch_transforms_active():  # seed batches (vmap): plain ops batch cheaply
        return _traced_tanh(x)
    if x.requires_grad:
        return _sigmoid_tanh_apply(x)
    return (x * 2.0).sigmoid_().mul_(2.0).sub_(1.0)


def _traced_tanh(x: torch.Tensor) -> torch.Tensor:
    """tanh inside a torch.compile graph (compile=true) as plain ops, which inductor fuses into
    its kernels and AOTAutograd differentiates itself: the custom autograd.Function would keep the
    graph out of AOTAutograd's cache (a longer compile in every run). 2σ(2x) − 1 here too: inductor's
    tanh made the whole update slower."""
    return (x * 2.0).sigmoid() * 2.0 - 1.0


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
        # F.linear on the parameters directly: nn.Module.__call__ costs more than the tiny matmul.
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = F.linear(x, layer.weight, layer.bias)
            if i < last or self.final_tanh:
                x = tanh(x)
        return x.float()  # bfloat16 under autocast (precision=bf16): the losses take float32


class _Exportable(nn.Module):
    def export_numpy(self) -> dict[str, np.ndarray]:
        """All weights as a flat {name: float32 array} dict (what edge devices load)."""
        return {k: v.detach().cpu().numpy().astype(np.float32, copy=True) for k, v in self.state_dict().items()}


class ConvEncoder(nn.Module):
    """A small conv stem for image observations (`cfg.obs_conv` = [H, W, C]): the first H*W*C input
    values are an image in HWC order (what env_adapters [gray, resize:WxH, flatten] produce); two
    stride-2 convolutions with tanh turn it into features, the rest of the input (message, agent id)
    is passed on beside them. A flattened image through the MLP alone costs a first layer of H*W*C x
    hidden weights; the convolutions share theirs over the image. Numpy twin: `numpy_policy.conv_encode`."""

    channels, kernel, stride = (16, 32), 4, 2

    def __init__(self, image: tuple[int, int, int], in_dim: int) -> None:
        super().__init__()
        h, w, c = image
        self.register_buffer("image", torch.tensor([h, w, c], dtype=torch.float32))
        self.hwc, self.shape = h * w * c, (h, w, c)
        layers, ch = [], c
        for out in self.channels:
            layers.append(nn.Conv2d(ch, out, self.kernel, self.stride))
            ch, h, w = out, (h - self.kernel) // self.stride + 1, (w - self.kernel) // self.stride + 1
        if h < 1 or w < 1:
            raise ValueError(f"obs_conv: image {image} is too small for two {self.kernel}x{self.kernel} stride-"
                             f"{self.stride} convolutions; fix: at least 10x10 (e.g. env_adapters resize:32x32)")
        self.convs = nn.ModuleList(layers)
        self.out_dim = ch * h * w + in_dim - self.hwc

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        h, w, c = self.shape
        img = x[..., : self.hwc].reshape(-1, h, w, c).permute(0, 3, 1, 2)
        for conv in self.convs:
            img = torch.tanh(conv(img))
        return torch.cat([img.reshape(*lead, -1), x[..., self.hwc:]], dim=-1)


class LocalPolicy(_Exportable):
    """Shared local actor-critic: categorical head (discrete) or Gaussian with a free log-std.
    With `image` ([H, W, C], cfg.obs_conv) the actor and the critic each read the input through their
    own `ConvEncoder` first."""

    def __init__(self, in_dim: int, action_dim: int, discrete: bool, actor_hidden: list[int],
                 critic_hidden: list[int], log_std_init: float = -0.5,
                 image: tuple[int, int, int] | None = None) -> None:
        super().__init__()
        self.in_dim, self.action_dim, self.discrete = in_dim, action_dim, discrete
        self.actor_enc = ConvEncoder(image, in_dim) if image else None
        self.critic_enc = ConvEncoder(image, in_dim) if image else None
        self.actor = TanhMLP([self.actor_enc.out_dim if image else in_dim, *actor_hidden, action_dim], out_std=0.01)
        self.critic = TanhMLP([self.critic_enc.out_dim if image else in_dim, *critic_hidden, 1], out_std=1.0)
        if not discrete:
            self.log_std = nn.Parameter(torch.full((action_dim,), float(log_std_init)))

    def actor_out(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (discrete) or the Gaussian mean (continuous)."""
        return self.actor(x if self.actor_enc is None else self.actor_enc(x))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x if self.critic_enc is None else self.critic_enc(x)).squeeze(-1)

    def logp_entropy(self, x: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """log π(a|x) and the policy entropy, for stored actions (unclipped samples if continuous)."""
        out = self.actor_out(x)
        if self.discrete:
            logp_all = torch.log_softmax(out, dim=-1)
            logp = logp_all.gather(-1, action.long().unsqueeze(-1)).squeeze(-1)
            entropy = -(logp_all.exp() * logp_all).sum(-1)
            return logp, entropy
        return gaussian_logp(action, out, self.log_std), gaussian_entropy(self.log_std).expand(out.shape[:-1])


def gaussian_logp(x: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """Diagonal Gaussian log-density of x summed over the last axis (with grad, for the losses).
    The numpy twin on the acting path, from the standard-normal draw, is
    `numpy_policy.gaussian_logp_of_draw`."""
    z = (x - mean) * torch.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)


def gaussian_entropy(log_std: torch.Tensor) -> torch.Tensor:
    return (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)


class CentralAgent(_Exportable):
    """Encoder over the global state, one linear head per local agent, tanh message means.

    The heads are stored as one (N, H, M) weight tensor so all N messages come out of one matmul
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
        n, hid, m = self.head_weight.shape
        # All N heads as one (H, N*M) matmul: cheaper than an einsum (permutes + bmm) per call.
        w = self.head_weight.permute(1, 0, 2).reshape(hid, n * m)
        out = torch.addmm(self.head_bias.reshape(n * m), h.reshape(-1, hid), w).float()  # float32 under autocast
        return tanh(out.reshape(*h.shape[:-1], n, m))

    def values(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) → (..., N): value of the message stream to each agent (rl mode only)."""
        if self.critic is None:
            raise RuntimeError("this CentralAgent was built without a critic (backprop mode)")
        return self.critic(state)


class AgentAttention(nn.Module):
    """A shared per-agent encoder, then one round of scaled dot-product attention across agents,
    then a linear output per agent: (..., N, T) tokens → (..., N, out).

        e_i = enc(x_i)                                   (tanh MLP, `hidden`, tanh after the last layer)
        c_i = Σ_j softmax_j(q_i · k_j / √H) v_j          q = e Wq^T, k = e Wk^T, v = e Wv^T
        y_i = [e_i ⊕ c_i] Wo^T + bo

    Every weight is shared by all agents and the sum over j does not depend on their order, so
    permuting the agents permutes the outputs the same way (tested) and the parameter count depends
    on the token width, not on N. Attention (not a plain mean) lets agent i's output depend on
    which other agent is where relative to it, which is what assigning agents to landmarks needs.
    """

    def __init__(self, token_dim: int, hidden: list[int], out_dim: int, out_std: float) -> None:
        super().__init__()
        self.encoder = TanhMLP([token_dim, *hidden], out_std=math.sqrt(2), final_tanh=True)
        h = hidden[-1]
        self.query, self.key, self.value = (_init_no_bias(nn.Linear(h, h, bias=False)) for _ in range(3))
        self.out = _init(nn.Linear(2 * h, out_dim), out_std)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        e = self.encoder(tokens)
        q, k, v = (F.linear(e, lin.weight) for lin in (self.query, self.key, self.value))
        scores = torch.matmul(q, k.transpose(-1, -2)) / math.sqrt(e.shape[-1])  # (..., N, N)
        context = torch.matmul(torch.softmax(scores, dim=-1), v)
        return F.linear(torch.cat([e, context], dim=-1), self.out.weight, self.out.bias).float()  # as TanhMLP's


def _init_no_bias(layer: nn.Linear) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, 1.0)
    return layer


class SetCentralAgent(_Exportable):
    """`central_net=set`: the central agent as a function of the set of agents.

    The global state s = o_1 ⊕ … ⊕ o_N ⊕ a_1(t-1) ⊕ … ⊕ a_N(t-1) is read as N tokens
    x_i = o_i ⊕ a_i(t-1) (o_i alone without `use_prev_actions`); the message means are
    tanh(AgentAttention(x)) and, in rl mode, the values a second AgentAttention with its own weights
    (as the concat net's critic shares nothing with its encoder). Same interface as `CentralAgent`.

    The concat net's first layer has N·(D + A) inputs and its heads are one per agent, so on cn
    (D = 6N) it grows with N²; here only the token width D + A grows. The `layout` buffer
    [N, D, A] travels with the weights so the numpy twin (`numpy_policy.NumpySetCentralAgent`)
    can cut the state into tokens.
    """

    def __init__(self, n_agents: int, obs_dim: int, act_dim: int, msg_dim: int, hidden: list[int],
                 critic_hidden: list[int] | None) -> None:
        super().__init__()
        self.n_agents, self.obs_dim, self.act_dim, self.msg_dim = n_agents, obs_dim, act_dim, msg_dim
        self.state_dim = n_agents * (obs_dim + act_dim)
        self.register_buffer("layout", torch.tensor([n_agents, obs_dim, act_dim], dtype=torch.float32))
        self.msg = AgentAttention(obs_dim + act_dim, hidden, msg_dim, out_std=1.0)
        self.critic = AgentAttention(obs_dim + act_dim, critic_hidden, 1, out_std=1.0) if critic_hidden else None

    def tokens(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) global state → (..., N, D + A) per-agent tokens o_i ⊕ a_i(t-1)."""
        lead, n, d = state.shape[:-1], self.n_agents, self.obs_dim
        obs = state[..., : n * d].reshape(*lead, n, d)
        if self.act_dim == 0:
            return obs
        return torch.cat([obs, state[..., n * d:].reshape(*lead, n, self.act_dim)], dim=-1)

    def message_mean(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) → (..., N, M) message means in [-1, 1]."""
        return tanh(self.msg(self.tokens(state)))

    def values(self, state: torch.Tensor) -> torch.Tensor:
        """(..., S) → (..., N): value of the message stream to each agent (rl mode only)."""
        if self.critic is None:
            raise RuntimeError("this SetCentralAgent was built without a critic (backprop mode)")
        return self.critic(self.tokens(state)).squeeze(-1)


def make_central(wiring: Wiring, obs_dim: int, act_dim: int, hidden: list[int],
                 critic_hidden: list[int]) -> CentralAgent | SetCentralAgent:
    """The central network a run's wiring (`learning.variant.Wiring`) asks for. act_dim is the width
    of one agent's previous action in the state (0 without `use_prev_actions`); the critic exists in
    rl mode only."""
    critic = critic_hidden if wiring.central_rl else None
    if wiring.set_central:
        return SetCentralAgent(wiring.n_agents, obs_dim, act_dim, wiring.msg_dim, hidden, critic)
    return CentralAgent(wiring.n_agents * (obs_dim + act_dim), wiring.n_agents, wiring.msg_dim, hidden, critic)
