"""Draw docs/results/mw3-branches.png/.svg: mw3 IL seed 1 (the archived run) and three
continuations of it from its checkpoint at episode 2,102, each with one change.

Run from the repository root: `.venv/bin/python docs/results/mw3_branches.py`.
How the branches were made is in docs/results/README.md ("Branching one run at its peak").
"""

import numpy as np
from hammer.experiments.plot import save_figure
from hammer.experiments.runs import load_run, rolling_mean
from hammer.experiments.train_stats import load_train_stats

BRANCH_AT = 2102
RUNS = [("control: the archived run", "docs/results/runs/mw3/mw3-il-s1"),
        ("seed=7 (env seeds only)", "docs/results/runs/mw3-branches/il-s1-seed7"),
        ("ent_coef=0.01", "docs/results/runs/mw3-branches/il-s1-ent01"),
        ("lr_local=1e-4", "docs/results/runs/mw3-branches/il-s1-lr1e-4")]


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for name, d in RUNS:
        m = load_run(d).paper_metric[:3500]
        x = np.arange(1, len(m) + 1)
        axes[0].plot(x[1500:], rolling_mean(m, 200)[1500:], lw=1.2, label=name)
        ep, v = load_train_stats(d)["train/local/entropy"]
        keep = (ep > 1500) & (ep <= 3500)
        axes[1].plot(ep[keep], v[keep], lw=1.2)
    for ax in axes:
        ax.axvline(BRANCH_AT, color="k", lw=0.8, ls=":")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("paper metric (rolling 200)")
    axes[1].set_ylabel("local policy entropy")
    axes[1].set_xlabel(f"episode (branches start at {BRANCH_AT:,}, the checkpoint before the best rolling-500 point)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    for p in save_figure(fig, "docs/results/mw3-branches", dpi=110):
        print(f"wrote {p}")


if __name__ == "__main__":
    main()
