"""compile=true: each minibatch step of the PPO update as one torch.compile graph.

A minibatch step of these small networks is hundreds of tiny ops, so what pays is one graph for
all of it: the losses (`TeamLearner.losses`, the one definition the eager loop uses too), their
gradients by `torch.func.grad` (a traced backward, so no autograd engine, AccumulateGrad or `.grad`
bookkeeping at run time), then per network the grad-norm clip and torch's own Adam maths, in place
on the parameters and on the Adam state the `torch.optim.Adam` objects own (checkpoints
unchanged). The maths, the rows and their order are the eager `TeamLearner.learn`'s; only float
rounding differs (tests/test_learning_compile.py). The eager path never reads this module.

`compile_scope=epoch` traces a whole epoch into one graph instead (`_train_epoch`: the epoch's
shuffle gather, then every minibatch step in order), one call per epoch instead of one per
minibatch: the update runs ~15-25% faster, for a compile (dynamo's tracing, mostly) about as many
times longer as an epoch has minibatches.

A seed batch (`learning.seed_batch`) runs the same graphs over stacked (S, ...) parameters and Adam
state (`seeds=S`, `learn_stacked`): the gradient is `vmap(grad(...))` of the same losses, every
seed's slice of the minibatch its own rows, each seed's gradient clipped by its own norm, and the
Adam maths, elementwise, steps every slice as that seed's own optimiser would.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from hammer.learning.ppo import PPOUpdater, UpdateStats, clip_coefficient, minibatch_indices
from torch import nn
from torch.optim.adam import adam as functional_adam

if TYPE_CHECKING:
    from hammer.learning.ppo_update import Masks
    from hammer.learning.team import Team

Losses = Callable[..., tuple[torch.Tensor, "torch.Tensor | None", dict[str, torch.Tensor]]]
Minibatches = Callable[[dict[str, torch.Tensor], np.random.Generator], Iterator[dict[str, torch.Tensor]]]

# cpp_wrapper: the graph's glue code (buffer allocation, size asserts, kernel calls) in C++ instead
# of Python, which is a large part of a call at these sizes.
COMPILE_OPTIONS = {"cpp_wrapper": True}
SKIP_GUARDS = True
# Each compiled learner or team in a process adds one graph to the same code object (dynamo guards
# on the instance), and dynamo refuses a ninth by default (`recompile_limit` 8; with fullgraph, a
# hard error): a notebook or script that trains many runs in one process, or a test session, would
# fail at its ninth. `allow_many_graphs` raises the limit up to dynamo's accumulated one.
MANY_GRAPHS = 256


def allow_many_graphs() -> None:
    import torch._dynamo.config as dynamo_config

    dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, MANY_GRAPHS)
    dynamo_config.accumulated_recompile_limit = max(dynamo_config.accumulated_recompile_limit, MANY_GRAPHS)


class CompiledUpdate:
    """An update's epochs and minibatches, each minibatch step one call of a compiled `_train_step`.
    Built from what a step needs: the team's networks, the one losses function, the networks'
    optimisers (`PPOUpdater`s), the epochs and minibatches of an update. Shapes are static, so there
    is one graph per minibatch size, batch fields and `Masks`: one for cn."""

    def __init__(self, team: Team, losses: Losses, updaters: list[PPOUpdater], epochs: int,
                 minibatches: int, scope: str = "step", seeds: int | None = None) -> None:
        allow_many_graphs()
        self.seeds = seeds  # None: one run; S: the params and fields are stacked (S, ...) over seeds
        self.nets = _Nets(team, losses)
        self.updaters, self.epochs, self.minibatches = updaters, epochs, minibatches
        self.scope = scope  # RunConfig.compile_scope: one graph per minibatch step, or per epoch
        self.step = torch.compile(self._train_step, fullgraph=True, dynamic=False, options=COMPILE_OPTIONS)
        self.epoch = torch.compile(self._train_epoch, fullgraph=True, dynamic=False, options=COMPILE_OPTIONS)
        self.compiled: set[tuple] = set()

    def learn(self, minibatches: Minibatches, b: dict[str, torch.Tensor], masks: Masks,
              rng: np.random.Generator) -> dict[str, float]:
        """The update on the batch `b` (losses masked as `masks`), its minibatches from
        `minibatches(b, rng)` every epoch: the same rows in the same order as the eager loop, the
        same statistics."""
        params = [p for opt in self.updaters for p in opt.params]
        states = [adam_state(opt) for opt in self.updaters]
        exp_avgs, exp_avg_sqs, steps = ([t for s in states for t in s[i]] for i in range(3))
        keys = tuple(b)
        rows = len(b[keys[0]])
        if self.scope == "epoch":
            return self._learn_epochs(b, keys, rows, masks, rng, params, exp_avgs, exp_avg_sqs, steps)
        graphs = {(len(part), masks, keys) for part in np.array_split(np.arange(rows), self.minibatches)}
        total = UpdateStats()
        with skip_guards(graphs <= self.compiled):
            for epoch in range(self.epochs):
                last = epoch == self.epochs - 1
                for mb in minibatches(b, rng):
                    stats = self.step(params, exp_avgs, exp_avg_sqs, steps, keys, [mb[k] for k in keys], masks)
                    if last:
                        total.add(stats)
        self.compiled |= graphs
        return total.means()

    def learn_stacked(self, b: dict[str, torch.Tensor], masks: Masks, rngs: list[np.random.Generator]
                      ) -> dict[str, list[float]]:
        """`learn` for a seed batch: `b` holds every seed's batch one after the other ((S*R, ...)
        rows), seed s's minibatches come from `rngs[s]` as its solo run's would. Returns each
        statistic's means, one per seed."""
        params = [p for opt in self.updaters for p in opt.params]
        states = [adam_state(opt) for opt in self.updaters]
        exp_avgs, exp_avg_sqs, steps = ([t for s in states for t in s[i]] for i in range(3))
        keys = tuple(b)
        fields = [b[k] for k in keys]
        rows = len(fields[0]) // len(rngs)
        offsets = np.arange(len(rngs))[:, None] * rows
        total = UpdateStats()
        for epoch in range(self.epochs):
            parts = [minibatch_indices(rows, self.minibatches, rng) for rng in rngs]
            sizes = tuple(len(p) for p in parts[0])
            perm = torch.from_numpy((np.stack([np.concatenate(p) for p in parts]) + offsets).reshape(-1)).to(
                fields[0].device)
            if self.scope == "epoch":
                graph: tuple = ("epoch", sizes, masks, keys)
                with skip_guards(graph in self.compiled):
                    stats = self.epoch(params, exp_avgs, exp_avg_sqs, steps, keys, fields, perm, sizes, masks)
                self.compiled.add(graph)
            else:
                shuffled = [self._shuffle(f, perm) for f in fields]
                stats, start = [], 0
                for n in sizes:
                    graph = (n, masks, keys)
                    with skip_guards(graph in self.compiled):
                        stats.append(self.step(params, exp_avgs, exp_avg_sqs, steps, keys,
                                               [f.narrow(1, start, n) for f in shuffled], masks))
                    self.compiled.add(graph)
                    start += n
            if epoch == self.epochs - 1:
                for st in stats:
                    total.add(st)
        return total.means()

    def _shuffle(self, field: torch.Tensor, perm: torch.Tensor) -> torch.Tensor:
        """`field`'s rows in the order `perm`; stacked over seeds: (S*R, ...) rows to (S, R, ...)."""
        out = field.index_select(0, perm)
        return out if self.seeds is None else out.reshape(self.seeds, len(out) // self.seeds, *out.shape[1:])

    def _learn_epochs(self, b: dict[str, torch.Tensor], keys: tuple[str, ...], rows: int, masks: Masks,
                      rng: np.random.Generator, params: list[torch.Tensor], exp_avgs: list[torch.Tensor],
                      exp_avg_sqs: list[torch.Tensor], steps: list[torch.Tensor]) -> dict[str, float]:
        """`learn` with one call of the compiled `_train_epoch` per epoch: the rows of each
        minibatch and their order are the eager loop's (`minibatch_indices` on the same stream)."""
        fields = [b[k] for k in keys]
        total = UpdateStats()
        for epoch in range(self.epochs):
            parts = minibatch_indices(rows, self.minibatches, rng)
            sizes = tuple(len(p) for p in parts)
            graph = ("epoch", sizes, masks, keys)
            with skip_guards(graph in self.compiled):
                stats = self.epoch(params, exp_avgs, exp_avg_sqs, steps, keys, fields,
                                   torch.from_numpy(np.concatenate(parts)).to(fields[0].device), sizes, masks)
            self.compiled.add(graph)
            if epoch == self.epochs - 1:
                for st in stats:
                    total.add(st)
        return total.means()

    def _train_epoch(self, params: list[torch.Tensor], exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
                     steps: list[torch.Tensor], keys: tuple[str, ...], fields: list[torch.Tensor],
                     perm: torch.Tensor, sizes: tuple[int, ...], masks: Masks) -> list[dict[str, torch.Tensor]]:
        """One epoch, written to be traced into one graph: every field gathered in the epoch's
        shuffled row order `perm`, then `_train_step` on each consecutive slice of `sizes` rows, in
        order (each step sees the parameters the previous one stepped). Returns each step's
        statistics."""
        shuffled = [self._shuffle(f, perm) for f in fields]
        dim = 0 if self.seeds is None else 1
        out, start = [], 0
        for n in sizes:
            out.append(self._train_step(params, exp_avgs, exp_avg_sqs, steps, keys,
                                        [f.narrow(dim, start, n) for f in shuffled], masks))
            start += n
        return out

    def _train_step(self, params: list[torch.Tensor], exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
                    steps: list[torch.Tensor], keys: tuple[str, ...], fields: list[torch.Tensor],
                    masks: Masks) -> dict[str, torch.Tensor]:
        """One whole minibatch step, written to be traced into one graph: the losses, their
        gradients, then per network `traced_clip_and_step`. Returns the statistics by name on every
        step: one graph instead of one with and one without them (half the compile time) for a few
        reductions per step."""
        names = self.nets.names

        def total_loss(ps: tuple[torch.Tensor, ...], fs: list[torch.Tensor]
                       ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
            r = dict(zip(keys, fs, strict=True))
            local, central, stats = torch.func.functional_call(self.nets, dict(zip(names, ps, strict=True)),
                                                               (r, masks, True))
            return (local if central is None else local + central), stats

        grad = torch.func.grad(total_loss, has_aux=True)
        if self.seeds is not None:  # each seed's gradient on its own slice of the minibatch
            grad = torch.func.vmap(grad)
        grads, stats = grad(tuple(p.detach() for p in params), fields)
        lo = 0
        with torch.no_grad():
            for opt in self.updaters:
                part = slice(lo, lo + len(opt.params))
                stats[f"{opt.name}/grad_norm"] = traced_clip_and_step(opt, params[part], list(grads[part]),
                                                                      exp_avgs[part], exp_avg_sqs[part], steps[part],
                                                                      stacked=self.seeds is not None)
                lo = part.stop
        return stats


class _Nets(nn.Module):
    """The team's networks as one module whose forward is the PPO losses, so that
    `torch.func.functional_call` can swap in the tensors `torch.func.grad` differentiates."""

    def __init__(self, team: Team, losses: Losses) -> None:
        super().__init__()
        self.local = team.local
        if team.central is not None:
            self.central = team.central
        self.losses = losses
        self.names = [n for n, _ in self.named_parameters()]

    def forward(self, *args: Any) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, torch.Tensor]]:
        return self.losses(*args)


def adam_state(opt: PPOUpdater) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """(exp_avgs, exp_avg_sqs, steps) of every parameter of `opt`, created as Adam's first step
    creates them (zeros, a float32 0-d step) where missing. The compiled step steps these tensors
    in place, so the `torch.optim.Adam` object keeps owning the state (checkpoints unchanged)."""
    optimizer = opt.optimizer
    group = optimizer.param_groups[0]
    for p in opt.params:
        if p not in optimizer.state:
            optimizer.state[p] = {"step": torch.zeros((), dtype=torch.float32, device=p.device),
                                  "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                  "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
    if len(optimizer.param_groups) != 1 or group["amsgrad"] or group["weight_decay"] or group["maximize"]:
        raise ValueError("compile=true supports plain Adam only (no amsgrad, weight decay, maximize)")
    states = [optimizer.state[p] for p in opt.params]
    return [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states], [s["step"] for s in states]


def traced_clip_and_step(opt: PPOUpdater, params: list[torch.Tensor], grads: list[torch.Tensor],
                         exp_avgs: list[torch.Tensor], exp_avg_sqs: list[torch.Tensor],
                         steps: list[torch.Tensor], stacked: bool = False) -> torch.Tensor:
    """`ppo.clip_and_step` written to be traced: the same clip rule (`clip_by_total_norm`), then
    torch's own Adam maths in its foreach/capturable form (what torch traces when it compiles an
    Adam optimiser), stepping the state from `adam_state` in place. Returns the norm before
    clipping (`stacked`: every tensor (S, ...), each seed's slice clipped by its own norm; the (S,)
    norms). Not the fused kernel `ppo.clip_and_step` calls: it mutates the Adam state in a way
    torch.compile cannot functionalize (an internal assert in torch 2.13), so a graph holds torch's
    reference maths of the same step."""
    group = opt.optimizer.param_groups[0]
    grads, norm = clip_by_total_norm(grads, opt.max_grad_norm, stacked)
    beta1, beta2 = group["betas"]
    # capturable: the step count stays a tensor inside the graph (torch allows it on CPU only
    # while compiling; run eagerly, e.g. under set_stance("force_eager"), the plain form runs).
    functional_adam(params, grads, exp_avgs, exp_avg_sqs, [], steps, foreach=True,
                    capturable=torch.compiler.is_compiling(), amsgrad=False, beta1=beta1, beta2=beta2,
                    lr=group["lr"], weight_decay=0.0, eps=group["eps"], maximize=False)
    return norm


def clip_by_total_norm(grads: list[torch.Tensor], max_norm: float, stacked: bool = False
                       ) -> tuple[list[torch.Tensor], torch.Tensor]:
    """`ppo.clip_grad_norm`'s rule (scale by min(1, max/(norm + 1e-6))) for a graph; returns the
    clipped gradients and the norm before clipping (`stacked`: per seed, as `ppo.clip_grad_norm`).

    The norm is a sum of squares instead of `_foreach_norm`: inductor fuses the sums into its own
    kernels, while `_foreach_norm` stays a loop of one library call per tensor inside the graph.
    """
    if not stacked:
        norm = torch.stack([g.pow(2).sum() for g in grads]).sum().sqrt()
        coef = clip_coefficient(norm, max_norm)
        return [g * coef for g in grads], norm
    norm = torch.stack([g.pow(2).flatten(1).sum(1) for g in grads], dim=1).sum(1).sqrt()
    coef = clip_coefficient(norm, max_norm)
    return [g * coef.reshape(-1, *([1] * (g.dim() - 1))) for g in grads], norm


def skip_guards(seen: bool) -> contextlib.AbstractContextManager:
    """Once every step graph an update needs exists (or the acting graph for these input shapes,
    `learning.fused_acting`), dynamo need not re-check their guards (every
    tensor argument and the config) on every call, a noticeable part of a compiled update. Under
    this stance dynamo would run a stale graph if a Python value the trace read had changed, so
    the key holds every such value that can change between calls (minibatch size, `Masks`, the
    batch fields); the rest (config, learning rates, network shapes) is fixed for a learner's life."""
    if seen and SKIP_GUARDS:
        return torch.compiler.set_stance(skip_guard_eval_unsafe=True)
    return contextlib.nullcontext()
