"""One plot per graph of the robust study: the files (``robust_distributed_files.py``) and the
long-chain robot teams (``robust_teams.py``), each against the outlier rate.

    python benchmarks/robust_study_plot.py --files-json F.json --teams-json T10.json T30.json ...
        [--out benchmarks/robust_study.png]

Per graph (a column): precision and recall of the rejected edges against the planted outliers
(top two rows; 1 is exact), and the accuracy the robot-teams issue asks for (bottom row): for a file,
the ATE against the outlier-free optimum in percent of the map's extent (must show: <= 1 %); for a
team, the ATE against the ground truth over the outlier-free optimum's (must show: <= 1.5x). One
marker per seed, a line through the median; the pipelines: the default (both starts, the lower robust
objective kept), the fully distributed one (``distributed=True``: with the team check, its default
since 2026-12-08, and the rows before without it), PCM then the fully distributed one
(``prefilter="pcm", distributed=True``; with PCM's ties broken as published, and with them kept:
``PCM(ties="keep")``), and GTSAM's GNC (TLS, from the centralized chordal start), a reference
outside this package. Nothing is solved here.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

PIPELINES = {  # the files' pipeline name, the teams' method name, the label
    "default": ("default", "tls", "default (both starts)"),
    "distributed": ("distributed", "dist-tls", "fully distributed, no team check (until 2026-12-07)"),
    "pcm-distributed": ("pcm-distributed", "dist-pcm+tls", "PCM + fully distributed"),
    "pcmties-distributed": ("pcmties-distributed", "dist-pcmties+tls", "PCM (ties kept) + fully distributed"),
    "gtsam": ("gtsam", "gtsam", "GTSAM's GNC (reference)"),
    "distributed-checked": ("distributed-checked", "dist-tls-checked", "fully distributed (team check, default)"),
}
ORDER = list(PIPELINES)  # colours and offsets per pipeline, the same in every panel
ATE_FLOOR = 1e-9  # exact rows (ATE ~1e-11 % of the extent) drawn at this floor of the log axis
SCORE_FLOOR = 0.5  # precision / recall below it drawn at it as a triangle, so that one-closure misses stay visible


def file_points(saved: dict) -> dict:
    """{file: {pipeline: [(rate, seed, precision, recall, ATE % of extent)]}} of the files' rows."""
    out: dict = {}
    names = {v[0]: k for k, v in PIPELINES.items()}
    for row in saved.values():
        if row.get("pipeline") in names:
            out.setdefault(row["file"], {}).setdefault(names[row["pipeline"]], []).append(
                (row["rate"], row["seed"], row["precision"], row["recall"], row["ate_percent"]))
    return out


def team_points(runs: list[dict]) -> dict:
    """{team label: {pipeline: [(rate, seed, precision, recall, ATE vs truth / optimum's)]}} of the
    teams' runs (one rate per run)."""
    out: dict = {}
    names = {v[1]: k for k, v in PIPELINES.items()}
    for run in runs:
        meta = run["meta"]
        noise = "low noise" if meta.get("noise", {}).get("sigma_R") else "Cube noise"
        label = f"team {meta['robots']} x {meta['poses']}, {noise},\n{meta['inter']} inter-robot closures" + \
            ("" if meta.get("rate_of") == "inter" else " (rate of all closures)")
        optimum = {r["seed"]: r["ate_gt"] for r in run["rows"] if r["method"].startswith("optimum")}
        for r in run["rows"]:
            if r["method"] in names:
                out.setdefault(label, {}).setdefault(names[r["method"]], []).append(
                    (meta["rate"], r["seed"], r["precision"], r["recall"], r["ate_gt"] / optimum[r["seed"]]))
    return out


def _panel(ax, series: dict, column: int, log: bool) -> None:
    for name, points in series.items():
        k = ORDER.index(name)
        at = np.array([p[0] for p in points], float)
        raw = np.array([p[column] for p in points], float)
        floor = ATE_FLOOR if log else SCORE_FLOOR
        values = np.maximum(raw, floor)
        below = (raw < floor) & (not log)  # an exact ATE keeps its circle
        offset = k - (len(ORDER) - 1) / 2  # the pipelines side by side
        ax.plot(at[~below] + offset, values[~below], "o", color=f"C{k}", alpha=0.6, ms=4)
        ax.plot(at[below] + offset, values[below], "v", color=f"C{k}", alpha=0.6, ms=5)
        rates = np.unique(at)
        ax.plot(rates, [np.median(values[at == r]) for r in rates], "-", color=f"C{k}", label=PIPELINES[name][2])
    if log:
        ax.set_yscale("log")
    ax.set_xticks(sorted({p[0] for points in series.values() for p in points}))


def plot(graphs: dict, kinds: dict, out: Path) -> None:
    """``graphs``: {title: {pipeline: points}}; ``kinds``: {title: "file" | "team"}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mmpgo_jax._io.atomic import atomic_write

    fig, axes = plt.subplots(3, len(graphs), figsize=(3.4 * len(graphs), 8.0), squeeze=False, sharex="col")
    for c, (title, series) in enumerate(graphs.items()):
        team = kinds[title] == "team"
        for r, (column, name) in enumerate(((2, "precision"), (3, "recall"))):
            _panel(axes[r, c], series, column, log=False)
            lowest = min(p[column] for points in series.values() for p in points)
            axes[r, c].set_ylim(max(SCORE_FLOOR, min(0.9, lowest - 0.02)) - 0.01, 1.005)
            axes[r, c].set_ylabel(name if c == 0 else "")
        _panel(axes[2, c], series, 4, log=True)  # a reference's misses reach 10-100x the must-show
        bound = 1.5 if team else 1.0
        axes[2, c].axhline(bound, color="k", lw=0.8, ls=":")
        axes[2, c].set_ylabel("ATE vs truth / optimum's" if team else "ATE vs optimum, % of extent")
        axes[2, c].set_xlabel("wrong, % of inter-robot closures")
        axes[0, c].set_title(title, fontsize=9)
    legend = {}  # one legend for the figure, every pipeline drawn in some panel
    for ax in axes.flat:
        handles, labels = ax.get_legend_handles_labels()
        legend.update(zip(labels, handles, strict=True))
    labels = [v[2] for v in PIPELINES.values() if v[2] in legend]  # in ORDER, as the colours
    fig.legend([legend[label] for label in labels], labels, loc="lower center", ncol=len(labels), fontsize=9)
    fig.suptitle(f"markers: seeds; lines: medians; dotted: the must-show bound; an ATE below {ATE_FLOOR:g} % "
                 f"of the extent (exact) drawn at it; triangles: precision or recall below {SCORE_FLOOR:g} "
                 "drawn at it",
                 fontsize=9)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    with atomic_write(out, "wb") as fh:
        fig.savefig(fh, format="png", dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--files-json", type=Path, required=True)
    p.add_argument("--teams-json", type=Path, nargs="*", default=[])
    p.add_argument("--out", type=Path, default=Path(__file__).with_name("robust_study.png"))
    args = p.parse_args(argv)
    graphs, kinds = {}, {}
    for name, series in file_points(json.loads(args.files_json.read_text())).items():
        graphs[name], kinds[name] = series, "file"
    runs = [run for path in args.teams_json for run in json.loads(path.read_text())["runs"]]
    for name, series in team_points(runs).items():
        graphs[name], kinds[name] = series, "team"
    plot(graphs, kinds, args.out)
    print(f"wrote {args.out}: {len(graphs)} graphs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
