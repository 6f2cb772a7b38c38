"""The benchmark registry and data-directory resolution."""

import re
from pathlib import Path

import pytest

import mmpgo_jax._io.datasets as dsm
from mmpgo_jax._io.datasets import (
    BENCHMARKS,
    BenchmarkInfo,
    DatasetNotFoundError,
    available_benchmarks,
    benchmark_info,
    data_dir,
    find_benchmark,
)

SHARED = Path(dsm.__file__).resolve().parents[2].parent / "shared" / "datasets"  # beside the repository
ITERS = {100, 250, 1000}


def _shared_or_skip() -> Path:
    if not SHARED.is_dir():
        pytest.skip("shared/datasets not present")
    return SHARED


def _readme_table(path: Path) -> dict[str, tuple[int, int, int]]:
    rows = {}
    for line in path.read_text().splitlines():
        m = re.match(r"^(\S+\.g2o)\s+(\d)\s+(\d+)\s+(\d+)\b", line)
        if m:
            rows[m.group(1)] = tuple(int(x) for x in m.groups()[1:])
    return rows


def _scan_g2o(path: Path) -> tuple[int, int, int]:
    """(d, n = max id + 1, m = number of edges) of a g2o file."""
    dim, max_id, m = None, -1, 0
    with open(path) as fh:
        for line in fh:
            tok = line.split()
            if not tok:
                continue
            tag = tok[0]
            if tag.startswith("EDGE_"):
                m += 1
                max_id = max(max_id, int(tok[1]), int(tok[2]))
                dim = 2 if tag == "EDGE_SE2" else 3
            elif tag.startswith("VERTEX_"):
                max_id = max(max_id, int(tok[1]))
    return dim, max_id + 1, m


# ------------------------------------------------------------------------------- the registry


def test_registry_contents():
    assert len(BENCHMARKS) == 19
    paper = [b for b in BENCHMARKS.values() if b.in_paper]
    assert sorted(b.name for b in paper if b.paper_table == "I") == sorted(
        ["ais2klinik", "city", "CSAIL", "M3500", "intel", "MITb"])
    assert sorted(b.name for b in paper if b.paper_table == "II") == sorted(
        ["sphere", "torus", "grid", "garage", "cubicle", "rim"])
    for b in BENCHMARKS.values():
        assert isinstance(b, BenchmarkInfo)
        assert b.dim == (2 if b.paper_table == "I" else 3) or not b.in_paper
        assert b.availability in {"shipped", "public", "unavailable"}
        assert b.source
        if b.in_paper:
            assert b.paper_fstar is not None
            for tab in (b.paper_mm, b.paper_amm, b.paper_dgs):
                assert set(tab) == ITERS
            # MM and AMM never go below the optimum (DGS has a misprint on rim, see notes)
            for tab in (b.paper_mm, b.paper_amm):
                assert all(v >= b.paper_fstar * (1 - 1e-3) for v in tab.values())
        else:
            assert b.paper_fstar is None and b.paper_mm is None and b.paper_amm is None
    assert {b.name for b in BENCHMARKS.values() if b.availability == "unavailable"} == {"grid", "rim"}
    assert {b.name for b in BENCHMARKS.values() if b.availability == "public"} == {
        "ais2klinik", "cubicle"}


def test_paper_numbers_transcribed():
    mit = BENCHMARKS["MITb"]
    assert (mit.file, mit.dim, mit.num_poses, mit.num_edges) == ("MIT.g2o", 2, 808, 827)
    assert mit.paper_fstar == 6.115e1
    assert dict(mit.paper_mm) == {100: 6.347e1, 250: 6.220e1, 1000: 6.136e1}
    assert dict(mit.paper_amm) == {100: 6.228e1, 250: 6.153e1, 1000: 6.117e1}
    assert dict(mit.paper_dgs) == {100: 9.244e1, 250: 7.453e1, 1000: 6.887e1}
    assert BENCHMARKS["ais2klinik"].paper_mm[100] == 2.012e2
    assert BENCHMARKS["garage"].paper_fstar == 1.263e0
    assert BENCHMARKS["rim"].paper_dgs[100] == 6.114e2  # as printed
    assert BENCHMARKS["cubicle"].paper_amm[1000] == 7.176e2
    assert BENCHMARKS["grid"].paper_fstar == 8.432e4


def test_notes_numbers():
    with_notes = {"MITb", "CSAIL", "intel", "M3500", "city", "sphere", "torus", "garage"}
    assert {b.name for b in BENCHMARKS.values() if b.sesync_fstar is not None} == with_notes
    assert {b.name for b in BENCHMARKS.values() if b.chordal_f is not None} == with_notes
    assert BENCHMARKS["MITb"].sesync_fstar == 61.1541
    assert BENCHMARKS["garage"].chordal_f == 1.4153
    # the best known optimum: our certified one (12 digits), else SE-Sync's, else the paper's
    assert BENCHMARKS["MITb"].fstar == BENCHMARKS["MITb"].ours_fstar == pytest.approx(61.1541, abs=5e-5)
    assert BENCHMARKS["rim"].fstar == 5.461e3
    for name in with_notes:
        b = BENCHMARKS[name]
        # the paper prints f* to 4 digits (garage: 1.262524 printed as 1.263)
        assert b.paper_fstar == pytest.approx(b.sesync_fstar, rel=5e-4)
        assert b.chordal_f >= b.sesync_fstar
    code = {"MITb", "intel", "M3500", "city", "sphere", "torus", "garage"}
    assert {b.name for b in BENCHMARKS.values() if b.code_mm is not None} == code
    for name in code:
        b = BENCHMARKS[name]
        for tab in (b.code_mm, b.code_amm_paper_rule, b.code_amm_adaptive):
            assert set(tab) == ITERS
        # docs/conventions.md §7: the C++ MM reproduces the paper's MM column to 3-4 digits
        for k in ITERS:
            assert b.code_mm[k] == pytest.approx(b.paper_mm[k], rel=3e-3)
        assert b.code_ms_per_iter_mm > 0 and b.code_ms_per_iter_amm > 0
        assert b.code_iters_to_1e_3 > 0
    assert dict(BENCHMARKS["MITb"].code_amm_adaptive) == {100: 61.25, 250: 61.16, 1000: 61.15}
    assert BENCHMARKS["garage"].code_iters_to_1e_3 == 321
    assert BENCHMARKS["city"].code_ms_per_iter_amm == 12.5  # measured 2026-12-01 (docs/conventions.md §7)


def test_registry_matches_readme():
    readme = _shared_or_skip() / "README.txt"
    if not readme.is_file():
        pytest.skip("README.txt not present")
    table = _readme_table(readme)
    assert len(table) == 19
    by_file = {b.file: b for b in BENCHMARKS.values()}
    assert set(table) == set(by_file)
    for f, (d, n, m) in table.items():
        b = by_file[f]
        assert (b.dim, b.num_poses, b.num_edges) == (d, n, m), f


def test_every_shipped_file_is_registered_with_matching_sizes():
    folder = _shared_or_skip()
    files = sorted(folder.glob("*.g2o"))
    if not files:
        pytest.skip("no .g2o files in shared/datasets")
    by_file = {b.file: b for b in BENCHMARKS.values()}
    for f in files:
        assert f.name in by_file, f"{f.name} missing from the registry"
        b = by_file[f.name]
        assert _scan_g2o(f) == (b.dim, b.num_poses, b.num_edges), f.name
        assert b.availability == "shipped"
    shipped = {b.file for b in BENCHMARKS.values() if b.availability == "shipped"}
    assert shipped == {f.name for f in files}


# --------------------------------------------------------------------------- lookup + data dir


@pytest.fixture
def fake_data(tmp_path, monkeypatch):
    monkeypatch.delenv("MMPGO_DATA", raising=False)
    for name in ("MIT.g2o", "parking-garage.g2o", "extra_thing.g2o"):
        (tmp_path / name).write_text("# fake\n")
    (tmp_path / "TORUS3D.G2O").write_text("# fake, odd case\n")
    return tmp_path


@pytest.mark.parametrize("query", ["MITb", "mitb", "MIT", "mit", "MIT.g2o", "mIt.G2o"])
def test_find_benchmark_aliases(fake_data, query):
    assert find_benchmark(query, data=fake_data) == fake_data / "MIT.g2o"


def test_find_benchmark_other_forms(fake_data, monkeypatch):
    assert find_benchmark("garage", fake_data) == fake_data / "parking-garage.g2o"
    assert find_benchmark("Parking-Garage", fake_data) == fake_data / "parking-garage.g2o"
    assert find_benchmark("torus", fake_data) == fake_data / "TORUS3D.G2O"  # case-insensitive file
    assert find_benchmark("extra_thing", fake_data) == fake_data / "extra_thing.g2o"  # unregistered
    assert find_benchmark(str(fake_data / "MIT.g2o")) == fake_data / "MIT.g2o"  # explicit path
    monkeypatch.setenv("MMPGO_DATA", str(fake_data))
    assert find_benchmark("MITb") == fake_data / "MIT.g2o"
    assert BENCHMARKS["MITb"].path() == fake_data / "MIT.g2o"
    assert benchmark_info("/some/where/MIT.g2o") is BENCHMARKS["MITb"]
    assert benchmark_info("nope") is None


def test_missing_file_message(fake_data):
    with pytest.raises(DatasetNotFoundError) as exc:
        find_benchmark("CSAIL", data=fake_data)
    assert isinstance(exc.value, FileNotFoundError)
    msg = str(exc.value)
    assert str(fake_data) in msg and "CSAIL.g2o" in msg
    assert "MMPGO_DATA" in msg and "--data" in msg
    assert "github.com/david-m-rosen/SE-Sync" in msg
    with pytest.raises(DatasetNotFoundError, match="MurpheyLab/DPGO"):
        find_benchmark("M3500", data=fake_data)
    with pytest.raises(DatasetNotFoundError, match="not available"):
        find_benchmark("rim", data=fake_data)
    with pytest.raises(DatasetNotFoundError,  # the registry's names, whole, the rest counted
                       match=r"'bogus' is neither a file here nor a registered benchmark.*registered: ais2klinik, city, "
                             r".* and \d+ more\.$"):
        find_benchmark("bogus", data=fake_data)
    with pytest.raises(DatasetNotFoundError, match="does not exist"):
        find_benchmark("MITb", data=fake_data / "missing")


def test_missing_file_messages_are_short(fake_data):
    """The messages fit on one line of about 300 characters (the CLI prints them as they are)."""
    for name in [*list(BENCHMARKS), "bogus"]:
        if (fake_data / BENCHMARKS[name].file).is_file() if name in BENCHMARKS else False:
            continue
        with pytest.raises(DatasetNotFoundError) as exc:
            find_benchmark(name, data=fake_data / "missing")
        msg = str(exc.value)
        assert "\n" not in msg and len(msg) - len(str(fake_data)) <= 300, msg


# ------------------------------------------------------------- names vs paths: no substitution


@pytest.mark.parametrize("form", ["{d}/nowhere/MIT.g2o", "./MIT.g2o", "~/no-such-dir-mmpgo/MIT.g2o", ".MIT.g2o"])
def test_missing_path_is_not_replaced_by_the_benchmark(fake_data, monkeypatch, tmp_path, form):
    """A path (directory part, leading ~ or .) is only a path, even when its name is a benchmark's."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    query = form.format(d=fake_data)
    with pytest.raises(DatasetNotFoundError) as exc:
        find_benchmark(query, data=fake_data)
    assert str(exc.value) == f"{query}: file not found"


def test_directory_is_not_replaced_by_the_benchmark(fake_data, tmp_path, monkeypatch):
    folder = tmp_path / "dir" / "intel.g2o"
    folder.mkdir(parents=True)
    (fake_data / "intel.g2o").write_text("# fake\n")
    with pytest.raises(IsADirectoryError) as exc:
        find_benchmark(str(folder), data=fake_data)
    assert str(exc.value) == f"{folder}: is a directory, not a g2o file"
    # a bare name that exists here as a directory is a path too
    monkeypatch.chdir(tmp_path / "dir")
    with pytest.raises(IsADirectoryError, match=r"^intel.g2o: is a directory"):
        find_benchmark("intel.g2o", data=fake_data)
    # ... while the name alone (no such entry here) is the benchmark
    assert find_benchmark("intel", data=fake_data) == fake_data / "intel.g2o"


def test_existing_bare_file_is_a_path(fake_data, tmp_path, monkeypatch):
    """A bare file name that exists in the working directory is that file, not the benchmark."""
    work = tmp_path / "work"
    work.mkdir()
    (work / "MIT.g2o").write_text("# mine\n")
    monkeypatch.chdir(work)
    assert find_benchmark("MIT.g2o", data=fake_data) == Path("MIT.g2o")
    assert find_benchmark("./MIT.g2o", data=fake_data) == Path("MIT.g2o")
    # names that do not exist here go to the data folder
    assert find_benchmark("MITb", data=fake_data) == fake_data / "MIT.g2o"
    assert find_benchmark("mit", data=fake_data) == fake_data / "MIT.g2o"
    # the registry's own lookup ignores the working directory
    assert BENCHMARKS["MITb"].path(fake_data) == fake_data / "MIT.g2o"


def test_names_a_path(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.g2o").write_text("")
    (tmp_path / "sub").mkdir()
    for path in ("a/b.g2o", "/x", "~/x", "~", "./x", ".x", "../x", "x.g2o", "sub", Path("x.g2o")):
        assert dsm.names_a_path(path), path
    for name in ("MITb", "city", "garage", "y.g2o", "intel.g2o"):
        assert not dsm.names_a_path(name), name


def test_tilde_path_is_expanded(fake_data, monkeypatch):
    monkeypatch.setenv("HOME", str(fake_data))
    assert find_benchmark("~/MIT.g2o") == fake_data / "MIT.g2o"


def test_no_data_dir_message(monkeypatch, tmp_path):
    monkeypatch.delenv("MMPGO_DATA", raising=False)
    monkeypatch.setattr(dsm, "_DEFAULT_DIR", tmp_path / "absent")
    assert data_dir() is None
    assert available_benchmarks() == []
    with pytest.raises(DatasetNotFoundError, match="MMPGO_DATA is unset"):
        find_benchmark("MITb")


def test_data_dir_precedence(monkeypatch, tmp_path):
    default, env, explicit = (tmp_path / x for x in ("default", "env", "explicit"))
    default.mkdir()
    monkeypatch.setattr(dsm, "_DEFAULT_DIR", default)
    monkeypatch.delenv("MMPGO_DATA", raising=False)
    assert data_dir() == default
    monkeypatch.setenv("MMPGO_DATA", "")
    assert data_dir() == default  # empty means unset
    monkeypatch.setenv("MMPGO_DATA", str(env))
    assert data_dir() == env
    assert data_dir(explicit) == explicit
    assert data_dir(str(explicit)) == explicit
    monkeypatch.delenv("MMPGO_DATA")
    assert data_dir(explicit) == explicit


def test_default_data_dir_is_shared():
    # mmpgo_jax/_io/datasets.py -> the folder holding the repository
    assert Path(dsm.__file__).resolve().parents[2].parent / "shared" / "datasets" == dsm._DEFAULT_DIR


def test_available_benchmarks(fake_data):
    names = [b.name for b in available_benchmarks(fake_data)]
    assert names == ["MITb", "torus", "garage"]  # registry order


def test_available_benchmarks_shared():
    folder = _shared_or_skip()
    avail = {b.file for b in available_benchmarks(folder)}
    assert avail == {f.name for f in folder.glob("*.g2o")}
