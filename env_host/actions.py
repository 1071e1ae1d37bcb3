"""Collecting one vector step's actions from the local agents, under a deadline.

The env host cannot wait forever for an agent: a lost or late action would stall every env copy.
So each step gets a deadline; an agent whose action has not arrived by then plays the env's
declared default action in every copy (counted, and marked in the rollout as `defaulted`). An
action that arrives for an earlier step is either a second copy of one already applied
(duplicate) or missed its deadline (late); both are counted and dropped, never applied to the
wrong step. An action for a step not published yet (only a buggy or hostile peer sends one) is
rejected and counted (`rejected.step_ahead` of the env host). What the step needs comes back in
one `StepActions`.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from hammer.faults.steplog import StepLog, column
from hammer.protocol.schemas import Action
from hammer.protocol.session import Subscription

log = logging.getLogger("hammer.env")

RECENT_STEPS = 16  # how far back an arriving action is recognised as a duplicate rather than late


@dataclass
class LinkCounters:
    """Counts for the local→env action link (per run)."""

    actions_on_time: int = 0
    actions_late: int = 0  # arrived after the deadline of their step (discarded)
    actions_duplicate: int = 0
    default_actions: int = 0  # agent×copy entries that used the declared default
    msg_fallback_copies: int = 0  # agent×copy entries whose agent acted on a fallback message
    off_policy_actions: int = 0  # actions produced by another policy version than the rollout's

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class StepActions:
    """Everything one vector step takes from the local agents."""

    actions: np.ndarray  # (K, N, *action_shape): received, or the declared default
    msgs: np.ndarray  # (K, N, M) float32: the message each agent acted on (zeros where none came)
    fallback: np.ndarray  # (K, N) bool: the agent acted on a fallback message (its central message was late)
    defaulted: np.ndarray  # (K, N) bool: the agent's action missed the deadline; the default was used
    arrived_ms: np.ndarray | None = None  # (N,) ms from the collection's start to each action (NaN: none in time)


class ActionCollector:
    """Gathers the agents' actions of a step from `actions_in` until all are in or the deadline passes."""

    def __init__(self, actions_in: Subscription, spec, num_envs: int, msg_dim: int, deadline_s: float,
                 step_log: StepLog, reject: Callable[[str, str], None] | None = None) -> None:
        self.actions_in, self.spec = actions_in, spec
        self._reject = reject or (lambda reason, what: log.warning("rejected (%s): %s", reason, what))
        self.n, self.k, self.msg_dim = spec.n_agents, num_envs, msg_dim
        self.deadline_s = deadline_s
        self.step_log = step_log
        self.counters = LinkCounters()
        self._cols = {e: column("local->env", e) for e in ("delivered", "late", "duplicate", "defaults")}
        self._recent_got: dict[int, np.ndarray] = {}  # step -> agents whose action arrived

    def collect(self, step: int, policy_version: int | np.ndarray) -> StepActions:
        """The actions of `step`; those of another version than `policy_version` (one for every
        agent, or (N,) during a staged rollout: each agent's own) are counted off-policy."""
        n, k = self.n, self.k
        out = StepActions(self.spec.default_actions(k), np.zeros((k, n, self.msg_dim), np.float32),
                          np.zeros((k, n), dtype=bool), np.zeros((k, n), dtype=bool), np.full(n, np.nan))
        got = np.zeros(n, dtype=bool)
        start = time.monotonic()
        deadline = start + self.deadline_s
        while not got.all():
            a = self.actions_in.get(timeout=max(0.0, deadline - time.monotonic()))
            if a is None:
                break
            if self._accept(a, step, got):
                self._apply(a, out, policy_version if np.isscalar(policy_version) else int(policy_version[a.agent]))
                got[a.agent] = True
                out.arrived_ms[a.agent] = (time.monotonic() - start) * 1e3
        out.defaulted[:, ~got] = True
        self.counters.default_actions += int(out.defaulted.sum())
        self.step_log.add(step, self._cols["defaults"], int(out.defaulted.sum()))
        self._recent_got[step] = got
        self._recent_got.pop(step - RECENT_STEPS, None)
        return out

    def _accept(self, a: Action, step: int, got: np.ndarray) -> bool:
        """Whether `a` is the first action of its agent for `step`; counts and logs it either way."""
        c, cols = self.counters, self._cols
        if a.step > step:  # cannot happen without a bug upstream: we have not published it yet
            self._reject("step_ahead", f"action for future step {a.step} (now {step}) from agent {a.agent}")
            return False
        self.step_log.add(a.step, cols["delivered"])
        if a.step < step:
            earlier = self._recent_got.get(a.step)
            if earlier is not None and earlier[a.agent]:
                c.actions_duplicate += 1  # a second copy of an action already applied
                self.step_log.add(a.step, cols["duplicate"])
            else:
                c.actions_late += 1
                self.step_log.add(a.step, cols["late"])
            return False
        if got[a.agent]:
            c.actions_duplicate += 1
            self.step_log.add(step, cols["duplicate"])
            return False
        return True

    def _apply(self, a: Action, out: StepActions, policy_version: int) -> None:
        c = self.counters
        if a.policy_version != policy_version:
            c.off_policy_actions += 1
        rows = a.env_idx
        out.actions[rows, a.agent] = a.action
        if a.msg is not None and self.msg_dim:
            out.msgs[rows, a.agent] = a.msg
        c.msg_fallback_copies += int(a.fallback.sum())
        out.fallback[rows, a.agent] = a.fallback
        c.actions_on_time += 1
