"""Forward passes of the exported networks in plain numpy (no torch: edge devices run this).

Loads the flat dicts from `LocalPolicy.export_numpy()` / `CentralAgent.export_numpy()` /
`SetCentralAgent.export_numpy()` (or a safetensors file read with safetensors.numpy) and reproduces
logits / Gaussian mean / values / message means to float32 tolerance. Layer naming follows
learning/networks.py; `numpy_central` picks the central network a weight dict holds.
"""

from __future__ import annotations

import numpy as np

LOG_2PI = float(np.log(2 * np.pi))


def params_from_blob(blob: bytes) -> dict[str, np.ndarray]:
    """The weight dict of a safetensors blob off the wire or a file (never pickle), float16 tensors
    as float32: a policy server may send the weights in half the bytes (`weights_float16`), and
    every forward pass computes in float32."""
    from safetensors.numpy import load

    return {k: v.astype(np.float32) if v.dtype == np.float16 else v for k, v in load(blob).items()}


def float16_blob(blob: bytes) -> bytes:
    """The same safetensors blob with every float32 tensor as float16 (half the bytes on a link)."""
    from safetensors.numpy import load, save

    return save({k: v.astype(np.float16) if v.dtype == np.float32 else v for k, v in load(blob).items()})


def _layers(params: dict[str, np.ndarray], prefix: str) -> list[tuple[np.ndarray, np.ndarray]]:
    out = []
    i = 0
    while f"{prefix}.layers.{i}.weight" in params:
        out.append((np.asarray(params[f"{prefix}.layers.{i}.weight"], dtype=np.float32),
                    np.asarray(params[f"{prefix}.layers.{i}.bias"], dtype=np.float32)))
        i += 1
    if not out:
        raise KeyError(f"no layers named '{prefix}.layers.0.weight' in the weight dict")
    return out


def mlp_forward(layers: list[tuple[np.ndarray, np.ndarray]], x: np.ndarray, final_tanh: bool) -> np.ndarray:
    """Same maths as networks.TanhMLP: x W^T + b, tanh between layers."""
    x = np.asarray(x, dtype=np.float32)
    last = len(layers) - 1
    for i, (w, b) in enumerate(layers):
        x = x @ w.T + b
        if i < last or final_tanh:
            x = np.tanh(x)
    return x


def softmax(logits: np.ndarray) -> np.ndarray:
    """Probabilities in float64 (what `sampling.categorical_inverse_cdf` consumes)."""
    e = np.array(logits, dtype=np.float64)  # a copy, computed in place from here (the same maths)
    e -= e.max(axis=-1, keepdims=True)
    np.exp(e, out=e)
    e /= e.sum(axis=-1, keepdims=True)
    return e


def take_last(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """`np.take_along_axis(a, idx[..., None], axis=-1)[..., 0]` (a: (..., A), idx: (...) ints) as one
    flat fancy index: the same values, without take_along_axis's per-call index building (this runs
    every acting step)."""
    flat = a.reshape(-1, a.shape[-1])
    return flat[np.arange(flat.shape[0]), idx.reshape(-1)].reshape(idx.shape)


def gaussian_logp_of_draw(z: np.ndarray, log_std: np.ndarray | float) -> np.ndarray:
    """Log-density of the Gaussian sample mean + exp(log_std) * z, summed over the last axis, from
    its standard-normal draw z (float32): acting knows z, so this needs no mean and no division.
    The torch twin, from the sample and the mean, is `networks.gaussian_logp` (training)."""
    return (-0.5 * z**2 - log_std - 0.5 * LOG_2PI).sum(-1).astype(np.float32)


def _conv(params: dict[str, np.ndarray], prefix: str) -> tuple[tuple[int, int, int], list] | None:
    if f"{prefix}.image" not in params:
        return None
    h, w, c = (int(v) for v in params[f"{prefix}.image"])
    convs, i = [], 0
    while f"{prefix}.convs.{i}.weight" in params:
        convs.append((np.asarray(params[f"{prefix}.convs.{i}.weight"], dtype=np.float32),
                      np.asarray(params[f"{prefix}.convs.{i}.bias"], dtype=np.float32)))
        i += 1
    return (h, w, c), convs


CONV_STRIDE = 2  # networks.ConvEncoder.stride


def conv_encode(enc: tuple[tuple[int, int, int], list] | None, x: np.ndarray) -> np.ndarray:
    """Same maths as networks.ConvEncoder: the first H*W*C values as an HWC image through the
    stride-2 convolutions with tanh, flattened channel-first, then the rest of x beside them."""
    if enc is None:
        return x
    (h, w, c), convs = enc
    x = np.asarray(x, dtype=np.float32)
    lead, hwc = x.shape[:-1], h * w * c
    img = x[..., :hwc].reshape(-1, h, w, c).transpose(0, 3, 1, 2)
    for weight, bias in convs:
        k = weight.shape[-1]
        win = np.lib.stride_tricks.sliding_window_view(img, (k, k), axis=(2, 3))[:, :, ::CONV_STRIDE, ::CONV_STRIDE]
        img = np.tanh(np.einsum("bchwij,ocij->bohw", win, weight, optimize=True) + bias[None, :, None, None])
    return np.concatenate([img.reshape(*lead, -1), x[..., hwc:]], axis=-1)


class NumpyLocalPolicy:
    """The shared local actor-critic; discrete iff there is no `log_std`."""

    def __init__(self, params: dict[str, np.ndarray]) -> None:
        self.actor = _layers(params, "actor")
        self.critic = _layers(params, "critic")
        self.actor_enc, self.critic_enc = _conv(params, "actor_enc"), _conv(params, "critic_enc")
        self.discrete = "log_std" not in params
        self.log_std = None if self.discrete else np.asarray(params["log_std"], dtype=np.float32)
        self.in_dim = self.actor[0][0].shape[1]
        if self.actor_enc is not None:  # the input the encoder takes, not what the MLP after it sees
            (h, w, c), _ = self.actor_enc
            probe = conv_encode(self.actor_enc, np.zeros((1, h * w * c), np.float32))
            self.in_dim += h * w * c - probe.shape[-1]

    def actor_out(self, x: np.ndarray) -> np.ndarray:
        """Logits (discrete) or Gaussian mean (continuous)."""
        return mlp_forward(self.actor, conv_encode(self.actor_enc, x), final_tanh=False)

    def value(self, x: np.ndarray) -> np.ndarray:
        return mlp_forward(self.critic, conv_encode(self.critic_enc, x), final_tanh=False)[..., 0]

    @property
    def std(self) -> np.ndarray:
        if self.log_std is None:
            raise AttributeError("a discrete policy has no std")
        return np.exp(self.log_std)


class NumpyCentralAgent:
    """`central_net=concat`: encoder + per-agent heads → message means; optional critic (rl mode)."""

    kind = "concat"

    def __init__(self, params: dict[str, np.ndarray]) -> None:
        self.encoder = _layers(params, "encoder")
        self.head_weight = np.asarray(params["head_weight"], dtype=np.float32)  # (N, H, M)
        self.head_bias = np.asarray(params["head_bias"], dtype=np.float32)  # (N, M)
        self.critic = _layers(params, "critic") if "critic.layers.0.weight" in params else None
        self.n_agents, hidden, self.msg_dim = self.head_weight.shape
        self.state_dim = self.encoder[0][0].shape[1]
        # All N heads as one (H, N*M) matmul, as CentralAgent.message_mean does: an einsum over
        # (N, H, M) costs more per call on the central server's acting path.
        self._heads = np.ascontiguousarray(self.head_weight.transpose(1, 0, 2).reshape(hidden, -1))
        self._heads_bias = self.head_bias.reshape(-1)

    def message_mean(self, state: np.ndarray) -> np.ndarray:
        h = mlp_forward(self.encoder, state, final_tanh=True)
        return np.tanh(h @ self._heads + self._heads_bias).reshape(*h.shape[:-1], self.n_agents, self.msg_dim)

    def values(self, state: np.ndarray) -> np.ndarray:
        if self.critic is None:
            raise AttributeError("this central agent has no critic (backprop mode)")
        return mlp_forward(self.critic, state, final_tanh=False)


def _attention(params: dict[str, np.ndarray], prefix: str) -> dict:
    """The weights of one `networks.AgentAttention` named `prefix`."""
    def f32(name: str) -> np.ndarray:
        return np.asarray(params[f"{prefix}.{name}"], dtype=np.float32)

    return {"encoder": _layers(params, f"{prefix}.encoder"), "query": f32("query.weight"), "key": f32("key.weight"),
            "value": f32("value.weight"), "out": (f32("out.weight"), f32("out.bias"))}


def attention_forward(net: dict, tokens: np.ndarray) -> np.ndarray:
    """Same maths as networks.AgentAttention: (..., N, T) → (..., N, out).
    e = enc(x); c_i = Σ_j softmax_j(q_i · k_j / √H) v_j; y = [e ⊕ c] Wo^T + bo."""
    lead, n = tokens.shape[:-2], tokens.shape[-2]
    # The per-agent layers on a 2-D (copies·agents, width) array: numpy's matmul of a stack of
    # matrices by one matrix does not go to BLAS as one product, and this is the server's hot path.
    e = mlp_forward(net["encoder"], tokens.reshape(-1, tokens.shape[-1]), final_tanh=True)
    h = e.shape[-1]
    qkv = e @ np.concatenate([net["query"], net["key"], net["value"]]).T  # (B·N, 3H) in one product
    q, k, v = (qkv[:, i * h:(i + 1) * h].reshape(-1, n, h) for i in range(3))
    scores = np.matmul(q, k.transpose(0, 2, 1)) / np.float32(np.sqrt(h))  # (B, N, N)
    w = np.exp(scores - scores.max(axis=-1, keepdims=True))
    w /= w.sum(axis=-1, keepdims=True)
    context = np.matmul(w, v).reshape(-1, h)
    weight, bias = net["out"]
    out = e @ weight[:, :h].T + context @ weight[:, h:].T + bias
    return out.reshape(*lead, n, -1)


class NumpySetCentralAgent:
    """`central_net=set` (`networks.SetCentralAgent`): the state cut into N tokens o_i ⊕ a_i(t-1),
    a shared per-agent encoder and attention across agents → message means; optional critic."""

    kind = "set"

    def __init__(self, params: dict[str, np.ndarray]) -> None:
        self.n_agents, self.obs_dim, self.act_dim = (int(v) for v in params["layout"])
        self.msg = _attention(params, "msg")
        self.critic = _attention(params, "critic") if "critic.encoder.layers.0.weight" in params else None
        self.msg_dim = self.msg["out"][0].shape[0]
        self.state_dim = self.n_agents * (self.obs_dim + self.act_dim)

    def tokens(self, state: np.ndarray) -> np.ndarray:
        state = np.asarray(state, dtype=np.float32)
        lead, n, d = state.shape[:-1], self.n_agents, self.obs_dim
        obs = state[..., : n * d].reshape(*lead, n, d)
        if self.act_dim == 0:
            return obs
        return np.concatenate([obs, state[..., n * d:].reshape(*lead, n, self.act_dim)], axis=-1)

    def message_mean(self, state: np.ndarray) -> np.ndarray:
        return np.tanh(attention_forward(self.msg, self.tokens(state)))

    def values(self, state: np.ndarray) -> np.ndarray:
        if self.critic is None:
            raise AttributeError("this central agent has no critic (backprop mode)")
        return attention_forward(self.critic, self.tokens(state))[..., 0]


def numpy_central(params: dict[str, np.ndarray]) -> NumpyCentralAgent | NumpySetCentralAgent:
    """The numpy central agent a weight dict holds: `layout` marks the set network, `head_weight`
    the concat one (docs/wire-format.md)."""
    if "layout" in params:
        return NumpySetCentralAgent(params)
    if "head_weight" in params:
        return NumpyCentralAgent(params)
    raise KeyError("central weights hold neither 'head_weight' (central_net=concat) nor 'layout' (central_net=set)")
