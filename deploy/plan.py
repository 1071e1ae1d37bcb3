"""What `hammer up`, `hammer serve` and `hammer serve --realtime` will run, decided before anything
starts and before any file is written: the team's config (from a config file or a bundle), the run's
RuntimeSettings (runtime.settings.build_settings, the one settings path: the config's `runtime:`
section or the bundle's fallback, the flags, the `--runtime` items), the roles started elsewhere and
the command each needs. Every mistake is a ValueError with one line naming the field and the fix;
the commands (hammer/commands/up.py, serve.py) only report it, and hammer/api.py's `serve_bundle`
plans with `plan_serve` too."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from hammer.protocol.structs import dump, parse, replace


@dataclass
class UpPlan:
    cfg: object  # learning.config.RunConfig
    settings: object  # runtime.settings.RuntimeSettings
    run_dir: Path
    faults: object  # faults.spec.FaultPlan: the link faults, for display


def plan_up(config: Path | None = None, *, preset: str | None = None, set_: list[str] | None = None,
            fields: dict | None = None, runtime: list[str] | None = None, faults_file: Path | None = None,
            fault: list[str] | None = None, fault_seed: int | None = None, chaos: list[str] | None = None,
            run_dir: Path | None = None, external: list[str] | None = None, secure: bool = False,
            insecure: bool = False) -> UpPlan:
    """The plan of one `hammer up` run. `fields`: RunConfig fields from flags (None values ignored;
    variant defaults to hammer, out to runs). The run directory defaults to OUT/up-<name>-<time>."""
    import yaml
    from hammer.faults.chaos import parse_chaos
    from hammer.faults.spec import build_plan
    from hammer.learning.config import load_yaml, merge_config, yaml_error_text
    from hammer.protocol.fault_injection import FaultSpec
    from hammer.runtime.settings import build_settings

    data = load_yaml(config) if config is not None else {}
    fault_section, chaos_section = data.pop("faults", None), data.pop("chaos", None) or []
    runtime_section = data.pop("runtime", None) or {}
    extra = {**data, **{k: v for k, v in (fields or {}).items() if v is not None}}
    extra.setdefault("variant", "hammer")
    extra.setdefault("out", "runs")
    cfg = merge_config(preset or "cn3", None, set_ or [], extra)
    links = build_plan(fault, fault_seed, fault_section)
    chaos_items = [*chaos_section, *(chaos or [])]
    for c in chaos_items:
        parse_chaos(c)
    if not isinstance(runtime_section, dict):
        raise ValueError(f"{config}: runtime: must be a mapping of RuntimeSettings fields")  # noqa: TRY004 - a config mistake: the one-line error
    path = Path(run_dir) if run_dir is not None else Path(cfg.out) / f"up-{cfg.run_name()}-{time.strftime('%Y%m%d-%H%M%S')}"
    rt: dict = {"run_id": path.name.replace("_", "-")[:64], **runtime_section}
    if links.links:
        if faults_file is not None:
            raise ValueError("--faults FILE and --fault/faults: link rules cannot be combined; fix: use one of them")
        rt["faults"] = links.to_spec()
        rt["fault_links"] = [dump(lf) for lf in links.links]
    if chaos_items:
        rt["chaos"] = chaos_items
    if external:
        rt["external"] = list(external)
    fixed: dict = {**({"secure": True} if secure else {}), **({"insecure": True} if insecure else {})}
    if faults_file is not None:
        try:
            fixed["faults"] = parse(FaultSpec, yaml.safe_load(Path(faults_file).read_text()))
        except yaml.YAMLError as e:
            raise ValueError(f"--faults {faults_file}{yaml_error_text(e)}; fix the syntax there") from None
        except Exception as e:  # noqa: BLE001 - any parse/validation problem in one line
            raise ValueError(f"--faults {faults_file}: {str(e).splitlines()[0]}") from None
    return UpPlan(cfg, build_settings(rt, runtime, fixed=fixed), path, links)


@dataclass
class ServePlan:
    bundle: object  # serve.bundle.Bundle
    cfg: object  # learning.config.RunConfig: the team as served
    settings: object  # runtime.settings.RuntimeSettings
    run_dir: Path
    faults: object  # faults.spec.FaultPlan
    external_agents: list[int]  # agents started elsewhere (`hammer local --bundle`)
    external_help: dict[str, str]  # role -> the one command that starts it elsewhere


def plan_serve(bundle: Path, *, episodes: int = 100, seed: int | None = None, fault: list[str] | None = None,
               fault_seed: int = 0, chaos: list[str] | None = None, runtime: list[str] | None = None,
               external: str | None = None, out: Path = Path("runs"), run_dir: Path | None = None,
               secure: bool = False, insecure: bool = False, listen: list[str] | None = None,
               num_envs: int | None = None) -> ServePlan:
    """What `hammer serve BUNDLE` (lock-stepped) will run: the bundle's team, the served run's settings
    (serve.served_settings.serve_settings), the roles started elsewhere and their commands. Raises
    ValueError (BundleError) with one line; writes nothing."""
    from hammer.serve.bundle import load_bundle
    from hammer.serve.served_settings import serve_settings

    b = load_bundle(bundle)
    cfg = b.config(episodes=episodes, msg_dropout=0.0, **({} if seed is None else {"seed": seed}),
                   **({} if num_envs is None else {"num_envs": num_envs}))
    b.check_env_here(cfg)
    skip, roles = external_roles(external, cfg)
    path = run_dir or Path(out) / f"serve-{Path(bundle).name}-{time.strftime('%Y%m%d-%H%M%S')}"
    settings, links = serve_settings(b, path.name, fault, fault_seed, chaos, runtime, listen=listen_endpoints(listen),
                                     fixed={**({"secure": True} if secure else {}),
                                            **({"insecure": True} if insecure else {})})
    if roles:
        settings = replace(settings, external=sorted({*settings.external, *roles}))
    if (skip or roles) and settings.hub_port == 0 and not settings.zenoh_config_file:  # they need the port now
        from hammer.protocol.session import free_loopback_port

        settings = replace(settings, hub_port=free_loopback_port())
    settings.refuse_plain_beyond_loopback(settings.hub_transport())
    return ServePlan(b, cfg, settings, path, links, skip,
                     external_help(Path(bundle), b, cfg, settings, path, skip, roles, seed))


def plan_fleet(bundle: Path, hz: float, *, seconds: float | None = None, episodes: int = 100,
               seed: int | None = None, fault: list[str] | None = None, chaos: list[str] | None = None,
               runtime: list[str] | None = None, external: str | None = None, out: Path = Path("runs"),
               run_dir: Path | None = None, secure: bool = False, insecure: bool = False,
               listen: list[str] | None = None, num_envs: int | None = None, timeline: Path | None = None,
               site: Path | None = None, external_site: bool = False):
    """What `hammer serve BUNDLE --realtime HZ` will run: (FleetPlan, run directory, external robots,
    the loaded bundle),
    its `--runtime` items applied (the bounds to the plan, the rest checked as the fleet's
    RuntimeSettings) and the router's port fixed (the robots' commands name it). Raises ValueError
    (BundleError) with one line for what does not apply to a fleet or is malformed; writes nothing."""
    from hammer.deploy.fleet_launch import FleetPlan, apply_runtime, fleet_settings
    from hammer.protocol.session import free_loopback_port
    from hammer.serve.bundle import load_bundle

    refused = ((fault, "--fault (link faults are a lock-stepped run's; cut a link instead: hammer bench fleet)"),
               (num_envs, "--num-envs (a fleet is one world, K=1)"))
    for given, what in refused:
        if given:
            raise ValueError(f"--realtime does not take {what}")
    try:
        robots = [int(x) for x in (external or "").split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--external {external!r}: with --realtime, robot indices only, e.g. 0,2") from None
    path = run_dir or Path(out) / f"fleet-{Path(bundle).name}-{time.strftime('%Y%m%d-%H%M%S')}"
    plan = FleetPlan(bundle=bundle, hz=hz, seconds=seconds, episodes=None if seconds is not None else episodes,
                     seed=seed, chaos=list(chaos or []), listen=listen_endpoints(listen), external=robots,
                     secure=secure, insecure=insecure, timeline=timeline, site=site, site_external=external_site)
    plan.hub_port = free_loopback_port()  # fixed now: the robots' commands name it
    apply_runtime(plan, list(runtime or []))
    for key in plan.runtime:  # the router's port is this command's own choice (--listen PORT for robots)
        if key in ("hub_port", "hub_listen", "zenoh_config_file", "secure_hub"):
            raise ValueError(f"--runtime {key}: a fleet's router is set by --listen (and --secure); "
                             "fix: leave it out")
    plan.check()
    team = load_bundle(bundle)
    from hammer.serve.edge_agent import site_columns

    if external_site and (not team.wiring().uses_central or site_columns(team.env_spec_data) is None):
        raise ValueError(f"--external-site: {Path(bundle).name} has no site feed (only a team with a central agent "
                         "and central-only columns, e.g. rware, has one); fix: leave it out")
    fleet_settings(team, plan, path.name)  # a bad --runtime value: one line, before anything
    return plan, path, robots, team


def listen_endpoints(listen: list[str] | None) -> list[str]:
    """--listen endpoints, checked: the agents must be told a fixed port (0 would be whatever the OS picks)."""
    from hammer.serve.edge_entry import check_endpoint

    for e in listen or []:
        check_endpoint(e, "--listen", "give this machine's address the agents reach and a fixed port, e.g. "
                                      "tcp/192.0.2.1:7447")
    return list(listen or [])


def hub_endpoint(settings) -> str:
    """Where a role on another machine connects: the first --listen endpoint (an any-address one as
    `<this host>`), else the loopback hub (an agent on this machine)."""
    proto = "tls" if settings.secure else "tcp"
    if settings.hub_listen:
        addr = settings.hub_listen[0].split("/", 1)[1]
        host, _, port = addr.rpartition(":")
        if host.strip("[]") in ("0.0.0.0", "::"):
            host = "<this host>"
        return f"{proto}/{host}:{port}"
    if settings.zenoh_config_file:
        return "<the hub's endpoint in your Zenoh config>"
    return f"{proto}/127.0.0.1:{settings.hub_port}"


def external_help(bundle: Path, b, cfg, settings, path: Path, agents: list[int], roles: list[str],
                  seed: int | None) -> dict[str, str]:
    """The one command each external role needs (the launcher shows it as it waits for them): an edge
    agent from the bundle, the central agent from the run directory; the hub's endpoint filled in."""
    import shlex

    from hammer.deploy.supervisor import role_args
    from hammer.protocol.session import is_loopback_endpoint

    where = hub_endpoint(settings)
    plain_out = not settings.secure and ("<" in where or not is_loopback_endpoint(where))  # the agent's consent too
    joins = ({"settings": path / "runtime.json", "identity": path / "identity"} if settings.secure
             else {"run_id": settings.run_id})
    num_envs = cfg.num_envs if cfg.num_envs != int(b.config_data["num_envs"]) else None
    out = {f"local-{i}": shlex.join(["hammer", *role_args("local", bundle=bundle, agent=i, **joins, connect=where,
                                                          insecure=plain_out, seed=seed, num_envs=num_envs)])
           for i in agents}
    if "central" in roles:
        out["central"] = shlex.join(["hammer", *role_args("central", run_dir=path, connect=where)]) + \
            " (the run directory's config.json, runtime.json and env_spec.json are all it reads)"
    return out


def external_roles(text: str | None, cfg) -> tuple[list[int], list[str]]:
    """--external: (agent indices, other roles) started elsewhere; only the central agent may be one of those."""
    if not text:
        return [], []
    items = [x.strip() for x in text.split(",") if x.strip()]
    roles = sorted({x for x in items if not x.lstrip("-").isdigit()})
    if [r for r in roles if r != "central"] or (roles and not cfg.wiring.uses_central):
        raise ValueError(f"--external {text!r}: expected agent indices and optionally central "
                         f"({'this team has no central agent' if roles == ['central'] else 'e.g. 0,2,central'})")
    out = sorted({int(x) for x in items if x not in roles})
    if any(not 0 <= i < cfg.n_agents for i in out):
        raise ValueError(f"--external {text!r}: this team has agents 0..{cfg.n_agents - 1}")
    return out, roles
