"""`mmpgo info` on every benchmark file reports d, n, m as in the data folder's README.txt."""

import re

import pytest
from conftest import data_dir

from mmpgo_jax.cli import main


def _readme_table():
    d = data_dir()
    if d is None or not (d / "README.txt").is_file():
        pytest.skip("benchmark data folder with README.txt not available (set MMPGO_DATA)")
    rows = {}
    for line in (d / "README.txt").read_text().splitlines():
        m = re.match(r"^(\S+\.g2o)\s+(\d)\s+(\d+)\s+(\d+)\s", line)
        if m and (d / m.group(1)).is_file():
            rows[m.group(1)] = tuple(int(x) for x in m.groups()[1:])
    assert rows, "README.txt table not found"
    return d, rows


def test_info_reports_readme_sizes(capsys):
    d, rows = _readme_table()
    for name, (dim, n, m) in rows.items():
        assert main(["info", str(d / name)]) == 0
        out = capsys.readouterr().out
        assert f"d = {dim}" in out, name
        assert re.search(rf"n = {n}\b", out), name
        assert f"m = {m}" in out, name
        assert "graph       connected" in out, name


def test_info_partition_table(capsys, benchmark_file):
    path = benchmark_file("MIT.g2o")
    assert main(["info", str(path), "--robots", "10"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if re.match(r"^\s+\d+\s+\d+\s+\d+\s+\d+\s+\d+", ln)]
    assert len(lines) == 10
    poses = [int(ln.split()[1]) for ln in lines]
    assert poses == [81] * 8 + [80] * 2  # docs/conventions.md §4: the first n mod A robots get one more


def test_info_bad_file_is_one_line_error(capsys):
    from pathlib import Path

    bad = Path(__file__).parent / "data" / "bad" / "self_loop.g2o"
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mmpgo: error: ") and "self_loop.g2o:3:" in err and "Traceback" not in err
