"""The live view of a launched run (`hammer up`, `hammer serve`): the dashboard table, the links table
and the plain status line, all read from the launcher's board (deploy.launcher.Board: the roles' heartbeats,
restarts, chaos, attendance). Shared by the commands that launch (`hammer up`, `hammer serve`) and open
to a library user's `on_tick` of `deploy.launcher.launch`; rich is imported only when a table is drawn."""

from __future__ import annotations

import time
from pathlib import Path

from hammer.protocol.structs import parse


def eta(start: tuple[float, int], episodes: int, budget: int) -> str:
    """Time left at this session's episode rate, as h:mm:ss ('-' until there is a rate)."""
    t0, e0 = start
    done, elapsed = episodes - e0, time.monotonic() - t0
    if done <= 0 or elapsed <= 0:
        return "-"
    return hms(max(0, budget - episodes) * elapsed / done)


def hms(seconds: float) -> str:
    """h:mm:ss with as many hours as it takes (26:03:00, not the 02:03:00 a clock shows after 24 h)."""
    s = int(seconds)
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}"


def links_table(board, cfg, settings):
    """Configured faults and their live effect per link (from the roles' heartbeats)."""
    from hammer.faults.links import COUNTERS_NOTE, collect_role_counters, link_table
    from hammer.faults.spec import LinkFault

    plan = [parse(LinkFault, d) for d in settings.fault_links]
    title = "faults: " + ("; ".join(lf.describe() for lf in plan) if plan else
                          "custom rules" if settings.faults and settings.faults.enabled else "none")
    if settings.chaos:
        title += f" | chaos: {', '.join(settings.chaos)}"
    roles = collect_role_counters(Path("/nonexistent"), board.last_by_pid)
    rows = link_table(roles, cfg.n_agents, cfg.wiring.uses_central)
    notes = [f"{link}: sent includes {row['unreported']:,} not yet reported by its sender (restarted or between "
             "heartbeats)" for link, row in rows.items() if row.get("unreported")]
    if board.chaos_log:
        notes.append("chaos fired: " + "; ".join(f"{e['event']} (t={e['t']:.0f}s, step {e['step']})"
                                                 for e in board.chaos_log[-3:]))
    return LinksView(title, rows, "\n".join([COUNTERS_NOTE, *notes]))


class LinksView:
    """The links table: a row per link and a column per counter where the terminal is wide enough for
    its ten columns, else turned (a column per link, a row per counter), so that no link name or count is
    cut to `env-…` in an 80-column terminal. Decided at each render, from the width there is."""

    def __init__(self, title: str, rows: dict[str, dict[str, int]], caption: str) -> None:
        self.title, self.rows, self.caption = title, rows, caption

    def wide(self):
        from hammer.faults.links import COLUMNS
        from rich.table import Table

        t = Table(title=self.title, caption=self.caption, show_header=True, expand=False)
        t.add_column("link", no_wrap=True)
        for col in COLUMNS:
            t.add_column(col, justify="right", no_wrap=True)
        for link, row in self.rows.items():
            t.add_row(link, *(f"{row[c]:,}" for c in COLUMNS))
        return t

    def turned(self):
        from hammer.faults.links import COLUMNS
        from rich.table import Table

        t = Table(title=self.title, caption=self.caption, show_header=True, expand=False)
        t.add_column("counter", no_wrap=True)
        for link in self.rows:
            t.add_column(link, justify="right", no_wrap=True)
        for col in COLUMNS:
            t.add_row(col, *(f"{row[col]:,}" for row in self.rows.values()))
        return t

    def __rich_console__(self, console, options):
        from rich.measure import Measurement

        wide = self.wide()
        natural = Measurement.get(console, options.update_width(10_000), wide).maximum  # its width uncut
        yield wide if natural <= options.max_width else self.turned()


def eta_text(board, cfg, rate: dict) -> str:
    """Time left at the episode rate seen since the first finished episode of this session."""
    env = board.heartbeats.get("env")
    episodes = int(env.counters.get("episodes", 0)) if env else 0
    if "start" not in rate and episodes > 0:
        rate["start"] = (time.monotonic(), episodes)
    return eta(rate["start"], episodes, cfg.episodes) if "start" in rate else "-"


def attendance_text(board) -> str:
    """Who left and came back, and who is away now (deploy.attendance); '' while nobody left."""
    att = getattr(board, "attendance", None)
    if att is None or not att.leaves():
        return ""
    per = "; ".join(f"{n} left {r.leaves}, rejoined {r.rejoins}" for n, r in sorted(att.roles.items()) if r.leaves)
    away = att.away()
    return per + (f"; away now: {', '.join(f'{n} {s:.0f} s' for n, s in sorted(away.items()))}" if away else "")


def rollout_text(run_dir, n_agents: int) -> str:
    """A served run's update history, for the dashboard: the version each agent's steps name (a
    staged rollout gives the canary's agents a version of their own, runtime/pushes.py) and the
    latest decision."""
    from hammer.runtime.pushes import HistoryError, assignment, read_pushes

    try:
        entries = read_pushes(run_dir)
    except HistoryError as e:
        return f"unreadable: {e}"
    if not entries:
        return ""
    a, last = assignment(entries), entries[-1]
    per = f"central:{a.base} " + " ".join(f"local-{i}:{v}" for i, v in enumerate(a.agent_versions(n_agents)))
    decision = last.get("decision")
    stage = f" stage {decision['stage']}" if isinstance(decision, dict) and "stage" in decision else ""
    reason = f" ({last['reason']})" if last.get("reason") else ""
    canary = f"canary v{a.canary} open; " if a.canary is not None else ""
    return f"{canary}{per}; last: {last.get('action', 'push')} v{last['version']}{stage}{reason}"


def dashboard_table(board, cfg, started: float, settings=None, rate: dict | None = None, run_dir=None):
    from rich.console import Group
    from rich.table import Table

    env = board.heartbeats.get("env")
    c = {**env.counters, **env.gauges} if env else {}
    t = Table(title=f"hammer up: {cfg.env} N={cfg.n_agents} {cfg.wiring.label} seed {cfg.seed}",
              show_header=True, expand=False)
    t.add_column("what")
    t.add_column("value", justify="right")
    t.add_row("episodes", f"{int(c.get('episodes', 0)):,} / {cfg.episodes:,}")
    t.add_row("paper metric (last 100)", f"{c.get('paper_metric_100', float('nan')):.2f}")
    t.add_row("env-steps/s", f"{board.env_rate():,.0f}")
    t.add_row("step latency p50 / p99 (ms)", f"{c.get('step_p50_ms', 0):.2f} / {c.get('step_p99_ms', 0):.2f}")
    t.add_row("late / duplicate actions", f"{int(c.get('actions_late', 0))} / {int(c.get('actions_duplicate', 0))}")
    t.add_row("default actions / msg fallbacks", f"{int(c.get('default_actions', 0))} / "
                                                 f"{int(c.get('msg_fallback_copies', 0))}")
    versions = ", ".join(f"{r}:{int(h.gauges.get('policy_version', -1))}" for r, h in sorted(board.heartbeats.items()))
    t.add_row("policy version per role", versions or "-")
    rollout = rollout_text(run_dir, cfg.n_agents) if run_dir is not None else ""
    if rollout:
        t.add_row("updates (pushes.json)", rollout)
    restarts = ", ".join(f"{r}:{n}" for r, n in sorted(board.restarts.items()) if n)
    t.add_row("roles alive / restarts", f"{len(board.alive)} / {restarts or 0}")
    t.add_row("leaves / rejoins", attendance_text(board) or "0")
    rejected = {r: {k[9:]: int(v) for k, v in h.counters.items() if k.startswith("rejected.") and v}
                for r, h in sorted(board.heartbeats.items())}
    t.add_row("rejected messages", "; ".join(f"{r} " + ", ".join(f"{k} {v}" for k, v in c.items())
                                             for r, c in rejected.items() if c) or "0")
    stalled = [f"{r}: {h.detail}" for r, h in sorted(board.heartbeats.items()) if h.detail.startswith("stalled")]
    if stalled:
        t.add_row("[bold red]stalled[/]", "\n".join(stalled))
    t.add_row("elapsed / eta", f"{time.monotonic() - started:,.0f} s / {eta_text(board, cfg, rate if rate is not None else {})}")
    if settings is None:
        return t
    return Group(t, links_table(board, cfg, settings))


def status_line(board, cfg, rate: dict) -> str:
    """The dashboard in one line, for a terminal that is not a TTY (every few seconds)."""
    env = board.heartbeats.get("env")
    c = {**env.counters, **env.gauges} if env else {}
    away = attendance_text(board)
    return (f"episodes {int(c.get('episodes', 0))}/{cfg.episodes}  "
            f"env-steps/s {board.env_rate():,.0f}  metric(100) {c.get('paper_metric_100', 0):.2f}  "
            f"p50/p99 {c.get('step_p50_ms', 0):.2f}/{c.get('step_p99_ms', 0):.2f} ms  "
            f"defaults {int(c.get('default_actions', 0))}  fallbacks {int(c.get('msg_fallback_copies', 0))}"
            f"  eta {eta_text(board, cfg, rate)}"
            + (f"  [{away}]" if away else "")
            + "".join(f"  [{e['event']}]" for e in board.chaos_log[-1:]))


def fleet_status_line(board, t: float) -> str:
    """A fleet's progress in one line (`hammer serve --realtime`), from the world's heartbeat."""
    w = board.heartbeats.get("env")
    c = {**w.counters, **w.gauges} if w else {}
    return (f"t {t:5.0f} s  ticks {int(c.get('ticks', 0))}  robots present "
            f"{int(c.get('robots_present', 0))}  defaults {int(c.get('default_actions', 0))}  "
            f"episodes {int(c.get('episodes', 0))}  metric(100) {c.get('paper_metric_100', 0):.2f}"
            + "".join(f"  [{e['event']}]" for e in board.chaos_log[-1:]))
