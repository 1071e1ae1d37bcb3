"""The site feed: what a fleet's central agent sees that no robot observes, from the site itself.

    from hammer.site import SiteFeed
    with SiteFeed("bundles/warehouse", run_id="site-a", connect="tcp/192.0.2.1:7447", identity="identity/") as site:
        while running:
            site.publish(wms_state())   # the C central-only columns of the team's observation rows

Why (docs/fleet.md, "The site feed"): in a warehouse the central agent's state has columns no robot
observes (which shelves are requested, where the goals are: rware's columns [L, D) of every row,
envs/rware_vec.py). They come from the site's warehouse management system, so the site publishes
them on their own key (`site/state`, a `SiteState`) with its own identity (`site`: in a secure
fleet only it may publish there, no robot key can). The fleet's central agent puts the newest feed
into every row of its state, and once the feed has been silent for `site_hold_s` it uses zeros
instead (the silent rule, as for a missing robot: logged, counted, named in the verdict).

A client of the fleet's router, opened as the robot SDK's is (`serve/edge_agent.open_fleet_client`):
until the router first answers (in the background for `connect_retry_s`), `publish` sends nothing
and returns False (counted). It never waits on the network: a reliable publisher with congestion
control DROP. Torch-free, as the robot's side is.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np
from hammer.protocol.access import SITE
from hammer.serve.edge_agent import FleetClient, site_columns

log = logging.getLogger("hammer.site")


class SiteFeed(FleetClient):
    """The site feed of the team in `bundle`, for run `run_id` (`publish`, `close`).

    Transport as `hammer.edge.EdgeAgent`'s: `connect` (the fleet's router) or `zenoh_config`;
    `identity` (a directory with ca.pem, site.pem, site.key) for a secure fleet; `insecure` to
    accept plain traffic beyond loopback; `runtime`: RuntimeSettings items (`zenoh_lease_s=30`, ...);
    `wait=True`: open the session here (ConnectionError after `connect_retry_s`), else in the
    background. `counts`: `published`, `unjoined` (calls before the session was open)."""

    _alone = "the feed sends nothing"
    counter = "site_published"  # the world's count of ticks whose columns went out on the feed

    def __init__(self, bundle: str | Path, *, run_id: str, connect: str | None = None,
                 zenoh_config: Path | None = None, identity: Path | None = None, insecure: bool = False,
                 connect_retry_s: float = 300.0, runtime: tuple[str, ...] = (), wait: bool = False) -> None:
        from hammer.serve.bundle import load_bundle
        from hammer.serve.edge_entry import edge_settings, edge_transport

        b = load_bundle(Path(bundle), check_config=False)
        env = b.env_spec_data
        self.local_dim, self.obs_dim = self._columns(b)
        self.dim = self.obs_dim - self.local_dim
        self.settings = edge_settings(b, run_id, None, list(runtime))
        self.transport = edge_transport(self.settings, SITE, int(env["n_agents"]), connect, zenoh_config,
                                        None if identity is None else Path(identity), insecure, client=True)
        self.name = SITE
        self.counts = {"published": 0, "unjoined": 0}
        self._env_idx = np.zeros(1, np.int64)
        self._pub = None
        self._start(wait, connect_retry_s)

    @staticmethod
    def columns(bundle: str | Path) -> int:
        """C: how many floats a state of this team's site feed has (ValueError: the team has none)."""
        from hammer.serve.bundle import load_bundle

        local, d = SiteFeed._columns(load_bundle(Path(bundle), check_config=False))
        return d - local

    @staticmethod
    def _columns(b) -> tuple[int, int]:
        cols = site_columns(b.env_spec_data)
        if cols is None:
            raise ValueError(f"bundle {b.path}: every robot of this team observes its whole row; it has no site "
                             "feed (only teams with central-only columns do, e.g. rware)")
        return cols

    def _join(self, retry_s: float) -> None:
        session = self._open(retry_s)
        if session is None:
            return
        try:
            pub = session.publisher(session.keys.site_state(), express=True, block=False)
            session.declare_alive(self.name)
        except BaseException:
            session.close()
            raise
        self._pub = pub
        self.session = session  # last: `publish` uses the session once all of it is declared
        self._joined()

    def publish(self, state: Any) -> bool:
        """Send the site's state: the C central-only columns (or a whole observation row of D, of which
        columns [L, D) are taken). False (counted) before the session is open. Never waits."""
        from hammer.protocol.schemas import SiteState

        c = np.asarray(state, dtype=np.float32).reshape(-1)
        if c.shape[0] == self.obs_dim:
            c = c[self.local_dim:]
        if c.shape[0] != self.dim or not np.isfinite(c).all():
            raise ValueError(f"state: expected {self.dim} finite floats (the team's central-only columns), got "
                             f"shape {np.shape(state)}{'' if np.isfinite(c).all() else ' with NaN/inf'}")
        if self._pub is None:
            self.counts["unjoined"] += 1
            return False
        self._pub.publish(SiteState(step=self.counts["published"], env_idx=self._env_idx, cols=c[None]))
        self.counts["published"] += 1
        return True


WAREHOUSE_FILE = "warehouse.npy"  # in a simulated fleet's run directory: the warehouse's current site columns


class WarehouseRecord:
    """A simulated warehouse's management system, as far as the site feed needs one: the world of a
    fleet whose site runs elsewhere (`hammer serve --realtime --external-site`) hands the env's
    current central-only columns here at every tick (`publish`, the world's one way to hand them on),
    and that site reads them (`simulated_warehouse`) to publish them. Out of band, as a real management
    system reads its own database: cutting the site's link silences the feed, not what the site knows.
    The file is rewritten only when the columns change (requests and goals move on a delivery, not on
    every tick), so the world's tick loop does no file I/O on most ticks; each write replaces the file
    whole (os.replace), so a reader gets one state's columns or the one before."""

    counter = "site_recorded"  # the world's count of ticks it handed on (not published: the site does)

    def __init__(self, run_dir: str | Path) -> None:
        self.path = Path(run_dir) / WAREHOUSE_FILE
        self._tmp = self.path.with_name(f".{WAREHOUSE_FILE}.{os.getpid()}")
        self._written: np.ndarray | None = None
        self.writes = 0

    def publish(self, cols: np.ndarray) -> bool:
        cols = np.asarray(cols, np.float32)
        if self._written is not None and np.array_equal(cols, self._written):
            return True  # the record already holds these columns
        with open(self._tmp, "wb") as f:
            np.save(f, cols, allow_pickle=False)
        os.replace(self._tmp, self.path)
        self._written, self.writes = cols.copy(), self.writes + 1
        return True


def simulated_warehouse(run_dir: str | Path):
    """In simulation, the site's view of the warehouse: a function returning the C central-only
    columns the world last wrote to RUN/warehouse.npy (`WarehouseRecord`), or None before its first
    tick. `SiteFeed(...).publish(simulated_warehouse(run)())` is what a site of a simulated fleet sends."""
    path = Path(run_dir) / WAREHOUSE_FILE

    def state() -> np.ndarray | None:
        try:
            with open(path, "rb") as f:
                return np.load(f, allow_pickle=False)
        except FileNotFoundError:
            return None

    return state
