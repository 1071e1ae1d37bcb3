"""What the secure profile costs, and what a flood on one agent's own key costs: the same short run
plain, secure, and secure with a flood, in one process, alternated.

Each repeat runs the plain profile and then the secure one (same config, same seed), so both see
the same host load; the figures are the env host's own (env-steps/s over the whole run including
PPO updates, and the latency of one distributed step: observations out -> every action back,
p50/p99). Medians over the repeats. The two profiles must produce the same metrics.csv (the
secure profile changes who may talk, not what is said), and the table says whether they did.

The flood (profile `secure+flood`): a peer holding agent 1's real identity publishes
4 MB payloads on agent 1's own action key, 25 a second, for the whole run. The access rules let it
(that key is agent 1's to publish on); the env host must refuse each one on arrival, by size,
before copying or decoding it, and keep its step rate. Its figures say how many it sent and how
many the env host refused (`rejected.size`, which also makes the run's verdict `degraded`).
"""

from __future__ import annotations

import csv
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

PROFILES = ("plain", "secure", "secure+flood")
FLOOD_BYTES, FLOOD_PER_S = 4 << 20, 25
FIGURES = ("env_steps_per_s", "step_latency_ms_p50", "step_latency_ms_p99")


def _metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "wall_time"} for r in csv.DictReader(f)]


class FloodPeer(threading.Thread):
    """FLOOD_PER_S payloads of FLOOD_BYTES a second on agent `agent`'s own action key, as that agent."""

    def __init__(self, run_id: str, transport, agent: int = 1) -> None:
        super().__init__(daemon=True, name="flood-peer")
        self.run_id, self.transport, self.agent = run_id, transport, agent
        self.stop_event, self.sent, self.error = threading.Event(), 0, None

    def run(self) -> None:
        from hammer.protocol.session import HammerSession

        try:
            with HammerSession(self.run_id, self.transport, sender=f"local-{self.agent}") as s:
                pub, big = s.publisher(s.keys.act(self.agent), reliable=False), bytes(FLOOD_BYTES)
                t0 = time.monotonic()
                while not self.stop_event.wait(max(0.0, t0 + (self.sent + 1) / FLOOD_PER_S - time.monotonic())):
                    pub.put_bytes(big)
                    self.sent += 1
        except Exception as e:  # noqa: BLE001 - reported with the figures
            self.error = e


def _flood_hook(run_dir: Path, n_agents: int, peers: list):
    """A launcher chaos hook that starts the flood once every role is up (the identity files exist)."""
    from hammer.protocol.session import TransportConfig
    from hammer.runtime.settings import RuntimeSettings

    def hook(sup, board) -> None:
        if not peers:
            rt = RuntimeSettings.load(run_dir)
            stolen = rt.secured(TransportConfig(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{rt.hub_port}"]),
                                "local-1", run_dir, n_agents)
            peers.append(FloodPeer(rt.run_id, stolen))
            peers[0].start()

    return hook


def bench_security(preset: str = "cn3", episodes: int = 100, repeats: int = 2) -> dict:
    """{"runs": [one dict per run], "median": {profile: {figure: value}}, "same_metrics": bool,
    "secure_over_plain": {figure: ratio}, "flood_over_secure": {figure: ratio}}."""
    from hammer.deploy.launcher import launch
    from hammer.learning.config import merge_config
    from hammer.runtime.settings import RuntimeSettings

    cfg = merge_config(preset, overrides=[f"episodes={episodes}", "variant=hammer"])
    runs, same, load0 = [], True, os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="hammer-bench-security-") as tmp:
        for r in range(repeats):
            dirs = {}
            for profile in PROFILES:
                # a loaded host can take more than the default minute to start every role: no figure depends on it
                settings = RuntimeSettings(run_id=f"bsec-{profile.replace('+', '-')}-{r}-{os.getpid()}",
                                           secure=profile != "plain", startup_timeout_s=300)
                dirs[profile] = Path(tmp) / f"{profile}-{r}"
                peers: list[FloodPeer] = []
                hook = _flood_hook(dirs[profile], cfg.n_agents, peers) if profile == "secure+flood" else None
                try:
                    res = launch(cfg, settings, dirs[profile], chaos=hook)
                finally:
                    for p in peers:
                        p.stop_event.set()
                        p.join(10)
                links = res.summary.get("links", {})
                env_rejected = res.summary.get("rejected", {}).get("env", {})
                runs.append({"profile": profile, "repeat": r, **{f: res.summary[f] for f in FIGURES},
                             "default_actions": links.get("default_actions"),
                             "msg_fallback_copies": links.get("msg_fallback_copies"), "wall_s": res.wall_time,
                             "flood_sent": peers[0].sent if peers else 0,
                             "flood_error": repr(peers[0].error) if peers and peers[0].error else None,
                             "env_rejected_size": env_rejected.get("size", 0), "degraded": res.summary.get("degraded"),
                             "degraded_reasons": res.summary.get("degraded_reasons"),
                             "loadavg_1m_end": os.getloadavg()[0]})
            same = same and _metrics(dirs["plain"]) == _metrics(dirs["secure"]) == _metrics(dirs["secure+flood"])
    median = {p: {f: statistics.median(x[f] for x in runs if x["profile"] == p) for f in FIGURES} for p in PROFILES}
    ratio = {f: median["secure"][f] / median["plain"][f] for f in FIGURES}
    flood = {f: median["secure+flood"][f] / median["secure"][f] for f in FIGURES}
    return {"preset": preset, "episodes": episodes, "repeats": repeats, "runs": runs, "median": median,
            "secure_over_plain": ratio, "flood_over_secure": flood, "same_metrics": same,
            "loadavg_1m_start": load0, "loadavg_1m": os.getloadavg()[0], "cpu_count": os.cpu_count(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
