"""Many seeds of one setting trained as one computation (`hammer train --seeds 0-7`).

Small networks spend their time on per-call overhead, not arithmetic, so S runs that differ only
in seed are cheaper as one batched computation than as S processes. Each seed is still an
ordinary `Trainer` (its own env copies, acting streams, rollout buffer, run directory, counters,
checkpoints), and its networks' parameters are views into stacked (S, ...) tensors:

  acting     one `torch.func.vmap` forward over the stacked parameters per vector step (central
             messages and values, local logits and values), then each seed samples from its own
             streams (`Team.sample_local`, `CentralActing.messages`) and steps its own env
  update     each seed's own GAE batch (`TeamLearner.batch`) and minibatch order (its stream),
             then per minibatch one `vmap(grad(TeamLearner.losses))` (the one loss definition,
             through `functional_call`), each seed's grad norm clipped on its own
             (`ppo.clip_grad_norm`, stacked), and one fused Adam step over the stacked tensors,
             which is per-slice the same elementwise maths as each seed's own Adam

Advantage normalisation and every loss mean are per seed because the losses run per slice under
vmap. Before a checkpoint the stacked Adam state is copied into each seed's own optimiser, so a
checkpoint is exactly a solo run's and `hammer train --resume` continues any seed alone.
With compile=true a seed batch runs the solo compiled run's graphs over the stacked parameters:
acting is `FusedActing`'s graph under vmap (each seed's draws from its own streams first, then one
call for every seed's networks and sampling), the update `CompiledUpdate` with `seeds=S`, one graph
per minibatch step or, `compile_scope=epoch`, per epoch (`CompiledUpdate.learn_stacked`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from hammer.learning.compiled_update import COMPILE_OPTIONS, CompiledUpdate, skip_guards
from hammer.learning.config import ConfigError, RunConfig, config_changes
from hammer.learning.fused_acting import FusedActing
from hammer.learning.ppo import PPOUpdater, UpdateStats, clip_and_step, minibatch_indices, minibatch_slices
from hammer.learning.ppo_update import Masks
from hammer.learning.rundir import RunDir
from hammer.learning.sampling import MINIBATCH_STREAM, env_reset_seed, stream
from hammer.learning.trainer import Progress, Trainer
from hammer.protocol.ranges import parse_indices
from torch import nn
from torch.func import functional_call, grad, vmap

# Fields a seed batch may differ in: the seed itself and where the run is written.
PER_SEED_FIELDS = frozenset({"seed", "out"})


def parse_seeds(text: str) -> list[int]:
    """`0-7`, `0,3,5` or `0-3,8` -> a sorted list of distinct seeds."""
    try:
        return parse_indices(text, "--seeds", what="seed")
    except ValueError as e:
        raise ConfigError(str(e)) from None


def check_batchable(cfgs: list[RunConfig]) -> None:
    """Seeds batch together only if their configs differ in nothing but the seed (and out)."""
    ref = cfgs[0].model_dump(mode="json")
    for cfg in cfgs[1:]:
        diff = config_changes(cfg.model_dump(mode="json"), ref, ignore=PER_SEED_FIELDS)
        if diff:
            field = next(iter(diff))
            raise ConfigError(f"seed batch: '{field}' differs between seeds; fix: batch only runs that differ "
                              "in seed")
    if len({c.seed for c in cfgs}) != len(cfgs):
        raise ConfigError("seed batch: a seed appears twice; fix: list each seed once")


class _Call(nn.Module):
    """One seed's networks as a module whose forward runs any function of them, so that
    `functional_call` can swap in a slice of the stacked parameters (vmap) for the call."""

    def __init__(self, trainer: Trainer) -> None:
        super().__init__()
        self.local = trainer.team.local
        if trainer.team.central is not None:
            self.central = trainer.team.central

    def forward(self, fn: Callable[..., Any], *args: Any) -> Any:
        return fn(*args)


class SeedBatch:
    """S `Trainer`s whose networks live in stacked tensors; `run` trains them all to budget."""

    def __init__(self, cfgs: list[RunConfig], run_dirs: list[RunDir], tensorboard: bool = True,
                 on_progress: Callable[[Progress], None] | None = None) -> None:
        check_batchable(cfgs)
        self.trainers = [Trainer(cfg, rd, tensorboard=tensorboard, on_progress=on_progress if i == 0 else None)
                         for i, (cfg, rd) in enumerate(zip(cfgs, run_dirs, strict=True))]
        self.n_seeds = len(self.trainers)
        self.cfg = cfgs[0]
        lead = self.trainers[0]
        self.call = _Call(lead)
        self.names = [n for n, _ in self.call.named_parameters()]
        per_seed = [dict(_Call(tr).named_parameters()) for tr in self.trainers]
        self.params = {n: torch.stack([p[n].detach() for p in per_seed]).contiguous() for n in self.names}
        for s, p in enumerate(per_seed):  # each seed's parameters become views of its slice
            for n in self.names:
                p[n].data = self.params[n][s]
        # one stacked Adam per network, in the order of each seed's own updaters
        self.groups: list[tuple[list[str], PPOUpdater]] = []
        for prefix, upd in (("local.", lead.learner.local_opt), ("central.", lead.learner.central_opt)):
            if upd is None:
                continue
            names = [n for n in self.names if n.startswith(prefix)]
            self.groups.append((names, PPOUpdater([self.params[n] for n in names], upd.optimizer.param_groups[0]["lr"],
                                                  upd.max_grad_norm, upd.name)))
        # compile=true: the solo compiled run's acting graph and update over the stacked parameters
        self.compiled: CompiledUpdate | None = None
        if self.cfg.compile:
            fused = lead.team.fused
            assert fused is not None
            self._fused, self._fused_seen = fused, set()
            self._fused_graph = torch.compile(self._fused_act, fullgraph=True, dynamic=False, options=COMPILE_OPTIONS)
            self.compiled = CompiledUpdate(lead.team, lead.learner.losses, [u for _, u in self.groups], self.cfg.epochs,
                                           self.cfg.minibatches, self.cfg.compile_scope, seeds=self.n_seeds)

    # ----- optimiser state <-> each seed's own optimiser ----------------------------------------
    def _opt_to_seeds(self) -> None:
        for g, (names, stacked) in enumerate(self.groups):
            opt = stacked.optimizer
            for s, tr in enumerate(self.trainers):
                upd = tr.learner.updaters[g]
                for n, p in zip(names, upd.params, strict=True):
                    st = opt.state.get(self.params[n])
                    if st:
                        upd.optimizer.state[p] = {"step": st["step"].clone(), "exp_avg": st["exp_avg"][s].clone(),
                                                  "exp_avg_sq": st["exp_avg_sq"][s].clone()}

    def _opt_from_seeds(self) -> None:
        for g, (names, stacked) in enumerate(self.groups):
            opt = stacked.optimizer
            for i, n in enumerate(names):
                states = [tr.learner.updaters[g].optimizer.state.get(tr.learner.updaters[g].params[i])
                          for tr in self.trainers]
                if not all(states):
                    continue
                steps = {float(st["step"]) for st in states}
                if len(steps) != 1:
                    raise ConfigError("seed batch resume: the seeds' optimisers are at different steps; fix: "
                                      "resume each seed alone with `hammer train --resume`")
                opt.state[self.params[n]] = {
                    "step": states[0]["step"].clone(),
                    "exp_avg": torch.stack([st["exp_avg"] for st in states]).contiguous(),
                    "exp_avg_sq": torch.stack([st["exp_avg_sq"] for st in states]).contiguous()}

    def restore(self) -> None:
        """Load every seed's latest checkpoint (they must be at the same update)."""
        for tr in self.trainers:
            tr.restore()
        if len({tr.update for tr in self.trainers}) != 1:
            raise ConfigError("seed batch resume: the seeds' checkpoints are at different updates; fix: resume "
                              "each seed alone with `hammer train --resume`")
        self._opt_from_seeds()

    # ----- batched forward passes ---------------------------------------------------------------
    @torch.no_grad()
    def _act(self, live: list[int], obs: list[np.ndarray], prev: list[np.ndarray], t: int) -> None:
        """One vector step for the live seeds: batched forward, per-seed sampling, env step, record."""
        lead = self.trainers[0].team
        trs = [self.trainers[s] for s in live]
        states = [tr.team.global_state(obs[s], prev[s], tr.vector_step) for s, tr in zip(live, trs, strict=True)]
        if self.compiled is not None:
            self._act_fused(live, trs, obs, prev, states, t)
            return
        all_states = self._stack_all(live, states)
        mean = values = None
        if lead.central is not None:
            mean, values = self._central_forward(self.params, all_states)
        outs = []
        if mean is not None:  # one copy to the host for every seed's sampling
            mean, values = lead.host(mean), (None if values is None else lead.host(values))
        for i, (s, tr) in enumerate(zip(live, trs, strict=True)):
            mean_s = None if mean is None else (lambda _st, s=s: mean[s])
            values_s = None if values is None else (lambda _st, s=s: values[s])
            outs.append(tr.team.acting.messages(states[i], tr.streams, tr.cfg.msg_dropout, mean_s, values_s))
        sent = self._stack_all(live, [c.sent for c in outs])
        all_obs = self._stack_all(live, [self.trainers[s].team.local_view(obs[s]) for s in live])  # what locals see

        out, value = self._local_forward(self.params, all_obs, sent)
        out, value = lead.host(out), lead.host(value)
        for i, (s, tr) in enumerate(zip(live, trs, strict=True)):
            action, logp, v = tr.team.sample_local(out[s], value[s], tr.streams)
            st = tr.env.step(tr.team.env_action(action))
            obs[s], prev[s], spent = tr._record(t, obs[s], prev[s], states[i], outs[i], action, logp, v, st)
            if spent:
                self._done[s] = True

    def _act_fused(self, live: list[int], trs: list[Trainer], obs: list[np.ndarray], prev: list[np.ndarray],
                   states: list[np.ndarray], t: int) -> None:
        """`_act` for compile=true: each seed's draws from its own streams (`FusedActing.inputs`),
        then one call of the acting graph for every seed, then each seed steps its env and records."""
        inputs = [tr.team.fused.inputs(obs[s], states[i], tr.streams, tr.cfg.msg_dropout)
                  for i, (s, tr) in enumerate(zip(live, trs, strict=True))]
        args = [self._stack_all(live, [np.ascontiguousarray(inp[j]) for inp in inputs]) for j in range(len(inputs[0]))]
        key = tuple((a.shape, a.dtype) for a in args)
        with skip_guards(key in self._fused_seen):
            out = self._fused_graph(self.params, *args)
        self._fused_seen.add(key)
        lead = self.trainers[0].team
        out = [lead.host(o) for o in out]
        for i, (s, tr) in enumerate(zip(live, trs, strict=True)):
            c, action, logp, v = FusedActing.outputs([o[s] for o in out], inputs[i][3])
            st = tr.env.step(tr.team.env_action(action))
            obs[s], prev[s], spent = tr._record(t, obs[s], prev[s], states[i], c, action, logp, v, st)
            if spent:
                self._done[s] = True

    def _fused_act(self, params: dict[str, torch.Tensor], *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """`FusedActing._act` for every seed, each on its slice of the stacked parameters."""
        def one(p: dict[str, torch.Tensor], *a: torch.Tensor) -> tuple[torch.Tensor, ...]:
            return functional_call(self.call, p, (self._fused._act, *a))

        return vmap(one)(params, *args)

    def _central_forward(self, params: dict[str, torch.Tensor], states: torch.Tensor
                         ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(S, K, N, M) message means and (rl) (S, K, N) central values for (S, K, state) states."""
        central = self.trainers[0].team.central
        rl = self.trainers[0].team.central_rl

        def one(p: dict[str, torch.Tensor], st: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            def fwd(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                mean = central.message_mean(x)
                return mean, (central.values(x) if rl else mean.new_zeros(()))
            return functional_call(self.call, p, (fwd, st))

        mean, values = vmap(one)(params, states)
        return mean, (values if rl else None)

    def _local_forward(self, params: dict[str, torch.Tensor], obs: torch.Tensor, msg: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """(S, K, N, A) actor outputs and (S, K, N) values of the local policy."""
        team = self.trainers[0].team

        def one(p: dict[str, torch.Tensor], o: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            def fwd(o: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                x = team.local_input(o, m)
                return team.local.actor_out(x), team.local.value(x)
            return functional_call(self.call, p, (fwd, o, m))

        return vmap(one)(params, obs, msg)

    def _stack_all(self, live: list[int], arrays: list[np.ndarray]) -> torch.Tensor:
        """(S, ...) tensor of the live seeds' arrays; finished seeds' slices are zeros."""
        team = self.trainers[0].team
        if len(live) == self.n_seeds:
            return team.tensor(np.stack(arrays))
        full = np.zeros((self.n_seeds, *arrays[0].shape), dtype=arrays[0].dtype)
        full[live] = np.stack(arrays)
        return team.tensor(full)

    # ----- the update ---------------------------------------------------------------------------
    def _learn(self, obs: list[np.ndarray], prev: list[np.ndarray], update: int) -> list[dict[str, float]]:
        """Every seed's PPO update as one batched computation (see the module docstring)."""
        cfg, lead = self.cfg, self.trainers[0].learner
        batches = [tr.learner.batch(obs[s], prev[s], tr.vector_step) for s, tr in enumerate(self.trainers)]
        bs = [b for b, _ in batches]
        # one graph for every seed: a masking op is skipped only where no seed needs it
        masks = Masks(all(m.full for _, m in batches), all(m.c_full for _, m in batches))
        rows = lead.buf.t * lead.buf.k
        big = {k: torch.cat([b[k] for b in bs]) for k in bs[0]}  # (S*R, ...)
        rngs = [stream(tr.cfg.seed, MINIBATCH_STREAM, update) for tr in self.trainers]
        if self.compiled is not None:
            means = self.compiled.learn_stacked(big, masks, rngs)
            return [{k: v[s] for k, v in means.items()} for s in range(self.n_seeds)]
        offsets = np.arange(self.n_seeds)[:, None] * rows
        total = UpdateStats()
        for epoch in range(cfg.epochs):
            last = epoch == cfg.epochs - 1
            parts = [minibatch_indices(rows, cfg.minibatches, rng) for rng in rngs]
            perm = lead.team.tensor((np.stack([np.concatenate(p) for p in parts]) + offsets).reshape(-1))
            shuffled = {k: v.index_select(0, perm).reshape(self.n_seeds, rows, *v.shape[1:]) for k, v in big.items()}
            for mb in minibatch_slices(shuffled, [len(p) for p in parts[0]], dim=1):
                stats = self._step(mb, masks, last)
                if last:
                    total.add(stats)
        means = total.means()  # each statistic (S,): one value per seed
        return [{k: v[s] for k, v in means.items()} for s in range(self.n_seeds)]

    def _grads(self, params: dict[str, torch.Tensor], mb: dict[str, torch.Tensor], masks: Masks, with_stats: bool
               ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Every seed's gradient of `TeamLearner.losses` on its slice of the minibatch, and the
        statistics (each (S,))."""
        learner = self.trainers[0].learner

        def loss(p: dict[str, torch.Tensor], r: dict[str, torch.Tensor]
                 ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
            local, central, stats = functional_call(self.call, p, (learner.losses, r, masks, with_stats))
            return (local if central is None else local + central), stats

        return vmap(grad(loss, has_aux=True))(params, mb)

    def _step(self, mb: dict[str, torch.Tensor], masks: Masks, with_stats: bool) -> dict[str, torch.Tensor]:
        """One minibatch step for every seed; returns the statistics and grad norms by name, each (S,)."""
        grads, stats = self._grads(self.params, mb, masks, with_stats)
        norms = {}
        with torch.no_grad():
            for names, upd in self.groups:
                # the fused Adam kernel reads a gradient in its parameter's memory layout: vmap can
                # return a permuted one (the central heads), so lay every gradient out densely
                gs = [grads[n].contiguous() for n in names]
                ps = [self.params[n] for n in names]
                for p, g in zip(ps, gs, strict=True):
                    p.grad = g
                norms[f"{names[0].split('.', 1)[0]}/grad_norm"] = clip_and_step(upd.optimizer, ps, gs, upd.max_grad_norm,
                                                                                   stacked=True)
        return {**stats, **norms}

    # ----- the loop -----------------------------------------------------------------------------
    def run(self) -> list[dict[str, Any]]:
        """Train every seed to its budget; returns the seeds' summaries (in seed order)."""
        cfg = self.cfg
        starts = [tr.start() for tr in self.trainers]
        resumed = starts[0]
        self._done = [tr.episodes >= tr.cfg.episodes for tr in self.trainers]
        summaries: list[dict[str, Any] | None] = [None] * self.n_seeds
        obs: list[Any] = [None] * self.n_seeds
        prev: list[Any] = [None] * self.n_seeds
        finished: set[int] = set()
        while True:
            for s in range(self.n_seeds):
                if self._done[s] and s not in finished:
                    summaries[s] = self.trainers[s].finish()
                    finished.add(s)
            live = [s for s in range(self.n_seeds) if not self._done[s]]
            if not live:
                break
            update = self.trainers[live[0]].update
            if update % cfg.checkpoint_every == 0:
                if not resumed:
                    self._opt_to_seeds()
                for s in live:
                    tr = self.trainers[s]
                    if not resumed:
                        tr.checkpoint()
                    obs[s], _ = tr.env.reset(env_reset_seed(tr.cfg.seed, update))
                    prev[s] = tr.team.zero_prev_actions(cfg.num_envs)
                resumed = False
            for s in live:
                self.trainers[s].writer.begin()
            for t in range(cfg.rollout_steps):
                self._act(live, obs, prev, t)
                live = [s for s in live if not self._done[s]]
                if not live:
                    break
            if not live:
                continue
            # a finished seed's slices keep training on its last rollout (cheaper than restacking);
            # it was exported when it finished and is never read again
            stats = self._learn(obs, prev, update)
            for s in live:
                self.trainers[s].log_update(stats[s])
        return summaries  # type: ignore[return-value]

    def close(self) -> None:
        for tr in self.trainers:
            tr.env.close()


def train_seeds(cfgs: list[RunConfig], run_dirs: list[RunDir], resume: bool = False, tensorboard: bool = True,
                on_progress: Callable[[Progress], None] | None = None) -> list[dict[str, Any]]:
    """Run (or resume) S seeds of one setting as one batched computation; returns the summaries."""
    batch = SeedBatch(cfgs, run_dirs, tensorboard=tensorboard, on_progress=on_progress)
    try:
        if resume:
            batch.restore()
        return batch.run()
    finally:
        batch.close()
