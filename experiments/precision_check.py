"""Does precision=bf16 learn as well as float32? bf16 runs' final paper metric against float32 runs'.

For each pair of groups (the same setting and variant, seeds 0-4, float32 and bf16): each run's
final performance (`report.final_performance`: the mean paper metric of its last `last` episodes),
cut at `episodes` first (a run with a constant learning rate cut at E episodes is the run with
budget E, so archived full-length runs compare with shorter bf16 ones), then the groups' IQMs
with the float32 group's stratified bootstrap CI (`stats.iqm_ci`). A bf16 IQM outside that CI is
said plainly: `inside` false.

    python -m hammer.experiments.precision_check --episodes 1000 --out docs/results/precision-bf16.json \\
        cn3=docs/results/runs/cn3:/tmp/bf16grid/cn3 ...   (NAME=FP32_DIR:BF16_DIR, runs matched by label)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from hammer.experiments.report import final_performance
from hammer.experiments.runs import Run, find_runs, load_run
from hammer.experiments.stats import iqm, iqm_ci


def _cut(run: Run, episodes: int) -> Run:
    if len(run.paper_metric) < episodes:
        raise ValueError(f"{run.path}: {len(run.paper_metric)} episodes, fewer than the {episodes} compared")
    return dataclasses.replace(run, episodes=run.episodes[:episodes], paper_metric=run.paper_metric[:episodes],
                               team_return=run.team_return[:episodes])


def compare(fp32_dir: Path, bf16_dir: Path, episodes: int, last: int) -> list[dict]:
    """One row per run label found under both directories."""
    groups: dict[str, dict[str, list[Run]]] = {}
    for side, root in (("fp32", fp32_dir), ("bf16", bf16_dir)):
        for path in find_runs([root]):
            run = load_run(path)
            if run.config.get("precision", "fp32") != side:
                raise ValueError(f"{path}: precision {run.config.get('precision', 'fp32')}, expected {side}")
            groups.setdefault(run.label, {}).setdefault(side, []).append(_cut(run, episodes))
    rows = []
    for label, sides in sorted(groups.items()):
        if set(sides) != {"fp32", "bf16"}:
            continue
        fin = {s: [final_performance(r, last) for r in sorted(rs, key=lambda r: r.seed)] for s, rs in sides.items()}
        m32, lo, hi = iqm_ci(fin["fp32"])
        m16 = float(iqm(fin["bf16"]))
        rows.append({"label": label, "seeds": {s: sorted(r.seed for r in rs) for s, rs in sides.items()},
                     "final": fin, "fp32_iqm": m32, "fp32_ci": [lo, hi], "bf16_iqm": m16,
                     "bf16_ci": list(iqm_ci(fin["bf16"])[1:]), "inside": lo <= m16 <= hi,
                     "bf16_not_worse": m16 >= lo})
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("pairs", nargs="+", help="NAME=FP32_DIR:BF16_DIR")
    ap.add_argument("--episodes", type=int, required=True, help="compare the first E episodes of every run")
    ap.add_argument("--last", type=int, default=500, help="final performance: mean of the last L of those")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    result = {"episodes": a.episodes, "last": a.last, "settings": {}}
    for pair in a.pairs:
        name, dirs = pair.split("=", 1)
        fp32, bf16 = dirs.split(":", 1)
        result["settings"][name] = rows = compare(Path(fp32), Path(bf16), a.episodes, a.last)
        for r in rows:
            print(f"{name:12s} {r['label']:16s} fp32 IQM {r['fp32_iqm']:8.3f} CI [{r['fp32_ci'][0]:.3f}, "
                  f"{r['fp32_ci'][1]:.3f}]  bf16 IQM {r['bf16_iqm']:8.3f}  "
                  f"{'inside' if r['inside'] else ('ABOVE' if r['bf16_not_worse'] else 'BELOW')} the fp32 CI")
    if a.out is not None:
        a.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
