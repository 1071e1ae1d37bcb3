"""`hammer view RUNS_DIR`: run directories in a browser, live, and as Prometheus metrics.

Its own process (Starlette on uvicorn), reading only files: each run's live.json, events.jsonl and
series.jsonl (written by its launcher, deploy/live.py), summary.json, metrics.csv, sweep.csv,
fleet.json / config.json / runtime.json (what kind of run it is). It opens no Zenoh session and
writes nothing, and every route answers GET only, so a browser cannot reach the run (pushes and
rollbacks stay commands).

Routes: `/` the one page (plain JavaScript, nothing from a CDN; it routes by its #fragment),
`/api/runs` the index, `/api/runs/<run>` a run's picture, `/api/runs/<run>/stream` the same as
server-sent events (a new picture as soon as live.json changes, at least one event a second so a
page can tell a dead server from a quiet run), `/api/runs/<run>/{events,series,curve,sweep}` for
the plots, `/metrics` for Prometheus (docs/view.md lists the names), `/healthz`.

Beyond loopback it answers only with the token (deploy.live.check_view_addr refuses to start
without one): `Authorization: Bearer TOKEN` (Prometheus), or `?token=TOKEN` once in a browser, which
sets an HttpOnly cookie for the page's own requests.
"""

from __future__ import annotations

import asyncio
import csv
import hmac
import json
import re
import time
from pathlib import Path

from hammer.deploy.live import EVENTS_FILE, LIVE_FILE, SERIES_FILE, SILENT_AFTER_S
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.middleware.base import BaseHTTPMiddleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response, StreamingResponse
from starlette.routing import Route

STATIC = Path(__file__).resolve().parent / "static"
RUN_MARKERS = ("live.json", "summary.json", "fleet.json", "config.json", "env_summary.json", "sweep.csv")
PART = re.compile(r"[A-Za-z0-9][A-Za-z0-9._=+-]{0,199}")
LIVE_FRESH_S = 5.0  # a live.json older than this, with no end written, is a launcher that stopped answering
STREAM_POLL_S = 0.1
STREAM_KEEPALIVE_S = 1.0
MAX_SERIES_LINES = 4000
COOKIE = "hammer_view_token"


# ----- reading run directories -----------------------------------------------------------------------
def _json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def find_runs(root: Path, depth: int = 2) -> list[Path]:
    """Run directories under `root` (itself, its children, their children), newest first."""
    out = []

    def visit(d: Path, level: int) -> None:
        if any((d / m).is_file() for m in RUN_MARKERS):
            out.append(d)
            return
        if level < depth:
            try:
                children = [c for c in d.iterdir() if c.is_dir() and not c.name.startswith(".")]
            except OSError:
                return
            for c in children:
                if c.name not in ("logs", "previous", "checkpoints", "policies", "identity", "final"):
                    visit(c, level + 1)

    visit(root, 0)
    return sorted(out, key=lambda p: _mtime(p), reverse=True)


def _mtime(d: Path) -> float:
    times = [(d / m).stat().st_mtime for m in (*RUN_MARKERS, "metrics.csv") if (d / m).is_file()]
    return max(times, default=0.0)


def resolve_run(root: Path, run: str) -> Path | None:
    """The run directory named `run` (a path relative to root, of plain names): None for anything else."""
    parts = run.split("/")
    if not parts or len(parts) > 3 or not all(PART.fullmatch(p) for p in parts):
        return None
    d = root.joinpath(*parts).resolve()
    if root not in d.parents and d != root:
        return None
    return d if d.is_dir() and any((d / m).is_file() for m in RUN_MARKERS) else None


def run_kind(d: Path) -> str:
    if (d / "fleet.json").is_file():
        return "fleet"
    if (d / "sweep.csv").is_file() and not (d / "config.json").is_file():
        return "fault sweep"  # `hammer faults sweep --out DIR`
    rt = _json(d / "runtime.json")
    if rt:
        return "serve" if rt.get("mode") == "eval" else "up"
    return "train" if (d / "config.json").is_file() else "run"


def run_info(root: Path, d: Path, now: float | None = None) -> dict:
    """One line of the index: kind, status, verdict, when, how long."""
    now = time.time() if now is None else now
    live = _json(d / LIVE_FILE)
    summary = _json(d / "summary.json") or _json(d / "env_summary.json")
    live_now = bool(live) and not live.get("ended") and now - float(live.get("written_at", 0)) < LIVE_FRESH_S
    if live_now:
        status = "live"
    elif summary.get("interrupted"):
        status = f"stopped ({summary.get('stopped_by')})"
    elif summary.get("completed"):
        status = "completed"
    elif live and not live.get("ended"):
        status = "not answering"
    elif summary or (d / "sweep.csv").is_file():
        status = "finished"  # a trainer's or a sweep's result, which says no more
    else:
        status = "unfinished"
    reasons = summary.get("degraded_reasons") or []
    started = live.get("started_at") or _mtime(d)
    wall = summary.get("wall_s") or summary.get("wall_time_s") or (live.get("elapsed_s") if live else None)
    metric = summary.get("final_paper_metric_last500", (summary.get("world") or {}).get("paper_metric_mean"))
    return {"run": d.relative_to(root).as_posix() if d != root else d.name, "kind": live.get("kind") or run_kind(d),
            "status": status, "degraded": bool(summary.get("degraded")), "verdict": reasons[:3],
            "started_at": started, "wall_s": wall, "paper_metric": metric,
            "has": {k: (d / f).is_file() for k, f in (("live", LIVE_FILE), ("curve", "metrics.csv"),
                                                      ("series", SERIES_FILE), ("sweep", "sweep.csv"))}}


def run_picture(root: Path, d: Path) -> dict:
    """A run's page: live.json as written (plus when the view read it); a run without one, what its
    summary says, in the same shape."""
    live = _json(d / LIVE_FILE)
    info = run_info(root, d)
    if not live:
        s = _json(d / "summary.json")
        rows = []
        for name, r in sorted((s.get("robots") or {}).items()):
            rows.append({"name": name, "robot": int(name.split("-")[1]) if name.startswith("local-") else None,
                         "state": "stopped", "rate_hz": r.get("control_hz"), "msg_age_p50_ms": r.get("msg_age_p50_ms"),
                         "msg_age_p99_ms": r.get("msg_age_p99_ms"), "defaults": r.get("defaults"),
                         "policy_acted": r.get("policy_version"), "policy_held": r.get("policy_held")})
        live = {"kind": info["kind"], "title": d.name, "rows": rows, "counts": {}, "alerts": [], "events": [],
                "ended": info["status"]}
    return {**live, "run": info["run"], "info": info, "server_time": time.time()}


def read_series(d: Path, limit: int = MAX_SERIES_LINES) -> list[dict]:
    return _read_jsonl(d / SERIES_FILE, limit)


def read_events(d: Path, limit: int = 500) -> list[dict]:
    return _read_jsonl(d / EVENTS_FILE, limit)


def _read_jsonl(path: Path, limit: int) -> list[dict]:
    """The last `limit` lines of a JSON-lines file the launcher appends to; a line being written is skipped."""
    try:
        lines = path.read_text().splitlines()[-limit:]
    except OSError:
        return []
    out = []
    for line in lines:
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def read_csv(path: Path, columns: tuple[str, ...], limit: int = 20_000) -> dict[str, list]:
    """Some columns of a CSV as lists (numbers where they parse), every k-th row past `limit` rows."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError:
        return {}
    step = max(1, len(rows) // limit)
    out: dict[str, list] = {c: [] for c in columns}
    for r in rows[::step]:
        for c in columns:
            v = r.get(c)
            try:
                out[c].append(float(v))
            except (TypeError, ValueError):
                out[c].append(v)
    return out


# ----- Prometheus ---------------------------------------------------------------------------------
STATES = ("ok", "late", "missing", "never", "stopped")


class RunsCollector:
    """Every run's live.json as metrics at scrape time (nothing kept between scrapes)."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def collect(self):
        labels = ["run", "role", "robot"]
        up = GaugeMetricFamily("hammer_role_up", "1 while the role or robot is heard of (state ok or late), else 0",
                               labels=labels)
        state = GaugeMetricFamily("hammer_role_state", "1 for the role's current state (ok, late, missing, never, "
                                  "stopped)", labels=[*labels, "state"])
        seen = GaugeMetricFamily("hammer_role_last_seen_seconds", "seconds since the role's latest heartbeat",
                                 labels=labels)
        rate = GaugeMetricFamily("hammer_role_rate_hz", "control rate (a robot's fresh actions applied per second) "
                                 "or work rate (env steps, acts, ticks per second)", labels=labels)
        age = GaugeMetricFamily("hammer_role_msg_age_milliseconds", "age of the central message acted on "
                                "(a robot), or step latency (the env host), by quantile", labels=[*labels, "quantile"])
        acted = GaugeMetricFamily("hammer_role_policy_version", "the policy version the role acts with", labels=labels)
        held = GaugeMetricFamily("hammer_role_policy_held", "the newest policy version the role holds", labels=labels)
        defaults = CounterMetricFamily("hammer_role_default_actions", "ticks or steps on the default action",
                                       labels=labels)
        fallbacks = CounterMetricFamily("hammer_role_fallbacks", "acts on the fallback message (stale or none)",
                                        labels=labels)
        restarts = CounterMetricFamily("hammer_role_restarts", "times the launcher restarted the role", labels=labels)
        rejected = CounterMetricFamily("hammer_role_rejected", "payloads the role refused", labels=labels)
        live_g = GaugeMetricFamily("hammer_run_live", "1 while the run's launcher writes its picture", labels=["run"])
        robots = GaugeMetricFamily("hammer_run_robots", "robots by state", labels=["run", "state"])
        metric = GaugeMetricFamily("hammer_run_paper_metric", "the paper metric over the latest 100 episodes",
                                   labels=["run"])
        steps = GaugeMetricFamily("hammer_run_env_steps_per_second", "env steps per second (`hammer up`)",
                                  labels=["run"])
        episodes = CounterMetricFamily("hammer_run_episodes", "episodes finished", labels=["run"])
        alerts = GaugeMetricFamily("hammer_run_alerts_firing", "alerts firing now", labels=["run"])
        now = time.time()
        for d in find_runs(self.root):
            live = _json(d / LIVE_FILE)
            if not live:
                continue
            run = d.relative_to(self.root).as_posix() if d != self.root else d.name
            fresh = not live.get("ended") and now - float(live.get("written_at", 0)) < LIVE_FRESH_S
            live_g.add_metric([run], 1.0 if fresh else 0.0)
            c = live.get("counts") or {}
            for s in STATES:
                if f"robots_{s}" in c:
                    robots.add_metric([run, s], float(c[f"robots_{s}"]))
            for fam, key in ((metric, "paper_metric_100"), (steps, "env_steps_per_s")):
                if c.get(key) is not None:
                    fam.add_metric([run], float(c[key]))
            if c.get("episodes") is not None:
                episodes.add_metric([run], float(c["episodes"]))
            alerts.add_metric([run], float(len(live.get("alerts") or [])))
            for r in live.get("rows") or []:
                lv = [run, str(r.get("name")), "" if r.get("robot") is None else str(r["robot"])]
                st = r.get("state")
                up.add_metric(lv, 1.0 if st in ("ok", "late") else 0.0)
                for s in STATES:
                    state.add_metric([*lv, s], 1.0 if st == s else 0.0)
                if r.get("last_seen_age_s") is not None:
                    seen.add_metric(lv, float(r["last_seen_age_s"]) + max(0.0, now - float(live.get("written_at", now))))
                for fam, key in ((rate, "rate_hz"), (acted, "policy_acted"), (held, "policy_held")):
                    if r.get(key) is not None:
                        fam.add_metric(lv, float(r[key]))
                for q, key in (("0.5", "msg_age_p50_ms"), ("0.99", "msg_age_p99_ms")):
                    if r.get(key) is not None:
                        age.add_metric([*lv, q], float(r[key]))
                for fam, key in ((defaults, "defaults"), (fallbacks, "fallbacks"), (restarts, "restarts"),
                                 (rejected, "rejected")):
                    if r.get(key) is not None:
                        fam.add_metric(lv, float(r[key]))
        yield from (live_g, robots, metric, steps, episodes, alerts, up, state, seen, rate, age, acted, held,
                    defaults, fallbacks, restarts, rejected)


# ----- the app ------------------------------------------------------------------------------------
class TokenGate(BaseHTTPMiddleware):
    """With a token: every request shows it (bearer header, cookie, or ?token= which sets the cookie)."""

    def __init__(self, app, token: str) -> None:
        super().__init__(app)
        self.token = token

    async def dispatch(self, request: Request, call_next):
        given = request.query_params.get("token")
        auth = request.headers.get("authorization", "")
        candidates = [given, request.cookies.get(COOKIE), auth[7:] if auth.lower().startswith("bearer ") else None]
        if not any(c and hmac.compare_digest(c.encode(), self.token.encode()) for c in candidates):
            return PlainTextResponse("hammer view: a token is needed (Authorization: Bearer TOKEN, or ?token=TOKEN)\n",
                                     status_code=401, headers={"WWW-Authenticate": "Bearer"})
        response = await call_next(request)
        if given:
            response.set_cookie(COOKIE, self.token, httponly=True, samesite="strict")
        return response


class ReadOnly(BaseHTTPMiddleware):
    """GET and HEAD only, and the headers that keep the page its own (no framing, no outside scripts)."""

    async def dispatch(self, request: Request, call_next):
        if request.method not in ("GET", "HEAD"):
            return PlainTextResponse("hammer view is read-only\n", status_code=405, headers={"Allow": "GET, HEAD"})
        response = await call_next(request)
        response.headers["X-Frame-Options"] = "DENY"
        response.headers["X-Content-Type-Options"] = "nosniff"
        response.headers["Content-Security-Policy"] = ("default-src 'self'; script-src 'self' 'unsafe-inline'; "
                                                       "style-src 'self' 'unsafe-inline'; img-src 'self' data:")
        return response


def create_app(root: Path, token: str | None = None) -> Starlette:
    root = Path(root).resolve()
    registry = CollectorRegistry(auto_describe=False)
    registry.register(RunsCollector(root))

    def the_run(request: Request) -> Path:
        d = resolve_run(root, request.path_params["run"])
        if d is None:
            raise _NotFound(request.path_params["run"])
        return d

    async def page(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def runs(request: Request) -> Response:
        now = time.time()
        return JSONResponse({"root": str(root), "server_time": now,
                             "runs": [run_info(root, d, now) for d in find_runs(root)]})

    async def run(request: Request) -> Response:
        return JSONResponse(run_picture(root, the_run(request)))

    async def events(request: Request) -> Response:
        return JSONResponse({"events": read_events(the_run(request))})

    async def series(request: Request) -> Response:
        return JSONResponse({"series": read_series(the_run(request)), "silent_after_s": SILENT_AFTER_S})

    async def curve(request: Request) -> Response:
        return JSONResponse(read_csv(the_run(request) / "metrics.csv", ("episode", "env_steps", "paper_metric",
                                                                         "team_return")))

    async def sweep(request: Request) -> Response:
        return JSONResponse(read_csv(the_run(request) / "sweep.csv", ("team", "drop", "delay_ms", "seed",
                                                                       "paper_metric", "msg_fallback_rate")))

    async def stream(request: Request) -> Response:
        d = the_run(request)

        async def gen():
            last_mtime, last_sent = None, 0.0
            while True:
                if await request.is_disconnected():
                    return
                try:
                    mtime = (d / LIVE_FILE).stat().st_mtime_ns
                except OSError:
                    mtime = None
                now = time.monotonic()
                if mtime != last_mtime or now - last_sent >= STREAM_KEEPALIVE_S:
                    last_mtime, last_sent = mtime, now
                    yield f"data: {json.dumps(run_picture(root, d))}\n\n"
                await asyncio.sleep(STREAM_POLL_S)

        return StreamingResponse(gen(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    async def metrics(request: Request) -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    async def healthz(request: Request) -> Response:
        return PlainTextResponse("ok\n")

    async def not_found(request: Request, exc: Exception) -> Response:
        return JSONResponse({"error": f"no run {exc.args[0]!r} under {root}"}, status_code=404)

    routes = [Route("/", page), Route("/api/runs", runs), Route("/api/runs/{run:path}/stream", stream),
              Route("/api/runs/{run:path}/events", events), Route("/api/runs/{run:path}/series", series),
              Route("/api/runs/{run:path}/curve", curve), Route("/api/runs/{run:path}/sweep", sweep),
              Route("/api/runs/{run:path}", run), Route("/metrics", metrics), Route("/healthz", healthz)]
    middleware = [Middleware(ReadOnly)] + ([Middleware(TokenGate, token=token)] if token else [])
    return Starlette(routes=routes, middleware=middleware, exception_handlers={_NotFound: not_found})


class _NotFound(Exception):
    pass


def serve(root: Path, host: str, port: int, token: str | None) -> None:
    """Serve until SIGTERM or Ctrl-C (uvicorn's own handling)."""
    import uvicorn

    uvicorn.run(create_app(root, token), host=host, port=port, log_level="warning", access_log=False,
                timeout_graceful_shutdown=1)
