"""The learning side of a HAMMER team, shared by the in-process trainer and the learner process.

`TeamLearner` owns what an update needs: the team's networks, one optimiser per network, the
rollout buffer and the PPO maths (GAE, clipped losses, minibatch epochs). The in-process `Trainer`
fills its buffer by acting itself; the distributed learner (`learning.learner_role`) fills it from
the env host's experience chunks. Both then call `learn`, so the update is written once.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from envs.base import EnvSpec
from learning.config import RunConfig
from learning.networks import gaussian_logp
from learning.ppo import (
    PPOUpdater,
    clipped_policy_loss,
    gae,
    masked_mean,
    minibatch_indices,
    next_values,
    normalize_advantages,
    value_loss,
)
from learning.rollout import RolloutBuffer
from learning.rundir import optimizer_from_tensors, optimizer_to_tensors
from learning.sampling import MINIBATCH_STREAM, stream
from learning.team import Team


class TeamLearner:
    def __init__(self, cfg: RunConfig, spec: EnvSpec) -> None:
        torch.set_num_threads(cfg.torch_threads)
        self.cfg = cfg
        self.team = Team(cfg, spec)
        self.local_opt = PPOUpdater(self.team.local.parameters(), cfg.lr_local, cfg.max_grad_norm)
        self.central_opt = (PPOUpdater(self.team.central.parameters(), cfg.lr_central, cfg.max_grad_norm)
                            if self.team.central is not None else None)
        self.buf = RolloutBuffer(cfg.rollout_steps, cfg.num_envs, cfg.n_agents, spec.obs_dim,
                                 self.team.state_dim, self.team.msg_dim, spec.action_shape, spec.discrete)
        self._msg_log_std = torch.full((max(self.team.msg_dim, 1),), math.log(cfg.msg_std))[: self.team.msg_dim]

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

    def batch(self, obs: np.ndarray, prev: np.ndarray) -> dict[str, torch.Tensor]:
        """Advantages/returns for the filled buffer, flattened to (T*K, N, ...) tensors."""
        cfg, team, buf = self.cfg, self.team, self.buf
        last_state = team.global_state(obs, prev)
        last_v = team.local_values(obs, team.bootstrap_messages(last_state))
        dones = buf.terminated | buf.truncated
        nv = next_values(buf.values, last_v, buf.final_values, buf.reset)
        adv, ret = gae(buf.rewards, buf.values, nv, buf.terminated, dones, cfg.gamma, cfg.gae_lambda, buf.active)

        def flat(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a.reshape(buf.t * buf.k, *a.shape[2:])))

        b = {"obs": flat(buf.obs), "state": flat(buf.state), "msg": flat(buf.msg), "keep": flat(buf.keep),
             "act": flat(buf.actions), "logp": flat(buf.logp), "adv": flat(adv), "ret": flat(ret),
             "mask": flat(buf.active.astype(np.float32))}
        if team.central_rl:
            c_nv = next_values(buf.c_values, team.central_values(last_state), buf.c_final_values, buf.reset)
            c_adv, c_ret = gae(buf.rewards, buf.c_values, c_nv, buf.terminated, dones, cfg.gamma,
                               cfg.gae_lambda, buf.active)
            b.update(raw=flat(buf.msg_raw), c_logp=flat(buf.c_logp), c_adv=flat(c_adv), c_ret=flat(c_ret),
                     c_mask=b["mask"] * b["keep"])
        return b

    def losses(self, b: dict[str, torch.Tensor], mb: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor | None, dict[str, float]]:
        """(local PPO loss, central PPO loss or None, logs) on the rows `mb`.

        backprop: the messages are recomputed from the stored global states with grad, so the
        local actor loss flows through u_i into the central heads and encoder (DIAL-style); the
        local critic sees detached messages. rl: the local loss sees the stored (sent) messages,
        the central loss is its own PPO on the Gaussian messages; the two graphs never meet.
        """
        cfg, team = self.cfg, self.team
        m = b["mask"][mb]
        backprop = team.central is not None and cfg.central_mode == "backprop"
        if backprop:
            msg = team.central.message_mean(b["state"][mb]) * b["keep"][mb].unsqueeze(-1)
        else:
            msg = b["msg"][mb]
        x = team.local_input(b["obs"][mb], msg)
        new_logp, entropy = team.local.logp_entropy(x, b["act"][mb])
        new_v = team.local.value(team.local_input(b["obs"][mb], msg.detach()) if backprop else x)
        a = normalize_advantages(b["adv"][mb], m) if cfg.norm_adv else b["adv"][mb]
        pg, st = clipped_policy_loss(new_logp, b["logp"][mb], a, cfg.clip, m)
        vl = value_loss(new_v, b["ret"][mb], m)
        ent = masked_mean(entropy, m)
        local_loss = pg - cfg.ent_coef * ent + cfg.vf_coef * vl
        logs = {"local/policy_loss": pg.item(), "local/value_loss": vl.item(), "local/entropy": ent.item(),
                "local/approx_kl": st["approx_kl"], "local/clipfrac": st["clipfrac"]}
        central_loss = None
        if team.central_rl:
            cm = b["c_mask"][mb]
            mean = team.central.message_mean(b["state"][mb])
            c_logp = gaussian_logp(b["raw"][mb], mean, self._msg_log_std)
            ca = normalize_advantages(b["c_adv"][mb], cm) if cfg.norm_adv else b["c_adv"][mb]
            cpg, cst = clipped_policy_loss(c_logp, b["c_logp"][mb], ca, cfg.clip, cm)
            cvl = value_loss(team.central.values(b["state"][mb]), b["c_ret"][mb], cm)
            central_loss = cpg + cfg.vf_coef * cvl
            logs.update({"central/policy_loss": cpg.item(), "central/value_loss": cvl.item(),
                         "central/approx_kl": cst["approx_kl"]})
        return local_loss, central_loss, logs

    def learn(self, obs: np.ndarray, prev: np.ndarray, update: int) -> dict[str, float]:
        """PPO epochs over shuffled minibatches of rows; one backward over the summed losses,
        then each network clips its own gradient norm and steps its own optimiser."""
        cfg, buf = self.cfg, self.buf
        b = self.batch(obs, prev)
        rng = stream(cfg.seed, MINIBATCH_STREAM, update)
        sums: dict[str, float] = {}
        n_mb = 0
        for _ in range(cfg.epochs):
            for mb_np in minibatch_indices(buf.t * buf.k, cfg.minibatches, rng):
                local_loss, central_loss, logs = self.losses(b, torch.from_numpy(mb_np))
                loss = local_loss if central_loss is None else local_loss + central_loss
                self.local_opt.zero_grad()
                if self.central_opt is not None:
                    self.central_opt.zero_grad()
                loss.backward()
                logs["local/grad_norm"] = self.local_opt.step()
                if self.central_opt is not None:
                    logs["central/grad_norm"] = self.central_opt.step()
                for key, v in logs.items():
                    sums[key] = sums.get(key, 0.0) + v
                n_mb += 1
        return {key: v / n_mb for key, v in sums.items()}

