"""`hammer bench`: the benchmark commands, wired into the `hammer` CLI by `hammer.cli`.

Without a subcommand, the whole-system table (`benchmarks.suite`); each subcommand measures one
part against a baseline taken in the same run:

  transport    typed protocol vs raw Zenoh bytes: msgs/s and round trips   (benchmarks.transport)
  codec        build/encode/decode us per message: fast path vs pydantic   (benchmarks.transport)
  loop-floor   the step loop with every role's work taken out               (benchmarks.loop_floor)
  workers      multiwalker in-process vs subprocess workers vs the ceiling  (benchmarks.bench_workers)
  rware        the numpy warehouse vs rware's own: env and hammer train      (benchmarks.bench_rware_vec)
  train        the in-process trainer's speed, PPO updates included         (benchmarks.train_bench)
  runtime      `hammer up` vs `hammer train`, same config, same run         (benchmarks.runtime)
  security     `hammer up --secure` vs plain vs a flood on one agent's key    (benchmarks.security)
  edge         an edge agent's RSS and cold start: --bundle vs --run-dir     (benchmarks.edge_bench)
  seeds        S seeds as one batched process vs one solo run                (benchmarks.seeds_bench)
  kernels      an update's layers alone (the arithmetic floor) vs the real loop (benchmarks.kernels)
  scale        cn N=3..50: train vs up vs up with agent pools, the floor      (benchmarks.scale)
  soak         a served team for N minutes: RSS per process, disk, growth    (benchmarks.soak)

The measuring code is imported inside each command, so `hammer --help` stays fast.
"""

from __future__ import annotations

import json
import logging
import os
import platform
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import fail

bench = typer.Typer(help="Benchmarks that print figures (ratios against a baseline measured in the same run). "
                         "Without a subcommand: the whole-system table (raw env, train, up, latency, RSS).",
                    invoke_without_command=True)


@bench.callback()
def bench_all(
    ctx: typer.Context,
    episodes: int = typer.Option(320, help="Episodes per runner and preset."),
    json_dir: str = typer.Option("runs/bench", "--json-dir", help="Write bench-<date>.json here ('' to skip; "
                                  "--json-dir docs/results to publish the figures)."),
) -> None:
    """Whole-system figures in one run; subcommands measure one part each."""
    if ctx.invoked_subcommand is not None:
        return
    from hammer.benchmarks.suite import run_suite

    run_suite(episodes, Path(json_dir) if json_dir else None)


@bench.command("transport")
def bench_transport(
    rounds: Annotated[int, typer.Option(min=10, help="round trips per payload and mode")] = 1000,
    flood: Annotated[int, typer.Option(min=100, help="messages per throughput burst")] = 5000,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
) -> None:
    """Messages/s and round-trip p50/p99 of typed messages vs raw bytes of the same size,
    over Zenoh on 127.0.0.1 to an echo peer in another (spawned) process."""
    from rich.table import Table

    from hammer.benchmarks.transport import bench_meta, rows_as_dicts, run_bench
    from hammer.console import table_console

    rows = run_bench(rounds=rounds, flood=flood)
    table = Table(title="hammer bench transport (typed protocol vs raw bytes, loopback, echo process)")
    for col in ("payload", "bytes", "enc us", "dec us", "typed msg/s", "raw msg/s", "ratio",
                "typed rtt p50/p99 us", "raw rtt p50/p99 us", "rtt ratio"):
        table.add_column(col, justify="left" if col == "payload" else "right")
    for r in rows:
        table.add_row(
            r.payload, str(r.bytes), f"{r.encode_us:.1f}", f"{r.decode_us:.1f}",
            f"{r.typed_msgs_per_s:,.0f}", f"{r.raw_msgs_per_s:,.0f}", f"{r.rate_ratio:.2f}",
            f"{r.typed_rtt_p50_us:.0f} / {r.typed_rtt_p99_us:.0f}",
            f"{r.raw_rtt_p50_us:.0f} / {r.raw_rtt_p99_us:.0f}", f"{r.rtt_ratio:.2f}",
        )
    console = table_console()
    console.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps({"meta": bench_meta(rounds, flood), "rows": rows_as_dicts(rows)},
                                       indent=2) + "\n")
        typer.echo(f"wrote {json_out}")


@bench.command("peers")
def bench_peers(
    jaxmarl_repo: Annotated[Path | None, typer.Option(help="A checkout of FLAIROx/JaxMARL (its baselines/IPPO; the "
                                                           "pip package does not ship them).")] = None,
    jax_venv: Annotated[Path, typer.Option(help="JaxMARL's own venv (built with pip here if missing)")] = Path(
        "/tmp/hammer-jaxmarl-venv"),
    env_steps: Annotated[int, typer.Option(min=1000, help="env steps of each run (JaxMARL's defaults: x2.5)")] = 400_000,
    out: Annotated[Path | None, typer.Option(help="write the JSON result here")] = None,
    hammer_set: Annotated[list[str] | None, typer.Option(help="more config for hammer's run, KEY=VALUE "
                                                               "(repeatable), e.g. compile_scope=epoch")] = None,
    hammer_schedules: Annotated[str, typer.Option(help="hammer's runs, comma-separated: cn3 (the matched schedule), "
                                                       "jaxmarl (JaxMARL's defaults exactly), jaxmarl-ppo-kK (its "
                                                       "PPO settings over K = 64, 128 or 256 env copies, 2,048 samples an update)")] = "cn3",
) -> None:
    """hammer's training rate against JaxMARL's IPPO-FF on MPE simple spread, one core each, one after
    the other: at hammer's cn3 schedule and at JaxMARL's defaults; compile times and the end of both
    learning curves (docs/fast-envs.md)."""
    from hammer.benchmarks.peers import main

    code = main([*(["--jaxmarl-repo", str(jaxmarl_repo)] if jaxmarl_repo else []), "--jax-venv", str(jax_venv),
                 "--env-steps", str(env_steps), *(["--out", str(out)] if out else []),
                 *(x for kv in hammer_set or [] for x in ("--hammer-set", kv)),
                 "--hammer-schedules", hammer_schedules])
    if code:
        raise typer.Exit(code)


@bench.command("wire")
def bench_wire(
    bundle: Annotated[Path | None, typer.Argument(help="A team's bundle for its dimensions (default: cn3 with "
                                                       "own-observation views, D=10 M=4 A=5 N=3).")] = None,
    num_envs: Annotated[str, typer.Option(help="env copies K, comma-separated")] = "1,32",
    out: Annotated[Path | None, typer.Option(help="write the JSON result here")] = None,
) -> None:
    """Encoded bytes one vector step puts on an agent's link and on the central agent's link, per
    message type, against the physical minimum (the numbers alone), at each K."""
    from hammer.benchmarks.wire import main

    code = main([*([str(bundle)] if bundle else []), "--num-envs", num_envs, *(["--out", str(out)] if out else [])])
    if code:
        raise typer.Exit(code)


@bench.command("codec")
def bench_codec(
    k: Annotated[int, typer.Option(min=1, help="env copies per message (K)")] = 32,
    number: Annotated[int, typer.Option(min=1, help="calls per timing (--cold: calls per figure)")] = 500,
    repeat: Annotated[int, typer.Option(min=1, help="timings per figure (the best is kept)")] = 7,
    cold: Annotated[bool, typer.Option("--cold", help="time single calls with cold caches (median CPU "
                                                       "time; --number calls each), as a woken-up role")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
) -> None:
    """Microseconds to build (validate), encode and decode (validate) each message of the
    control loop, and a bare msgpack.unpackb of the same bytes (no checks: the floor)."""
    from rich.table import Table

    from hammer.benchmarks.transport import codec_bench, codec_rows_as_dicts, role_costs
    from hammer.console import table_console

    sizes = ((3, 18, 4), (5, 30, 8))
    rows = codec_bench(k=k, sizes=sizes, number=number, repeat=repeat, cold=cold)
    load = os.getloadavg()
    console = table_console()
    regime = "cache-cold single calls, median CPU time" if cold else "hot loop, best wall time"
    table = Table(title=f"hammer bench codec (us per message, {regime}; load {load[0]:.2f})")
    for col in ("payload", "bytes", "build", "encode", "decode", "total", "bare unpackb"):
        table.add_column(col, justify="left" if col == "payload" else "right")
    for r in rows:
        table.add_row(r.payload, str(r.bytes), f"{r.build_us:.1f}", f"{r.encode_us:.1f}", f"{r.decode_us:.1f}",
                      f"{r.total_us:.1f}", f"{r.unpackb_us:.1f}")
    console.print(table)
    roles = Table(title="codec time per vector step and role (us)"
                  + (", upper bound: a role pays cold caches once per wake-up, not per call" if cold else ""))
    for col in ("N", "role", "us"):
        roles.add_column(col, justify="left" if col == "role" else "right")
    per_role = {}
    for n, _, _ in sizes:
        per_role[n] = role_costs(rows, k, n)
        for role, us in per_role[n].items():
            roles.add_row(str(n), role, f"{us:.0f}")
    console.print(roles)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        meta = {"python": platform.python_version(), "cpus": os.cpu_count(), "loadavg": load, "k": k,
                "number": number, "repeat": repeat, "cold": cold}
        json_out.write_text(json.dumps({"meta": meta, "rows": codec_rows_as_dicts(rows),
                                        "roles": {str(n): r for n, r in per_role.items()}}, indent=2) + "\n")
        typer.echo(f"wrote {json_out}")


@bench.command("loop-floor")
def bench_loop_floor(
    steps: Annotated[int, typer.Option(min=50, help="timed vector steps per topology and mode")] = 1000,
    k: Annotated[int, typer.Option(min=1, help="env copies per message (K)")] = 32,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
) -> None:
    """Latency floor of the step loop: env -> central -> local agents -> env with every role's
    work removed (same keys, publishers and subscriptions as `hammer up`), typed messages vs raw
    bytes, one process per local agent vs one for all. Compare with `hammer bench runtime`."""
    from rich.table import Table

    from hammer.benchmarks.loop_floor import rows_as_dicts as floor_dicts
    from hammer.benchmarks.loop_floor import run_floor
    from hammer.console import table_console

    rows = run_floor(k=k, steps=steps)
    load = os.getloadavg()
    table = Table(title=f"hammer bench loop-floor (us per vector step, K={k}, loopback, no work in any role; "
                        f"load {load[0]:.2f})")
    for col in ("N", "local agents", "payload", "processes", "p50 us", "p99 us", "steps"):
        table.add_column(col, justify="left" if col in ("local agents", "payload") else "right")
    for n, r in rows:
        table.add_row(str(n), "one process each" if r.topology == "split" else "one process for all",
                      r.mode, str(r.processes), f"{r.p50_us:.0f}", f"{r.p99_us:.0f}", str(r.steps))
    console = table_console()
    console.print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        meta = {"python": platform.python_version(), "cpus": os.cpu_count(), "loadavg": load, "k": k,
                "steps": steps}
        json_out.write_text(json.dumps({"meta": meta, "rows": floor_dicts(rows)}, indent=2) + "\n")
        typer.echo(f"wrote {json_out}")


@bench.command("workers")
def bench_workers(
    num_envs: int = typer.Option(8, help="K copies"),
    workers: int = typer.Option(2, help="worker processes"),
    n_agents: int = typer.Option(3, help="walkers"),
    steps: int = typer.Option(300, help="batched steps per timed phase"),
) -> None:
    """Multiwalker env-steps/s in-process vs SubprocVecEnv vs the ceiling of independent processes (no IPC), same run; prints the speed-ups and load."""
    from hammer.benchmarks.bench_workers import main

    main([f"--num-envs={num_envs}", f"--workers={workers}", f"--n-agents={n_agents}", f"--steps={steps}"])


@bench.command("rware")
def bench_rware(
    n_agents: Annotated[str, typer.Option("--n", help="comma-separated robot counts (rware-tiny-<N>ag)")] = "2,4",
    copies: Annotated[str, typer.Option("--k", help="comma-separated copy counts K for the env figure")] = "1,16,64,256",
    seconds: Annotated[float, typer.Option(min=0.5, help="timed seconds per env measurement")] = 4.0,
    episodes: Annotated[int, typer.Option(min=0, help="episodes of each hammer train run (0: skip the train figure)")] = 96,
    seed: Annotated[int, typer.Option(help="run seed")] = 0,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
) -> None:
    """The numpy warehouse (impl=numpy) vs rware's own (impl=rware) in one run: copy-steps per CPU-second at each K, and `hammer train` end to end on the presets with the same seed (wall, CPU, identical metrics.csv); prints the ratios and the load. Pin it (`taskset -c 1`) to measure one core."""
    from hammer.benchmarks.bench_rware_vec import main

    try:
        ns, ks = [int(v) for v in n_agents.split(",")], [int(v) for v in copies.split(",")]
    except ValueError:
        fail(f"--n and --k take comma-separated integers, got {n_agents!r} and {copies!r}")
    if min(ns + ks) < 1:
        fail("--n and --k must be >= 1")
    main(["--n", *map(str, ns), "--k", *map(str, ks), f"--seconds={seconds}", f"--episodes={episodes}",
          f"--seed={seed}", *(["--json", str(json_out)] if json_out else [])])


@bench.command("train")
def bench_train(
    variant: Annotated[str, typer.Option(help="hammer | il | random | centralized")] = "hammer",
    central_mode: Annotated[str, typer.Option(help="rl | backprop")] = "rl",
    cn_episodes: Annotated[int, typer.Option(help="episodes of each cn3 run (cn and cn-mpe2)")] = 300,
    mw_updates: Annotated[int, typer.Option(help="timed PPO updates of each mw3 run")] = 2,
    full: Annotated[bool, typer.Option("--full", help="really run the 30,000-episode cn3 run (~minutes)")] = False,
    extrapolate_from: Annotated[int, typer.Option(help="episodes of the measured run the full run is "
                                                       "extrapolated from (without --full)")] = 2000,
    seed: Annotated[int, typer.Option(help="run seed")] = 0,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures to this JSON file")] = None,
) -> None:
    """Training speed: cn3 (vectorised vs mpe2 reference), the full cn3 run's wall time, mw3 workers."""
    from rich.console import Console

    from hammer.benchmarks.train_bench import run_bench

    err = Console(stderr=True)
    if min(cn_episodes, mw_updates, extrapolate_from) < 1:
        typer.secho("error: --cn-episodes, --mw-updates and --extrapolate-from must be >= 1", fg="red", err=True)
        raise typer.Exit(2)
    r = run_bench(variant, central_mode, cn_episodes, mw_updates, full, extrapolate_from, seed=seed,
                  progress=lambda msg: err.print(f"[dim]bench train: {msg} (load {os.getloadavg()[0]:.2f})[/dim]"))
    print_train_table(r)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(r, indent=2))
        err.print(f"wrote {json_out}")


@bench.command("seeds")
def bench_seeds(
    presets: Annotated[str, typer.Option(help="comma-separated presets")] = "cn3,cn5",
    sizes: Annotated[str, typer.Option(help="comma-separated seed counts S")] = "1,2,4,8,16",
    updates: Annotated[int, typer.Option(min=1, help="timed PPO updates per measurement")] = 3,
    compile_: Annotated[bool, typer.Option("--compile", help="compile=true for the batched runs (the first "
                                                             "compile takes minutes)")] = False,
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures to this JSON file")] = None,
) -> None:
    """Aggregate env-steps/s of S seeds trained as one batch (`hammer train --seeds`) vs one solo run,
    and the cn3 grid's wall time (5 variants x 5 seeds x 30,000 episodes) with and without batching."""
    from rich.table import Table

    from hammer.benchmarks.seeds_bench import grid_estimate, run_bench
    from hammer.console import table_console

    try:
        ps = tuple(p.strip() for p in presets.split(",") if p.strip())
        ss = tuple(int(x) for x in sizes.split(","))
    except ValueError:
        typer.secho("error: --sizes takes integers, e.g. 1,2,4,8,16", fg="red", err=True)
        raise typer.Exit(2) from None
    rows = run_bench(ps, ss, updates, compile_)
    table = Table(title="hammer bench seeds (hammer-rl, aggregate env-copy steps/s of the training loop)")
    for col in ("preset", "mode", "S", "seconds", "env-steps/s", "x solo", "load"):
        table.add_column(col, justify="left" if col in ("preset", "mode") else "right")
    for r in rows:
        table.add_row(r["preset"], r["mode"], str(r["seeds"]), f"{r['seconds']:.1f}", f"{r['env_steps_per_s']:,}",
                      f"{r['ratio']:.2f}", f"{r['load']:.2f}")
    console = table_console()
    console.print(table)
    grid = None
    if "cn3" in ps:
        grid = grid_estimate(rows)
        console.print(f"cn3 grid (25 runs x 30,000 episodes, estimated from hammer-rl rows): solo one after another "
                      f"{grid['solo_s'] / 60:.0f} min, seed-batched (S=5) {grid['batched_s'] / 60:.0f} min "
                      f"({grid['speedup']:.2f}x)")
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps({"rows": rows, "grid": grid}, indent=2))
        typer.echo(f"wrote {json_out}")


@bench.command("kernels")
def bench_kernels(
    variants: Annotated[str, typer.Option(help="comma-separated cn3 variants: il, hammer (rl), hammer-backprop")] = "il",
    updates: Annotated[int, typer.Option(min=1, help="timed updates of the real loop per row")] = 30,
    repeats: Annotated[int, typer.Option(min=10, help="calls per timed kernel (best of three loops)")] = 300,
    precisions: Annotated[str, typer.Option(help="comma-separated precisions: fp32, bf16 (RunConfig.precision; "
                                                 "bf16 needs native bfloat16, docs/fast-envs.md)")] = "fp32",
    json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures to this JSON file")] = None,
) -> None:
    """The arithmetic floor of one cn3 training update, one core: every Linear layer's forward and
    backward matmuls and tanh at the run's shapes (no Python, optimiser, loss or sampling), with the
    env step, against the real update and collection, eager and compile=true, per precision (bf16:
    the update's layers in bfloat16). A rate target above the floor's rate cannot be reached by
    removing overhead (docs/fast-envs.md)."""
    from rich.table import Table

    from hammer.benchmarks.kernels import measure
    from hammer.console import table_console
    from hammer.learning.config import ConfigError

    known = {"il": ("il", "rl"), "hammer": ("hammer", "rl"), "hammer-rl": ("hammer", "rl"),
             "hammer-backprop": ("hammer", "backprop")}
    names = [v.strip() for v in variants.split(",") if v.strip()]
    bad = [v for v in names if v not in known]
    if bad:
        fail(f"--variants: unknown {', '.join(bad)}; fix: one of {', '.join(known)}")
    precs = [p.strip() for p in precisions.split(",") if p.strip()]
    if not precs or any(p not in ("fp32", "bf16") for p in precs):
        fail(f"--precisions: {precisions!r}; fix: fp32, bf16 or fp32,bf16")
    try:
        rows = [measure(known[v][0], c, updates, repeats, central_mode=known[v][1], precision=p)
                for v in names for p in precs for c in (False, True)]
    except ConfigError as e:  # bf16 without native bfloat16
        fail(str(e))
    table = Table(title="hammer bench kernels (cn3, one core; ms per update of "
                        f"{rows[0]['schedule']})")
    for col in ("variant", "precision", "compile", "update", "floor", "collect", "env", "act floor", "env-steps/s",
                "at the floor", "load"):
        table.add_column(col, justify="left" if col == "variant" else "right")
    for r in rows:
        table.add_row(r["variant"], r["precision"], str(r["compile"]).lower(), f"{r['update_ms']:.1f}",
                      f"{r['update_floor_ms']:.1f}",
                      f"{r['collect_ms']:.1f}", f"{r['env_ms']:.1f}", f"{r['act_floor_ms']:.1f}",
                      f"{r['env_steps_per_s']:,}", f"{r['floor_env_steps_per_s']:,}", f"{r['load_1min']:.2f}")
    table_console().print(table)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(rows, indent=2))
        typer.echo(f"wrote {json_out}")


@bench.command("runtime")
def bench_runtime(
    presets: Annotated[str, typer.Option(help="Comma-separated presets to measure.")] = "cn3,cn5",
    episodes: Annotated[int, typer.Option(help="Episodes per measurement (same for both runners).")] = 320,
    variant: Annotated[str, typer.Option(help="Variant to run.")] = "hammer",
    central_mode: Annotated[str, typer.Option(help="Central mode (hammer).")] = "backprop",
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the figures as JSON here.")] = None,
) -> None:
    """env-steps/s of `hammer up` vs `hammer train` (same config, same run) and step latency p50/p99."""
    from rich.table import Table

    from hammer.benchmarks.runtime import bench_runtime, same_label
    from hammer.console import table_console

    logging.basicConfig(level=logging.WARNING)
    rows = bench_runtime(presets.split(","), episodes, variant, central_mode)
    t = Table(title=f"hammer bench runtime ({variant}/{central_mode}, {episodes} episodes each, "
                    f"load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    for col in ("preset", "train env-steps/s", "up env-steps/s", "up / train", "up lag-1 / train", "loop p50 ms",
                "loop p99 ms", "same metrics"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(r["preset"], f"{r['train_env_steps_per_s']:,.0f}", f"{r['up_env_steps_per_s']:,.0f}",
                  f"{r['ratio_up_over_train']:.2f}", f"{r.get('ratio_up_lag1_over_train', float('nan')):.2f}",
                  f"{r['step_latency_ms_p50']:.2f}", f"{r['step_latency_ms_p99']:.2f}", same_label(r))
    table_console().print(t)
    if json_out is not None:
        json_out.write_text(json.dumps(rows, indent=1))


@bench.command("security")
def bench_security(
    preset: Annotated[str, typer.Option(help="Preset to run.")] = "cn3",
    episodes: Annotated[int, typer.Option(help="Episodes per run.")] = 100,
    repeats: Annotated[int, typer.Option(help="Plain/secure/flooded triples, alternated (medians are shown).")] = 2,
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the figures as JSON here.")] = None,
) -> None:
    """What `hammer up --secure` costs, and what a 4 MB x 25/s flood on one agent's own key (with that agent's
    identity) costs: env-steps/s and step latency p50/p99, plain vs secure vs secure+flood, same run."""
    from rich.table import Table

    from hammer.benchmarks.security import FIGURES, PROFILES, bench_security
    from hammer.console import table_console

    logging.basicConfig(level=logging.WARNING)
    r = bench_security(preset, episodes, repeats)
    t = Table(title=f"hammer bench security ({preset}, {episodes} episodes, median of {repeats}, "
                    f"load {r['loadavg_1m']:.1f} on {r['cpu_count']} cores)")
    t.add_column("profile")
    for col in ("env-steps/s", "step p50 ms", "step p99 ms"):
        t.add_column(col, justify="right")
    for p in PROFILES:
        m = r["median"][p]
        t.add_row(p, f"{m['env_steps_per_s']:,.0f}", f"{m['step_latency_ms_p50']:.2f}", f"{m['step_latency_ms_p99']:.2f}")
    q = r["secure_over_plain"]
    t.add_row("secure / plain", *(f"{q[f]:.2f}" for f in FIGURES))
    q = r["flood_over_secure"]
    t.add_row("secure+flood / secure", *(f"{q[f]:.2f}" for f in FIGURES))
    flood = [x for x in r["runs"] if x["profile"] == "secure+flood"]
    t.caption = (f"same metrics.csv in every profile: {r['same_metrics']}; flood: 4 MB x 25/s on agent 1's own key "
                 f"with its identity, {sum(x['flood_sent'] for x in flood)} sent, "
                 f"{sum(x['env_rejected_size'] for x in flood)} refused by size at the env host; "
                 f"verdict degraded in {sum(bool(x['degraded']) for x in flood)} of {len(flood)} flooded runs")
    table_console().print(t)
    if json_out is not None:
        json_out.write_text(json.dumps(r, indent=1))


@bench.command("edge")
def bench_edge_command(
    act_s: Annotated[float, typer.Option(help="Seconds each agent acts (lock-step) while its RSS is sampled.")] = 3.0,
    repeats: Annotated[int, typer.Option(min=1, help="Measurements per entry, alternated (medians are shown).")] = 3,
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the figures as JSON here.")] = None,
    python: Annotated[Path | None, typer.Option(
        help="The agents' interpreter, e.g. a torch-free edge venv (python -m hammer.benchmarks.edge_venv PATH); "
             "default this one.")] = None,
    num_envs: Annotated[int, typer.Option(min=1, help="The team's env copies K (1: a robot, where the edge entry "
                                                      "runs the lite agent without numpy).")] = 1,
) -> None:
    """An edge agent's footprint: RSS while acting and cold start (process start to first action), for
    `hammer local --bundle` (no run directory; with the numpy agent too) and today's `hammer local
    --run-dir`, in one run."""
    import tempfile

    from rich.table import Table

    from hammer.benchmarks.edge_bench import bench_edge
    from hammer.console import table_console

    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory(prefix="hammer-bench-edge-") as work:
        load = os.getloadavg()[0]
        r = bench_edge(Path(work), act_s, repeats, python, num_envs)
    tg = r["targets"]
    t = Table(title=f"hammer bench edge (cn3 local agent, K={num_envs}, median of {repeats}, load {load:.1f}-"
                    f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores{', ' + str(python) if python else ''})")
    for col in ("entry", "RSS MB", "cold start s", "step p50 ms"):
        t.add_column(col, justify="left" if col == "entry" else "right")
    for entry, m in r["median"].items():
        t.add_row(entry, f"{m['rss_mb']:.1f}", f"{m['cold_start_s']:.2f}", f"{m['step_ms_p50']:.2f}")
    edge = r["median"]["edge (hammer local --bundle)"]
    t.caption = (f"targets: RSS <= {tg['rss_mb']:.0f} MB ({'met' if edge['rss_mb'] <= tg['rss_mb'] else 'missed'}), "
                 f"cold start <= {tg['cold_start_s']:g} s "
                 f"({'met' if edge['cold_start_s'] <= tg['cold_start_s'] else 'missed'})")
    table_console().print(t)
    if json_out is not None:
        json_out.write_text(json.dumps(r, indent=1))


@bench.command("scale")
def bench_scale_command(
    ns: Annotated[str, typer.Option("--n", help="agent counts N, comma-separated")] = "3,5,10,20,50",
    episodes: Annotated[int, typer.Option(min=32, help="episodes per runner and N (32 per PPO update)")] = 160,
    floor_steps: Annotated[int, typer.Option(min=50, help="timed loop-floor steps per N and topology")] = 300,
    json_dir: Annotated[str, typer.Option("--json-dir", help="write scale-<date>.json, .md and .png here "
                                          "(--json-dir docs/results to publish)")] = "runs/bench",
) -> None:
    """Scaling on cn: per N, `hammer train`, `hammer up` (one process per agent), `hammer up` with
    agent pools and the loop floor at the same N: env-steps/s, step p50/p99, messages and bytes per
    step, CPU and RSS per role, where the step's time goes; a markdown table and a PNG plot."""
    from hammer.benchmarks.scale import bench_scale, markdown

    logging.basicConfig(level=logging.WARNING)
    try:
        n_values = tuple(int(x) for x in ns.split(","))
    except ValueError:
        fail(f"--n {ns!r}: expected comma-separated agent counts, e.g. --n 3,5,10")
    r = bench_scale(n_values, episodes, floor_steps, Path(json_dir) if json_dir else None,
                    progress=lambda line: typer.echo(line, err=True))
    typer.echo(f"hammer bench scale, {r['meta']['date']}, {r['meta']['cpu_count']} cores, {episodes} episodes per point")
    typer.echo(markdown(r))
    for f in r.get("files", []):
        typer.echo(f"wrote {f}")


@bench.command("soak")
def bench_soak(
    minutes: Annotated[float, typer.Option(min=0.1, help="how long to serve the team")] = 10.0,
    every: Annotated[float, typer.Option(min=1, help="seconds between samples")] = 30.0,
    bundle: Annotated[Path | None, typer.Option(help="serve this bundle (default: an untrained cn3 team, "
                                                     "exported as `hammer bench edge` makes one)")] = None,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="RuntimeSettings field=value for the served run, repeatable, e.g. trace=true.")] = None,
    work: Annotated[Path | None, typer.Option(help="where the bundle and the run go (default runs/soak-<time>)")] = None,
    json_dir: Annotated[str, typer.Option("--json-dir", help="write soak-<date>.json here ('' to skip; "
                                          "--json-dir docs/results to publish)")] = "runs/bench",
) -> None:
    """A served team for MINUTES: RSS of the launcher and every role process and the run directory's disk
    use every EVERY seconds, then each one's growth from the first minute to the end."""
    from hammer.benchmarks.soak import print_soak, run_soak, write_result
    from hammer.console import table_console

    try:
        r = run_soak(minutes, every, work, bundle, tuple(runtime or ()), progress=lambda line: typer.echo(line, err=True))
    except RuntimeError as e:
        fail(str(e), code=1)
    print_soak(r, table_console())
    if json_dir:
        typer.echo(f"wrote {write_result(r, Path(json_dir))}")


@bench.command("fleet")
def bench_fleet(
    bundle: Annotated[Path, typer.Argument(help="A trained team (`hammer export`) that can run as a fleet (cn, mw).")],
    hz: Annotated[float, typer.Option(min=0.1, help="the world's and the central agent's rate")] = 20.0,
    trials: Annotated[str | None, typer.Option(
        help="cuts, KIND:SECONDS[xN] comma-separated, robots in turn: port (the robot's switch port), nic (the "
             "robot's own interface), hub (the serving machine's port: every robot), site (a team with a site feed: the "
             "site in a namespace of its own, its port); default "
             "port:0.5x2,port:5x2,port:8x2,port:30x2,nic:8x2,nic:30x1,hub:8x2")] = None,
    insecure: Annotated[bool, typer.Option(help="the plain profile (default: --secure, as docs/fleet.md runs it)")] = False,
    per_fleet: Annotated[int, typer.Option(min=1, help="trials per fleet session")] = 10,
    bytes_s: Annotated[float, typer.Option(help="first: bytes and packets per control step on robot 0's link "
                                                "over this many quiet seconds")] = 0.0,
    rate_kbit: Annotated[int, typer.Option(min=0, help="a tbf limit (kbit/s, both ways) on robot 0's port (0 = none)")] = 0,
    neigh_retrans_ms: Annotated[int | None, typer.Option(
        help="the kernel's neighbour (ARP) retransmission timer on every machine's interface (Linux: 1000 ms)")] = None,
    runtime: Annotated[list[str] | None, typer.Option(
        "--runtime", help="passed to `hammer serve --realtime --runtime`, e.g. zenoh_lease_s=10")] = None,
    edge_venv: Annotated[Path | None, typer.Option(help="the robots' interpreter (a torch-free venv)")] = None,
    push: Annotated[Path | None, typer.Option(help="instead of trials: a hot update to this bundle 10 s into the "
                                                   "run (exported with --works-with BUNDLE); each robot's switch "
                                                   "and every robot's control rate while they pull")] = None,
    work: Annotated[Path, typer.Option(help="where the fleets' run directories and logs go")] = Path(
        "/tmp/hammer-bench-fleet"),
    out: Annotated[Path | None, typer.Option(help="write the JSON result here; each trial goes to "
                                                  "OUT.trials.jsonl as it ends, and the same command again runs "
                                                  "only the trials still missing")] = None,
    soak_minutes: Annotated[float | None, typer.Option(help="instead: a fleet on loopback this long, RSS per "
                                                           "process and disk every 30 s (no root)")] = None,
) -> None:
    """The documented fleet (`hammer serve --realtime --secure` and the robot command it prints) across
    network namespaces (root): a serving machine and one namespace per robot on a bridge; links cut and
    restored, each cut repeated and every trial reported: the healthy robots' control rate during it,
    when the cut robot, the world and the central agent were back on fresh traffic (docs/fleet.md)."""
    from hammer.benchmarks.fleet_bench import main

    code = main([str(bundle), "--hz", str(hz), *(["--trials", trials] if trials else []),
                 *(["--insecure"] if insecure else []), "--per-fleet", str(per_fleet), "--bytes-s", str(bytes_s),
                 *(["--neigh-retrans-ms", str(neigh_retrans_ms)] if neigh_retrans_ms is not None else []),
                 "--rate-kbit", str(rate_kbit), *(x for r in runtime or [] for x in ("--runtime", r)),
                 *(["--edge-venv", str(edge_venv)] if edge_venv else []), "--work", str(work),
                 *(["--out", str(out)] if out else []), *(["--push", str(push)] if push else []),
                 *(["--soak-minutes", str(soak_minutes)] if soak_minutes else [])])
    if code:
        raise typer.Exit(code)


def register(app: typer.Typer) -> None:
    """Add the `bench` group to the top-level app."""
    app.add_typer(bench, name="bench")


def print_train_table(r: dict) -> None:
    """The table of `hammer bench train` (benchmarks.train_bench.run_bench's figures)."""
    from rich.table import Table

    from hammer.console import table_console

    mode = f"/{r['central_mode']}" if r["variant"] == "hammer" else ""
    t = Table(title=f"hammer train speed ({r['variant']}{mode}; env-steps/s include PPO updates; "
                    f"{r['cores']} cores)")
    for col in ("preset", "setting", "env-steps/s", "note", "load 1-min (before/after)"):
        t.add_column(col, justify="right" if col == "env-steps/s" else "left")

    def ld(x: dict) -> str:
        return f"{x['load_before']:.2f} / {x['load_after']:.2f}"

    cn, ref = r["cn3"]["cn"], r["cn3"]["cn-mpe2"]
    t.add_row("cn3", "env cn (vectorised)", f"{cn['env_steps_per_s']:,.0f}", f"{cn['episodes']} episodes", ld(cn))
    t.add_row("cn3", "env cn-mpe2 (reference)", f"{ref['env_steps_per_s']:,.0f}",
              f"{ref['episodes']} episodes; cn / cn-mpe2 = {r['cn3']['ratio']:.2f}x", ld(ref))
    f = r["full"]
    how = ("measured" if not f["extrapolated"] else
           f"EXTRAPOLATED from {f['episodes']:,} episodes ({f['wall_s']:.1f} s, startup {f['startup_s']:.1f} s)")
    t.add_row("cn3", "one full 30,000-episode run", f"{f['env_steps_per_s']:,.0f}",
              f"wall {f['full_wall_s']:.0f} s = {f['full_wall_s'] / 60:.1f} min, {how}", ld(f))
    for key in ("workers=0", "workers=2"):
        m = r["mw3"][key]
        name = "in-process" if key == "workers=0" else "env_workers=2"
        note = f"{m['updates']} updates after {m['warmup']} warm-up"
        if key == "workers=2":
            note += f"; speed-up {r['mw3']['speedup']:.2f}x over in-process"
        t.add_row("mw3", name, f"{m['env_steps_per_s']:,.0f}", note, ld(m))
    console = table_console()
    console.print(t)
    console.print("The machine is shared: compare figures only with the load average beside them.")
