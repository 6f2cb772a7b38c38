"""benchmarks/robust_study_plot.py, the robust study's plot per graph: the rows of both benchmark
scripts' JSON formats land in the right graph and pipeline, and the figure is written."""

import json

from repo_scripts import load_script


def _module():
    return load_script("benchmarks/robust_study_plot.py")


def _file_row(file, rate, seed, pipeline, ate):
    return dict(file=file, rate=rate, seed=seed, pipeline=pipeline, precision=1.0, recall=0.9, ate_percent=ate)


def test_rows_are_grouped_per_graph_and_pipeline_and_the_figure_written(tmp_path):
    study = _module()
    files = {f"MIT|{r}|1|{p}": _file_row("MIT", r, 1, p, a)
             for r, p, a in ((10, "default", 1e-11), (30, "distributed", 0.02), (30, "gtsam", 5.0),
                             (30, "central", 0.1))}
    points = study.file_points(files)
    assert set(points) == {"MIT"} and set(points["MIT"]) == {"default", "distributed", "gtsam"}  # not "central"
    assert points["MIT"]["distributed"] == [(30, 1, 1.0, 0.9, 0.02)]
    # a team's accuracy: ATE against the truth over the outlier-free optimum's, seed by seed
    meta = dict(robots=10, poses=500, inter=30, rate=30, rate_of="inter", noise=dict(sigma_R=0.0157))
    rows = [dict(seed=0, method="optimum (no outliers)", ate_gt=2.0),
            dict(seed=0, method="dist-tls", precision=0.5, recall=1.0, ate_gt=3.0),
            dict(seed=0, method="pcm", precision=0.1, recall=0.1, ate_gt=9.0),
            dict(seed=0, method="dist-pcm+tls", precision=0.2, recall=1.0, ate_gt=4.0)]
    teams = study.team_points([dict(meta=meta, rows=rows)])
    ((label, series),) = teams.items()
    assert "low noise" in label and "inter-robot" in label
    assert series == {"distributed": [(30, 0, 0.5, 1.0, 1.5)], "pcm-distributed": [(30, 0, 0.2, 1.0, 2.0)]}
    files_json, teams_json = tmp_path / "files.json", tmp_path / "teams.json"
    files_json.write_text(json.dumps(files))
    teams_json.write_text(json.dumps(dict(runs=[dict(meta=meta, rows=rows)])))
    out = tmp_path / "study.png"
    assert study.main(["--files-json", str(files_json), "--teams-json", str(teams_json), "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
