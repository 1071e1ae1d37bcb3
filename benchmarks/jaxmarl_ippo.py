"""JaxMARL's IPPO-FF on MPE simple spread, timed: run by `hammer bench peers` in JaxMARL's own venv.

    PYTHON_OF_THE_JAX_VENV jaxmarl_ippo.py REPO SCHEDULE TOTAL_TIMESTEPS

This file imports nothing of hammer (the jax venv has no hammer): it loads
`REPO/baselines/IPPO/ippo_ff_mpe.py` (the public FLAIROx/JaxMARL repository; the pip package does not
ship its baselines) as it is, with its config file, and overrides only the schedule: `defaults`
keeps the YAML's (16 envs x 128 steps, 4 epochs x 4 minibatches, gamma 0.99), `hammer` is hammer's
cn3 preset (32 envs x 25 steps, 8 epochs x 4 minibatches, gamma 0.95, lr 3e-4, no annealing). The
baseline's module imports wandb, hydra, omegaconf and matplotlib for its `main`, which is not
called; where they are not installed, empty stand-ins take their names (wandb.log does nothing,
as in its own disabled mode). Prints one JSON line: env steps (one step of the team in one env
copy), compile seconds, run seconds, the rate, and the mean episode return over the last 10 % of
updates.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import time
import types
from pathlib import Path


def _stand_ins() -> None:
    for name in ("wandb", "hydra", "omegaconf", "matplotlib", "matplotlib.pyplot"):
        try:
            __import__(name)
        except ImportError:
            m = types.ModuleType(name)
            m.log = m.init = lambda *a, **k: None
            m.main = lambda *a, **k: (lambda f: f)
            m.OmegaConf = types.SimpleNamespace(to_container=lambda c: c)
            sys.modules[name] = m
    if "matplotlib" in sys.modules and not hasattr(sys.modules["matplotlib"], "pyplot"):
        sys.modules["matplotlib"].pyplot = sys.modules["matplotlib.pyplot"]


def _yaml(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text())


def main() -> None:
    repo, schedule, total = Path(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    _stand_ins()
    spec = importlib.util.spec_from_file_location("ippo_ff_mpe", repo / "baselines/IPPO/ippo_ff_mpe.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import jax

    config = _yaml(repo / "baselines/IPPO/config/ippo_ff_mpe.yaml")
    if schedule == "hammer":
        config.update({"NUM_ENVS": 32, "NUM_STEPS": 25, "UPDATE_EPOCHS": 8, "NUM_MINIBATCHES": 4, "GAMMA": 0.95,
                       "GAE_LAMBDA": 0.95, "LR": 3e-4, "ANNEAL_LR": False})
    config["TOTAL_TIMESTEPS"] = total
    train = jax.jit(mod.make_train(config))
    rng = jax.random.PRNGKey(int(config["SEED"]))
    t0 = time.perf_counter()
    compiled = train.lower(rng).compile()
    t1 = time.perf_counter()
    out = jax.block_until_ready(compiled(rng))
    t2 = time.perf_counter()
    steps = int(config["NUM_UPDATES"]) * int(config["NUM_STEPS"]) * int(config["NUM_ENVS"])
    returns = out["metrics"]["returned_episode_returns"]
    tail = max(1, returns.shape[0] // 10)
    print(json.dumps({"system": "jaxmarl", "schedule": schedule, "jax": jax.__version__, "env_steps": steps,
                      "compile_s": round(t1 - t0, 2), "run_s": round(t2 - t1, 3),
                      "env_steps_per_s": round(steps / (t2 - t1), 1),
                      "num_envs": config["NUM_ENVS"], "num_steps": config["NUM_STEPS"],
                      "final_return_mean": float(returns[-tail:].mean())}))


if __name__ == "__main__":
    main()
