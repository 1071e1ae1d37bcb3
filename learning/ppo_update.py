"""The learning side of a HAMMER team, shared by the in-process trainer and the learner process.

`TeamLearner` owns what an update needs: the team's networks, one optimiser per network, the
rollout buffer and the PPO maths (GAE, clipped losses, minibatch epochs). The in-process `Trainer`
fills its buffer by acting itself; the distributed learner (`learner.worker`) fills it from
the env host's experience chunks. Both then call `learn`, so the update is written once.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np
import torch
from hammer.envs.base import EnvSpec
from hammer.learning.compiled_update import CompiledUpdate
from hammer.learning.config import RunConfig
from hammer.learning.networks import gaussian_logp
from hammer.learning.ppo import (
    PPOUpdater,
    UpdateStats,
    clipped_surrogate,
    gae,
    masked_mean,
    minibatch_indices,
    minibatch_slices,
    next_values,
    normalize_advantages,
    value_loss,
)
from hammer.learning.precision import update_autocast
from hammer.learning.rollout import RolloutBuffer
from hammer.learning.rundir import optimizer_from_tensors, optimizer_to_tensors
from hammer.learning.sampling import MINIBATCH_STREAM, stream
from hammer.learning.team import Team


class Masks(NamedTuple):
    """Which masking ops a batch's losses need: `full`, every agent present in every row (no agent
    mask); `c_full`, also no message dropped (no central mask). Decided per batch by `batch()` and
    passed to `losses`; a compiled step is one graph per value."""

    full: bool = False
    c_full: bool = False


MASKED = Masks()  # every masking op: right for any batch, the default where none was decided


class TeamLearner:
    def __init__(self, cfg: RunConfig, spec: EnvSpec) -> None:
        torch.set_num_threads(cfg.torch_threads)
        self.cfg = cfg
        self.team = Team(cfg, spec)
        self.local_opt = PPOUpdater(self.team.local.parameters(), cfg.lr_local, cfg.max_grad_norm, "local")
        self.central_opt = (PPOUpdater(self.team.central.parameters(), cfg.lr_central, cfg.max_grad_norm, "central")
                            if self.team.central is not None else None)
        self.buf = RolloutBuffer(cfg.rollout_steps, cfg.num_envs, cfg.n_agents, spec.obs_dim,
                                 self.team.state_dim, self.team.msg_dim, spec.action_shape, spec.discrete)
        self._msg_log_std = torch.full((max(self.team.msg_dim, 1),), math.log(cfg.msg_std),
                                       device=self.team.device)[: self.team.msg_dim]
        self.updaters = [opt for opt in (self.local_opt, self.central_opt) if opt is not None]
        self.compiled_update = (CompiledUpdate(self.team, self.losses, self.updaters, cfg.epochs, cfg.minibatches,
                                              cfg.compile_scope)
                                if cfg.compile else None)

    # ----- state (checkpoints) -------------------------------------------------------------------
    def state_tensors(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Network and optimiser state as flat tensors + JSON metadata (no pickle)."""
        tensors = {f"local/{k}": v for k, v in self.team.local.state_dict().items()}
        t, opt_meta = optimizer_to_tensors(self.local_opt.optimizer, "opt_local")
        tensors.update(t)
        meta: dict[str, Any] = {"opt_local": opt_meta}
        if self.team.central is not None:
            tensors.update({f"central/{k}": v for k, v in self.team.central.state_dict().items()})
            t, meta["opt_central"] = optimizer_to_tensors(self.central_opt.optimizer, "opt_central")
            tensors.update(t)
        return tensors, meta

    def load_state(self, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
        self.team.local.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("local/")})
        optimizer_from_tensors(self.local_opt.optimizer, "opt_local", tensors, meta["opt_local"])
        if self.team.central is not None:
            self.team.central.load_state_dict({k[8:]: v for k, v in tensors.items() if k.startswith("central/")})
            optimizer_from_tensors(self.central_opt.optimizer, "opt_central", tensors, meta["opt_central"])
        # The config decides the learning rate, not the checkpoint (which restores its own): a run
        # resumed with a changed lr must train with it. Also: checkpoints from before the fused Adam.
        for opt, lr in ((self.local_opt, self.cfg.lr_local), (self.central_opt, self.cfg.lr_central)):
            if opt is not None:
                for group in opt.optimizer.param_groups:
                    group.update(fused=True, foreach=None, lr=lr)

    def batch(self, obs: np.ndarray, prev: np.ndarray, step: int | None = None) -> tuple[dict[str, torch.Tensor], Masks]:
        """Advantages/returns for the filled buffer, flattened to (T*K, N, ...) tensors, and the
        masking the losses need for them. `obs`, `prev`: the state after the rollout, vector `step`."""
        cfg, team, buf = self.cfg, self.team, self.buf
        last_state = team.global_state(obs, prev, step)
        last_v = team.local_values(obs, team.bootstrap_messages(last_state))
        dones = buf.terminated | buf.truncated
        nv = next_values(buf.values, last_v, buf.final_values, buf.reset)
        adv, ret = gae(buf.rewards, buf.values, nv, buf.terminated, dones, cfg.gamma, cfg.gae_lambda, buf.active)

        def flat(a: np.ndarray) -> torch.Tensor:
            return team.tensor(np.ascontiguousarray(a.reshape(buf.t * buf.k, *a.shape[2:])))

        b = {"obs": flat(team.local_view(buf.obs)), "state": flat(buf.state), "msg": flat(buf.msg), "keep": flat(buf.keep),
             "act": flat(buf.actions), "logp": flat(buf.logp), "adv": flat(adv), "ret": flat(ret),
             "mask": flat(buf.active.astype(np.float32))}
        # All agents present (and no message dropped): the losses skip their masking ops.
        full = bool(buf.active.all())
        masks = Masks(full, full and bool(buf.keep.all()))
        if team.central_rl:
            c_nv = next_values(buf.c_values, team.central_values(last_state), buf.c_final_values, buf.reset)
            c_adv, c_ret = gae(buf.rewards, buf.c_values, c_nv, buf.terminated, dones, cfg.gamma,
                               cfg.gae_lambda, buf.active)
            b.update(raw=flat(buf.msg_raw), c_logp=flat(buf.c_logp), c_adv=flat(c_adv), c_ret=flat(c_ret),
                     c_mask=b["mask"] * b["keep"])
        return b, masks

    def losses(self, r: dict[str, torch.Tensor], masks: Masks = MASKED, with_stats: bool = True
               ) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, torch.Tensor]]:
        """`_losses` in the run's precision (`learning.precision`): under bfloat16 autocast for bf16,
        so the eager, compiled and seed-batched updates, which all call this, run the same maths."""
        if self.cfg.precision == "fp32":
            return self._losses(r, masks, with_stats)
        with update_autocast(self.cfg.precision, self.team.device):
            return self._losses(r, masks, with_stats)

    def _losses(self, r: dict[str, torch.Tensor], masks: Masks = MASKED, with_stats: bool = True
                ) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, torch.Tensor]]:
        """(local PPO loss, central PPO loss or None, statistics) on the minibatch `r` of a batch
        whose masking is `masks`; the statistics are 0-d tensors by name (none unless `with_stats`).

        backprop: the messages are recomputed from the stored global states with grad, so the
        local actor loss flows through u_i into the central heads and encoder (DIAL-style); the
        local critic sees detached messages. rl: the local loss sees the stored (sent) messages,
        the central loss is its own PPO on the Gaussian messages; the two graphs never meet.
        """
        cfg, team = self.cfg, self.team
        m = None if masks.full else r["mask"]
        backprop = team.wiring.central_backprop
        if backprop:
            msg = team.central.message_mean(r["state"])
            if cfg.msg_dropout > 0:
                msg = msg * r["keep"].unsqueeze(-1)
        else:
            msg = r["msg"]
        x = team.local_input(r["obs"], msg)
        new_logp, entropy = team.local.logp_entropy(x, r["act"])
        new_v = team.local.value(team.local_input(r["obs"], msg.detach()) if backprop else x)
        a = normalize_advantages(r["adv"], m) if cfg.norm_adv else r["adv"]
        pg, kl, clipfrac = clipped_surrogate(new_logp, r["logp"], a, cfg.clip, m, with_stats)
        vl = value_loss(new_v, r["ret"], m)
        ent = masked_mean(entropy, m)
        local_loss = pg - cfg.ent_coef * ent + cfg.vf_coef * vl
        stats = ({"local/policy_loss": pg.detach(), "local/value_loss": vl.detach(), "local/entropy": ent.detach(),
                  "local/approx_kl": kl, "local/clipfrac": clipfrac} if with_stats else {})
        central_loss = None
        if team.central_rl:
            cm = None if masks.c_full else r["c_mask"]
            mean = team.central.message_mean(r["state"])
            c_logp = gaussian_logp(r["raw"], mean, self._msg_log_std)
            ca = normalize_advantages(r["c_adv"], cm) if cfg.norm_adv else r["c_adv"]
            cpg, ckl, _ = clipped_surrogate(c_logp, r["c_logp"], ca, cfg.clip, cm, with_stats)
            cvl = value_loss(team.central.values(r["state"]), r["c_ret"], cm)
            central_loss = cpg + cfg.vf_coef * cvl
            if with_stats:
                stats.update({"central/policy_loss": cpg.detach(), "central/value_loss": cvl.detach(),
                              "central/approx_kl": ckl})
        return local_loss, central_loss, stats

    def epoch_minibatches(self, b: dict[str, torch.Tensor], rng: np.random.Generator
                          ) -> Iterator[dict[str, torch.Tensor]]:
        """One epoch's minibatches of the batch `b`: the rows `minibatch_indices` gives, in its
        order. Every field is gathered once in the epoch's shuffled row order, so a minibatch is a
        contiguous slice (a view) instead of one gather per field per minibatch."""
        parts = minibatch_indices(self.buf.t * self.buf.k, self.cfg.minibatches, rng)
        perm = self.team.tensor(np.concatenate(parts))
        yield from minibatch_slices({k: v.index_select(0, perm) for k, v in b.items()}, [len(p) for p in parts])

    def learn(self, obs: np.ndarray, prev: np.ndarray, update: int, step: int | None = None) -> dict[str, float]:
        """PPO epochs over shuffled minibatches of rows; one backward over the summed losses,
        then each network clips its own gradient norm and steps its own optimiser.

        The returned logs are means over the last epoch's minibatches (how far the final policy
        moved from the rollout policy), kept as tensors and turned into floats once per update.
        compile=true runs the same loop with each minibatch step one compiled graph
        (`learning.compiled_update`).
        """
        cfg = self.cfg
        b, masks = self.batch(obs, prev, step)
        rng = stream(cfg.seed, MINIBATCH_STREAM, update)
        if self.compiled_update is not None:
            return self.compiled_update.learn(self.epoch_minibatches, b, masks, rng)
        total = UpdateStats()
        for epoch in range(cfg.epochs):
            last = epoch == cfg.epochs - 1
            for mb in self.epoch_minibatches(b, rng):
                local_loss, central_loss, stats = self.losses(mb, masks, with_stats=last)
                loss = local_loss if central_loss is None else local_loss + central_loss
                for opt in self.updaters:
                    opt.zero_grad()
                loss.backward()
                norms = {f"{opt.name}/grad_norm": opt.clip_and_step() for opt in self.updaters}
                if last:
                    total.add({**stats, **norms})
        return total.means()
