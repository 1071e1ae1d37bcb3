"""Print the tables of docs/results/faults-ownobs/README.md from the faults sweeps' CSVs: per
training seed, the cn3-ownobs HAMMER team (rl mode: `hammer/`, backprop mode: `hammer-backprop/`)
evaluated with its messages and with every message cut, and the IL team of the same seed; then
the means over seeds and the tests.

Run from the repository root: `.venv/bin/python docs/results/faults_ownobs.py`.
How the sweeps were made is in docs/results/faults-ownobs/README.md.
"""

from pathlib import Path

import numpy as np
from hammer.experiments.fault_sweep import aggregate, read_results
from hammer.experiments.report import sem
from scipy import stats

HERE = Path(__file__).parent / "faults-ownobs"


def load(sweep: str) -> dict:
    """`faults.sweep.aggregate` of one sweep directory under faults-ownobs/."""
    return aggregate(read_results(HERE / sweep / "sweep.csv"))


def per_seed(agg: dict, drop: float) -> dict[int, float]:
    """Training seed (the `-sN` of a team label) -> mean paper metric over the evaluation seeds at
    this drop rate, no delay."""
    return {int(team.rsplit("-s", 1)[1]): a["mean"] for (team, d, delay), a in sorted(agg.items())
            if d == drop and delay == 0}


def table(team: str, il: dict[int, float]) -> None:
    """One team kind (a sweep directory under faults-ownobs/) against the IL team of each seed."""
    agg = load(team)
    with_msgs, cut = per_seed(agg, 0.0), per_seed(agg, 1.0)
    seeds = sorted(set(with_msgs) & set(cut) & set(il))
    a, b, c = (np.array([d[s] for s in seeds]) for d in (with_msgs, cut, il))
    print(f"| training seed | {team}, messages | {team}, messages cut | IL |")
    print("|---|---|---|---|")
    for s, x, y, z in zip(seeds, a, b, c):
        print(f"| {s} | {x:.2f} | {y:.2f} | {z:.2f} |")
    print(f"| mean ± s.e. ({len(seeds)} seeds) | {a.mean():.2f} ± {sem(a):.2f} | {b.mean():.2f} ± {sem(b):.2f} "
          f"| {c.mean():.2f} ± {sem(c):.2f} |")
    print()
    print(f"- cutting the messages: {np.mean(b - a):+.2f} ± {sem(b - a):.2f} (paired t-test "
          f"p = {stats.ttest_rel(a, b).pvalue:.2g}; worse on {int(np.sum(b < a))} of {len(seeds)} seeds)")
    print(f"- {team} with messages against IL: {np.mean(a - c):+.2f}, Welch p = "
          f"{stats.ttest_ind(a, c, equal_var=False).pvalue:.2g}")
    print(f"- {team} with messages cut against IL: {np.mean(b - c):+.2f}, Welch p = "
          f"{stats.ttest_ind(b, c, equal_var=False).pvalue:.2g}")
    print()


def main() -> None:
    il = per_seed(load("il"), 0.0)
    for team in ("hammer", "hammer-backprop"):
        if (HERE / team / "sweep.csv").is_file():
            table(team, il)


if __name__ == "__main__":
    main()
