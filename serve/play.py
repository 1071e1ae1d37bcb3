"""`hammer play BUNDLE --out team.gif`: watch a trained team, with the messages it sends.

Runs a few episodes in this process with the bundle's frozen weights and the acting code the
runtime uses (numpy forwards: `local_agent.client.LocalAgent`, `learning.central_acting.CentralActing`,
the same random streams), on the PettingZoo env behind the bundle's env id (cooperative navigation:
mpe2 simple_spread; multiwalker: SISL) created with render_mode="rgb_array", so the picture is the
environment's own renderer. Beside each frame a panel shows every agent's message vector at that
step, so a person sees what the team does and how the messages change. Writes a GIF (Pillow).
Needs the training install (PettingZoo, matplotlib).
"""

from __future__ import annotations

import importlib
import time
from pathlib import Path

import numpy as np

# The bundle's env id -> the PettingZoo catalog entry that renders it, and how its kwargs are named there.
RENDERED = {"cn": ("cn-mpe2", {"max_steps": "max_cycles", "local_ratio": "local_ratio"}),
            "cn-mpe2": ("cn-mpe2", None), "mw": ("mw-pettingzoo", None), "mw-pettingzoo": ("mw-pettingzoo", None)}


class PlayError(ValueError):
    """The team cannot be played; the message says why and what to do."""


def render_env(env_id: str, n_agents: int, env_kwargs: dict):
    """The PettingZoo parallel env of `env_id`, rendering rgb_array frames, and how many leading
    observation entries the team sees (None: all). cn's observe_others=false is mpe2's observation
    without its tail (other agents, communication): [v_i, p_i, landmarks - p_i] comes first in both."""
    from hammer.envs.catalog import _PETTINGZOO

    if env_id not in RENDERED:
        raise PlayError(f"env {env_id!r}: play renders {', '.join((*RENDERED, 'rware'))}; fix: export a team of "
                        "one of those")
    name, rename = RENDERED[env_id]
    kwargs = dict(env_kwargs)
    keep = None
    if rename is not None and kwargs.get("observe_others", True) is False:
        from hammer.envs.spread import spread_obs_dim

        kwargs.pop("observe_others")
        keep = spread_obs_dim(n_agents, observe_others=False)
    elif rename is not None:
        kwargs.pop("observe_others", None)
    if rename is not None:
        unknown = sorted(set(kwargs) - set(rename))
        if unknown:
            raise PlayError(f"env_kwargs {', '.join(unknown)}: mpe2's renderer has no such option; fix: play a team "
                            "trained with the default observations")
        kwargs = {rename[k]: v for k, v in kwargs.items()}
    e = _PETTINGZOO[name]
    factory = getattr(importlib.import_module(e.module), e.factory)
    return factory(**{**e.defaults, e.n_key: n_agents, **kwargs, "render_mode": "rgb_array"}), keep


def message_panel(msgs: np.ndarray, height: int, step: int, reward: float) -> np.ndarray:
    """(H, W, 3) uint8: one bar group per agent, its message components in [-1, 1]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n, m = msgs.shape
    fig, ax = plt.subplots(figsize=(height / 100 * 0.8, height / 100), dpi=100)
    width = 0.8 / max(m, 1)
    for j in range(m):
        ax.bar(np.arange(n) + (j - (m - 1) / 2) * width, msgs[:, j], width, label=f"u[{j}]")
    ax.set_ylim(-1.05, 1.05)
    ax.axhline(0, color="black", linewidth=0.6)
    if n <= 3:
        ax.set_xticks(range(n), [f"agent {i}" for i in range(n)])
    else:  # "agent i" labels would overlap
        ax.set_xticks(range(n), [str(i) for i in range(n)])
        ax.set_xlabel("agent", fontsize=8)
    ax.set_title(f"messages, step {step}\nstep reward {reward:+.2f}", fontsize=9)
    if m:
        ax.legend(fontsize=7, loc="lower right")
    else:
        ax.text(0.5, 0.5, "no messages (variant without them)", ha="center", transform=ax.transAxes)
    fig.tight_layout()
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img


def _side_by_side(frame: np.ndarray, panel: np.ndarray) -> np.ndarray:
    h = max(frame.shape[0], panel.shape[0])
    pad = [np.pad(a, ((0, h - a.shape[0]), (0, 0), (0, 0)), constant_values=255) for a in (frame, panel)]
    return np.concatenate(pad, axis=1).astype(np.uint8)


# ----- the warehouse, drawn here ---------------------------------------------------------------------
CELL = 30  # pixels per warehouse cell
LEGEND = 14  # pixels per legend line under the floor
_ROBOT_COLOURS = ((230, 120, 20), (40, 150, 60), (150, 60, 200), (200, 40, 90), (30, 120, 200), (120, 90, 40))
_ARROW = {0: (0, -1), 1: (0, 1), 2: (-1, 0), 3: (1, 0)}  # rware's Direction: UP, DOWN, LEFT, RIGHT


def warehouse_frame(wh, sensor_range: int) -> np.ndarray:
    """(H, W, 3) uint8 picture of one rware `Warehouse`: goal cells dark, shelves blue (requested: red),
    robots as numbered discs with their heading (filled dark when carrying a shelf), each robot's
    (2·sensor_range+1)² window outlined in its colour."""
    from PIL import Image, ImageDraw

    rows, cols = wh.grid_size
    img = Image.new("RGB", (cols * CELL + 1, rows * CELL + 1 + 2 * LEGEND), (255, 255, 255))
    d = ImageDraw.Draw(img)
    d.text((3, rows * CELL + 3), "red: requested shelf, dark: goal", fill=(0, 0, 0))
    d.text((3, rows * CELL + 3 + LEGEND), "box: what a robot sees (dark disc: loaded)", fill=(0, 0, 0))
    box = lambda x, y, pad=0: (x * CELL + pad, y * CELL + pad, (x + 1) * CELL - pad, (y + 1) * CELL - pad)
    for x in range(cols + 1):
        d.line((x * CELL, 0, x * CELL, rows * CELL), fill=(225, 225, 225))
    for y in range(rows + 1):
        d.line((0, y * CELL, cols * CELL, y * CELL), fill=(225, 225, 225))
    for gx, gy in wh.goals:
        d.rectangle(box(gx, gy), fill=(60, 60, 60))
    requested = {sh.id for sh in wh.request_queue}
    for sh in wh.shelfs:
        d.rectangle(box(sh.x, sh.y, 4), fill=(220, 50, 50) if sh.id in requested else (90, 130, 200))
    for k, a in enumerate(wh.agents):
        c = _ROBOT_COLOURS[k % len(_ROBOT_COLOURS)]
        r = sensor_range
        x0, y0 = max(a.x - r, 0) * CELL + 1, max(a.y - r, 0) * CELL + 1  # the window, clipped to the floor
        x1, y1 = min(a.x + r + 1, cols) * CELL - 1, min(a.y + r + 1, rows) * CELL - 1
        d.rectangle((x0, y0, x1, y1), outline=c, width=2)
        d.ellipse(box(a.x, a.y, 6), fill=tuple(v // 2 for v in c) if a.carrying_shelf is not None else c,
                  outline=(0, 0, 0))
        cx, cy = (a.x + 0.5) * CELL, (a.y + 0.5) * CELL
        dx, dy = _ARROW[a.dir.value]
        d.line((cx, cy, cx + dx * CELL * 0.45, cy + dy * CELL * 0.45), fill=(0, 0, 0), width=3)
        d.text((a.x * CELL + 3, a.y * CELL + 1), str(k), fill=(0, 0, 0))
    return np.asarray(img)


def _warehouse_episodes(cfg, spec, episodes: int, max_steps: int, act):
    """(frame, messages (N, M), mean step reward, episode, step from 1) per step of `episodes` episodes of
    hammer's own rware env (one copy, reset with seed + episode like the PettingZoo path), acting with
    `act(obs, prev)`."""
    from hammer.envs.registry import make_vec_env
    from hammer.learning.central_acting import zero_prev_actions
    from hammer.learning.rollout import next_prev_actions

    env = make_vec_env(cfg.env, cfg.n_agents, 1, env_kwargs=cfg.env_kwargs or None)
    sr = env.settings.sensor_range
    try:
        for ep in range(episodes):
            obs, _ = env.reset(cfg.seed + ep)
            prev = zero_prev_actions(spec, 1)
            for t in range(1, min(max_steps, spec.max_steps) + 1):
                frame = warehouse_frame(env.envs[0], sr)
                actions, msgs = act(obs, prev)
                step = env.step(actions)
                yield frame, msgs, float(step.reward.mean()), ep, t
                prev, obs = next_prev_actions(spec, actions, step).prev, step.obs
    finally:
        env.close()


def team(bundle, seed: int | None = None, num_envs: int = 1):
    """(cfg, spec, local agents, messages) of the bundle's frozen team, acting as a fleet's robots and
    central agent do (numpy forwards, the runtime's random streams): `messages(obs, prev, present=None,
    site=None)` -> (K, N, M), the central agent's state built by `CentralActing.global_state` with the
    missing rule (`present`, (K, N) bool) and the site feed's silent rule (`site`, (L, (K,) bool)) as a
    fleet's central agent applies them; `means`: the messages' means, not what is sent (rl: a draw)."""
    from hammer.learning.central_acting import CentralActing
    from hammer.learning.numpy_policy import numpy_central
    from hammer.learning.sampling import ActingStreams
    from hammer.local_agent.client import AgentSpec, LocalAgent
    from safetensors.numpy import load as load_safetensors

    cfg = bundle.config(msg_dropout=0.0, num_envs=num_envs, **({} if seed is None else {"seed": seed}))
    spec, w = bundle.env_spec(), cfg.wiring
    local_blob = (bundle.path / "local.safetensors").read_bytes()
    agents = [LocalAgent(AgentSpec.from_config(cfg, spec, i)) for i in range(cfg.n_agents)]
    for a in agents:
        a.load_weights(local_blob, 0)
    acting, streams = CentralActing.from_config(cfg), ActingStreams(cfg.seed, cfg.n_agents)
    net = (numpy_central(load_safetensors((bundle.path / "central.safetensors").read_bytes()))
           if w.has_central_network else None)

    def messages(obs: np.ndarray, prev: np.ndarray, present: np.ndarray | None = None,
                 site: tuple[int, np.ndarray] | None = None, means: bool = False) -> np.ndarray:
        out = acting.messages(acting.global_state(obs, prev, present, site), streams, 0.0,
                              net.message_mean if net is not None else None,
                              net.values if net is not None and acting.rl else None)
        return out.mean if means else out.sent

    return cfg, spec, agents, messages


def play(bundle, out: Path, episodes: int = 3, seed: int | None = None, max_steps: int = 200,
         fps: float = 8.0, stills: int = 4, progress=None) -> dict:
    """Render `episodes` episodes of the bundle's team into the GIF `out` (a *.png: a sheet of `stills`
    frames spread over them); returns what was played. `progress(line)`: a line as each episode ends
    (drawing a frame takes a good part of a second: a warehouse episode is a minute)."""
    from hammer.envs.rware_vec import is_rware
    from hammer.learning.central_acting import encode_actions, zero_prev_actions
    from PIL import Image

    kind = Path(out).suffix.lower()
    if kind not in (".gif", ".png"):
        raise PlayError(f"--out {out}: play writes a GIF (or a PNG sheet of still frames); fix: name it *.gif or *.png")
    cfg, spec, agents, messages = team(bundle, seed)
    w = cfg.wiring

    frames: list[np.ndarray] = []
    t_start = [time.monotonic()]

    def ended(ep: int, steps: int, ret: float) -> None:
        if progress is not None:
            progress(f"episode {ep + 1}/{episodes}: {steps} steps, paper metric {ret:.2f} "
                     f"({time.monotonic() - t_start[0]:.0f} s)")
        t_start[0] = time.monotonic()

    if is_rware(cfg.env):
        from hammer.envs.local_view import local_view_from_config

        view = local_view_from_config(cfg, spec)

        def act(obs: np.ndarray, prev: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            msgs = messages(obs, prev)  # the central agent sees every row whole, as on the wire
            seen = obs.reshape(1, -1) if w.joint_obs else view(obs)
            acts = [a.act(seen if w.joint_obs else seen[:, i], msgs[:, i] if w.msg_dim else None)[0]
                    for i, a in enumerate(agents)]
            return np.array(acts)[None], msgs[0]

        returns = [0.0] * episodes
        last = min(max_steps, spec.max_steps)
        for frame, msgs, r, ep, t in _warehouse_episodes(cfg, spec, episodes, max_steps, act):
            returns[ep] += r
            frames.append(_side_by_side(frame, message_panel(msgs, max(frame.shape[0], 240), t, r)))
            if t == last:
                ended(ep, t, returns[ep])
    else:
        env, keep = render_env(cfg.env, cfg.n_agents, cfg.env_kwargs or {})
        returns = []
        try:
            for ep in range(episodes):
                obs_d, _ = env.reset(seed=cfg.seed + ep)
                prev, ret, t = zero_prev_actions(spec, 1), 0.0, 0
                while env.agents and t < max_steps:
                    t += 1
                    present = np.array([[aid in obs_d for aid in spec.agent_ids]])
                    obs = np.stack([np.asarray(obs_d[aid], np.float32)[:keep] if aid in obs_d
                                    else np.zeros(spec.obs_dim, np.float32) for aid in spec.agent_ids])[None]
                    msgs = messages(obs, prev)
                    joint = obs.reshape(1, -1)
                    acts = [a.act(joint if w.joint_obs else obs[:, i], msgs[:, i] if w.msg_dim else None)[0]
                            for i, a in enumerate(agents)]
                    act_arr = np.array(acts)[None]
                    frame = env.render()
                    step = {aid: (int(acts[i]) if spec.discrete else np.clip(acts[i], spec.action_low,
                                                                              spec.action_high))
                            for i, aid in enumerate(spec.agent_ids) if aid in env.agents}
                    obs_d, rew, _, _, _ = env.step(step)
                    r = float(np.mean(list(rew.values()))) if rew else 0.0
                    ret += r
                    frames.append(_side_by_side(frame, message_panel(msgs[0], frame.shape[0], t, r)))
                    prev = encode_actions(spec, act_arr, present)
                returns.append(ret)
                ended(ep, t, ret)
        finally:
            env.close()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if kind == ".png":
        sheet = still_sheet(frames, stills)
        Image.fromarray(sheet).save(out)
        return {"frames": len(frames), "episodes": episodes, "paper_metric": returns, "size": sheet.shape[1::-1]}
    imgs = [Image.fromarray(f) for f in frames]
    imgs[0].save(out, save_all=True, append_images=imgs[1:], duration=int(1000 / fps), loop=0, optimize=False)
    return {"frames": len(frames), "episodes": episodes, "paper_metric": returns, "size": imgs[0].size}


def still_sheet(frames: list[np.ndarray], stills: int = 4, columns: int = 2) -> np.ndarray:
    """`stills` frames spread evenly over the played steps (never the first: nothing has happened
    yet), `columns` to a row, as one picture for a document."""
    if not frames:
        raise PlayError("no frames were played; fix: --max-steps 1 or more")
    k = min(stills, len(frames))
    picks = [round((j + 1) * (len(frames) - 1) / k) for j in range(k)]
    h, w = max(f.shape[0] for f in frames), max(f.shape[1] for f in frames)
    rows = -(-k // columns)
    sheet = np.full((rows * h, min(k, columns) * w, 3), 255, np.uint8)
    for j, i in enumerate(picks):
        f = frames[i]
        r, c = divmod(j, columns)
        sheet[r * h:r * h + f.shape[0], c * w:c * w + f.shape[1]] = f
    return sheet
