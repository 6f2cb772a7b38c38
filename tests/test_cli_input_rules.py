"""The command line's input rules, run in-process through ``cli.main`` (no subprocesses):

* FILE: a path is only a path (missing / directory are errors, never a benchmark of that name);
  only a bare name is looked up in the data folder, and the command says which file it used;
* --strict-information, and the reader's warnings as one line ``mmpgo: warning: ...``;
* every numeric option is validated when it is parsed (exit 2, one line naming option and range);
* errors are one line of at most about 300 characters;
* outputs are checked before any work, written all-or-none, and through symbolic links.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import warnings
from pathlib import Path

import pytest

import mmpgo_jax._io.g2o as g2o_mod
from mmpgo_jax._io.atomic import atomic_group, atomic_write
from mmpgo_jax.cli import main, outputs
from mmpgo_jax.cli.app import build_parser
from mmpgo_jax.cli.commands import info
from mmpgo_jax.cli.errors import MAX_MESSAGE, CLIError, one_line

DATA = Path(__file__).resolve().parent / "data"
TINY = DATA / "tiny2d.g2o"  # 4 poses
TINY3 = DATA / "tiny3d.g2o"
BAD = DATA / "bad"
MAX_LINE = len("mmpgo: error: ") + MAX_MESSAGE


def _error_line(capsys, rc, *, status=2) -> str:
    """The single stderr line of a failed command (checks status, one line, no traceback)."""
    cap = capsys.readouterr()
    assert rc == status, f"exit {rc}\nstdout:\n{cap.out}\nstderr:\n{cap.err}"
    assert "Traceback" not in cap.err, cap.err
    lines = cap.err.splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got:\n{cap.err}"
    assert lines[0].startswith("mmpgo: error: "), lines[0]
    assert len(lines[0]) <= MAX_LINE, len(lines[0])
    return lines[0]


def _temp_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") and (".tmp" in p.name))


@pytest.fixture
def data(tmp_path, monkeypatch):
    """A data folder holding MIT.g2o (really tiny2d), intel.g2o and an unregistered extra.g2o."""
    folder = tmp_path / "data"
    folder.mkdir()
    shutil.copy(TINY, folder / "MIT.g2o")
    shutil.copy(TINY, folder / "intel.g2o")
    shutil.copy(TINY3, folder / "extra.g2o")
    monkeypatch.setenv("MMPGO_DATA", str(folder))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return folder


# --------------------------------------------------------------------------------------------
# 1. names vs paths
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
def test_missing_path_is_an_error_not_the_benchmark(capsys, data, command):
    """`mmpgo info /no/such/dir/MIT.g2o` used to describe the benchmark MIT."""
    rc = main([command, "/no/such/dir/MIT.g2o"])
    assert _error_line(capsys, rc) == "mmpgo: error: /no/such/dir/MIT.g2o: file not found"


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
def test_directory_is_an_error_not_the_benchmark(capsys, data, tmp_path, command):
    """`mmpgo solve DIR/intel.g2o` (a directory) used to solve the benchmark intel."""
    folder = tmp_path / "dir" / "intel.g2o"
    folder.mkdir(parents=True)
    rc = main([command, str(folder)])
    assert _error_line(capsys, rc) == f"mmpgo: error: {folder}: is a directory, not a g2o file"
    # relative forms are paths too
    rc = main([command, "./MIT.g2o"])
    assert _error_line(capsys, rc) == "mmpgo: error: ./MIT.g2o: file not found"


def test_existing_directory_with_a_bare_name(capsys, data):
    os.mkdir("intel.g2o")
    rc = main(["info", "intel.g2o"])
    assert _error_line(capsys, rc) == "mmpgo: error: intel.g2o: is a directory, not a g2o file"


@pytest.mark.parametrize("name", ["MITb", "mit", "MIT.g2o"])
def test_bare_name_uses_the_data_folder_and_says_so(capsys, data, name):
    assert main(["info", name]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"using {data / 'MIT.g2o'} (benchmark MITb)"
    assert out[1] == f"file        {data / 'MIT.g2o'}"


def test_unregistered_bare_name_in_the_data_folder(capsys, data):
    assert main(["info", "extra"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"using {data / 'extra.g2o'} (from the data folder)"
    assert "d = 3" in out


def test_bare_name_existing_here_is_that_file(capsys, data):
    """A bare file name that exists in the working directory is that file, without a note."""
    shutil.copy(TINY3, "MIT.g2o")
    assert main(["info", "MIT.g2o"]) == 0
    out = capsys.readouterr().out
    assert not out.startswith("using") and out.splitlines()[0] == "file        MIT.g2o"
    assert "d = 3" in out  # the local file, not the data folder's 2D MIT.g2o


def test_solve_and_optimum_announce_the_file(capsys, data, tmp_path):
    assert main(["solve", "MITb", "--robots", "2", "--iterations", "0", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"using {data / 'MIT.g2o'} (benchmark MITb)"
    assert out.count("using ") == 1
    assert main(["optimum", "intel", "--no-certify", "--max-iterations", "3"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == f"using {data / 'intel.g2o'} (benchmark intel)"


def test_unknown_bare_name(capsys, data):
    rc = main(["info", "nosuchbench"])
    line = _error_line(capsys, rc)
    assert "'nosuchbench' is neither a file here nor a registered benchmark" in line
    assert str(data) in line and "MIT.g2o" in line  # what the folder holds
    assert re.search(r"registered: ais2klinik, city, .* and \d+ more\.$", line)  # whole names


# --------------------------------------------------------------------------------------------
# 2. --strict-information and one-line warnings
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
def test_strict_information_is_an_option(command):
    args = build_parser().parse_args([command, "x.g2o", "--strict-information"])
    assert args.strict_information is True
    assert build_parser().parse_args([command, "x.g2o"]).strict_information is False


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
def test_strict_information_refuses_non_pd_information(capsys, command):
    path = BAD / "not_pd_se2.g2o"
    rc = main([command, str(path), "--strict-information", "--no-progress"] if command == "solve"
              else [command, str(path), "--strict-information"])
    line = _error_line(capsys, rc)
    assert line.startswith(f"mmpgo: error: {path}:"), line


def _fake_reader(monkeypatch, category, message, *, filename=None):
    """read_g2o that emits ``category(message)`` as if from inside mmpgo_jax (like G2OWarning)."""
    real = g2o_mod.read_g2o
    calls = []

    def read_g2o(path, **kw):
        calls.append(kw)
        if not kw.get("strict_information"):
            warnings.warn_explicit(message.format(path=path), category, filename or g2o_mod.__file__, 1,
                                   module="mmpgo_jax._io.g2o")
        return real(path, **{k: v for k, v in kw.items() if k != "strict_information"})

    monkeypatch.setattr(g2o_mod, "read_g2o", read_g2o)
    return calls


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
def test_reader_warning_is_one_line(capsys, monkeypatch, command):
    class G2OWarning(UserWarning):
        pass

    monkeypatch.setattr(g2o_mod, "G2OWarning", G2OWarning, raising=False)
    _fake_reader(monkeypatch, G2OWarning,
                 "{path}: 1 of 5 information matrices are\nnot positive definite; SE-Sync weights used")
    argv = {"info": ["info", str(TINY)], "solve": ["solve", str(TINY), "-A", "2", "-n", "0", "--no-progress"],
            "optimum": ["optimum", str(TINY), "--no-certify", "--max-iterations", "2"]}[command]
    assert main(argv) == 0
    err = capsys.readouterr().err
    expected = f"mmpgo: warning: {TINY}: 1 of 5 information matrices are not positive definite; SE-Sync weights used"
    assert err.splitlines() == [expected], err


def test_other_user_warning_from_mmpgo_is_one_line(capsys, monkeypatch):
    _fake_reader(monkeypatch, UserWarning, "something odd\n  in {path}")
    assert main(["info", str(TINY)]) == 0
    assert capsys.readouterr().err == f"mmpgo: warning: something odd in {TINY}\n"


def test_foreign_warnings_are_left_alone(capsys, monkeypatch):
    _fake_reader(monkeypatch, UserWarning, "from elsewhere", filename="/somewhere/else/lib.py")
    with pytest.warns(UserWarning, match="from elsewhere"):  # passed on to the usual display
        assert main(["info", str(TINY)]) == 0
    err = capsys.readouterr().err
    assert "mmpgo: warning" not in err


INDEFINITE = [DATA / "indefinite_se2.g2o", DATA / "indefinite_se3.g2o"]


@pytest.mark.parametrize("path", INDEFINITE, ids=lambda p: p.name)
def test_real_reader_warning_on_indefinite_information(capsys, path):
    assert main(["info", str(path)]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"mmpgo: warning: {path}: "), lines
    assert "not positive definite" in lines[0]


@pytest.mark.parametrize("command", ["info", "solve", "optimum"])
@pytest.mark.parametrize("path", INDEFINITE, ids=lambda p: p.name)
def test_real_reader_strict_information(capsys, command, path):
    rc = main([command, str(path), "--strict-information"] + (["--no-progress"] if command == "solve" else []))
    line = _error_line(capsys, rc)
    assert line.startswith(f"mmpgo: error: {path}:") and "positive definite" in line, line


# --------------------------------------------------------------------------------------------
# 3. numeric options are validated when parsed
# --------------------------------------------------------------------------------------------

# (command line, option as named in the message, the range the message states)
_F = str(TINY)
BAD_OPTIONS = [
    (["info", _F, "--robots", "0"], "--robots/-A", ">= 1"),
    (["info", _F, "-A", "x"], "--robots/-A", ">= 1"),
    (["solve", _F, "--robots", "0"], "--robots/-A", ">= 1"),
    (["solve", _F, "--checkpoint-every", "0"], "--checkpoint-every", ">= 1"),
    (["solve", _F, "--heartbeat-timeout", "0"], "--heartbeat-timeout", "between 1 and 3600"),
    (["solve", _F, "--iterations", "-1"], "--iterations/-n", "between 0 and"),
    (["solve", _F, "-n", "1.5"], "--iterations/-n", "between 0 and"),
    (["solve", _F, "--iterations", str(2**31)], "--iterations/-n", "between 0 and 2147483647"),
    (["solve", _F, "--chunk", "0"], "--chunk", "between 1 and"),
    (["solve", _F, "--chunk", "-1"], "--chunk", "between 1 and"),
    (["solve", _F, "--pcm-confidence", "1"], "--pcm-confidence", "finite number in (0, 1)"),
    (["solve", _F, "--pcm-confidence", "0"], "--pcm-confidence", "finite number in (0, 1)"),
    (["solve", _F, "--xi", "nan"], "--xi", "finite number >= 0"),
    (["solve", _F, "--xi", "inf"], "--xi", "finite number >= 0"),
    (["solve", _F, "--xi", "-inf"], "--xi", "finite number >= 0"),
    (["solve", _F, "--xi=-1e-3"], "--xi", "finite number >= 0"),
    (["solve", _F, "--xi", "-1"], "--xi", "finite number >= 0"),
    (["solve", _F, "--xi", "abc"], "--xi", "finite number >= 0"),
    (["solve", _F, "--grad-tol", "0"], "--grad-tol", "finite number > 0"),
    (["solve", _F, "--grad-tol", "nan"], "--grad-tol", "finite number > 0"),
    (["solve", _F, "--grad-tol", "-1e-3"], "--grad-tol", "finite number > 0"),
    (["solve", _F, "--devices", "-1"], "--devices", ">= 0"),
    (["solve", _F, "--processes", "0"], "--processes", ">= 1"),
    (["solve", _F, "--num-processes", "0"], "--num-processes", ">= 1"),
    (["solve", _F, "--process-id", "-1"], "--process-id", ">= 0"),
    (["solve", _F, "--local-devices", "0"], "--local-devices", ">= 1"),
    (["solve", _F, "--timeout", "0"], "--timeout", "finite number > 0"),
    (["solve", _F, "--timeout", "inf"], "--timeout", "finite number > 0"),
    (["solve", _F, "--coordinator", "localhost"], "--coordinator", "PORT between 1 and 65535"),
    (["solve", _F, "--coordinator", "localhost:0"], "--coordinator", "PORT between 1 and 65535"),
    (["solve", _F, "--coordinator", "localhost:65536"], "--coordinator", "PORT between 1 and 65535"),
    (["solve", _F, "--coordinator", ":1234"], "--coordinator", "PORT between 1 and 65535"),
    (["optimum", _F, "--grad-tol", "0"], "--grad-tol", "finite number > 0"),
    (["optimum", _F, "--grad-tol", "inf"], "--grad-tol", "finite number > 0"),
    (["optimum", _F, "--max-iterations", "0"], "--max-iterations", "between 1 and"),
    (["demo", "--poses", "1"], "--poses", "between 2 and"),
    (["demo", "--robots", "0"], "--robots/-A", ">= 1"),
    (["demo", "--iterations", "-5"], "--iterations/-n", "between 0 and"),
    (["demo", "--seed", "-1"], "--seed", ">= 0"),
    (["bench", "--iterations", "0"], "--iterations/-n", "between 1 and"),
    (["bench", "--robots", "-3"], "--robots/-A", ">= 1"),
    (["solve", _F, "--threads", "0"], "--threads", ">= 1"),
    (["bench", "--threads", "0"], "--threads", ">= 1"),
    (["solve", _F, "--loss-scale", "0"], "--loss-scale", "finite number > 0"),
    (["solve", _F, "--loss-scale", "nan"], "--loss-scale", "finite number > 0"),
    (["sweep", _F, "--robots", "2", "0"], "--robots/-A", ">= 1"),
    (["sweep", _F, "--iterations", "0"], "--iterations/-n", "between 1 and"),
    (["sweep", _F, "--seed", "-1"], "--seed", ">= 0"),
    (["sweep", _F, "--outlier-rates", "10", "100"], "--outlier-rates", ">= 0 and < 100"),
    (["sweep", _F, "--outlier-rates", "-5"], "--outlier-rates", ">= 0 and < 100"),
    (["sweep", _F, "--outlier-rates", "nan"], "--outlier-rates", ">= 0 and < 100"),
    (["sweep", _F, "--outlier-seed", "-1"], "--outlier-seed", ">= 0"),
    (["sweep", _F, "--pcm", "--pcm-confidence", "1"], "--pcm-confidence", "finite number in (0, 1)"),
]


@pytest.mark.parametrize("argv, option, allowed", BAD_OPTIONS,
                         ids=[" ".join(a[0:1] + a[2:]) for a, _, _ in BAD_OPTIONS])
def test_bad_numeric_option(capsys, tmp_path, argv, option, allowed):
    rc = main(argv)
    line = _error_line(capsys, rc)
    assert line.startswith(f"mmpgo: error: argument {option}: must be "), line
    assert allowed in line, line
    value = argv[-1].split("=", 1)[1] if argv[-1].startswith("--") else argv[-1]
    assert f"got {value!r}" in line, line


@pytest.mark.parametrize("argv", [a for a, _, _ in BAD_OPTIONS if a[0] == "solve"][:6])
def test_bad_numeric_option_in_sharded_entry_point(capsys, argv):
    """`python -m mmpgo_jax.sharding` parses with the same checks."""
    from mmpgo_jax import sharding

    _error_line(capsys, sharding.main(argv))


def test_issue_cases(capsys):
    """The reported cases: --chunk 0 hung, --chunk -1 crashed, --xi nan/inf/-1 were accepted,
    info --robots 0 was ignored."""
    for argv, option in [(["solve", _F, "--chunk", "0"], "--chunk"), (["solve", _F, "--chunk", "-1"], "--chunk"),
                         (["solve", _F, "--xi", "nan"], "--xi"), (["solve", _F, "--xi", "inf"], "--xi"),
                         (["solve", _F, "--xi", "-1"], "--xi"), (["info", _F, "--robots", "0"], "--robots/-A")]:
        line = _error_line(capsys, main(argv))
        assert f"argument {option}: " in line, line


def _numeric_actions():
    """(subcommand, action) of every option of every subcommand that takes a value with a type."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        for action in p._actions:
            if action.type is not None:
                yield name, action


def test_every_numeric_option_is_validated_and_swept():
    """No option parses with a bare int/float, and the sweep above covers every typed option."""
    swept = {(a[0], opt.split("/")[0]) for a, opt, _ in BAD_OPTIONS}
    assert len(swept) == 33  # info 1, solve 17, optimum 2, demo 4, bench 3, sweep 6
    for name, action in _numeric_actions():
        assert action.type not in (int, float), f"{name} {action.option_strings}: unchecked {action.type}"
        assert action.type.__name__ in ("integer", "number", "host_port"), (name, action.option_strings)
        assert (name, action.option_strings[0]) in swept, f"{name} {action.option_strings[0]} missing from BAD_OPTIONS"


@pytest.mark.parametrize("argv", [
    ["solve", _F, "--xi", "0", "--chunk", "1", "--iterations", "0", "--grad-tol", "1e-12", "--robots", "1"],
    ["solve", _F, "--devices", "0", "--processes", "1", "--timeout", "0.5", "--coordinator", "[::1]:8476",
     "--num-processes", "1", "--process-id", "0", "--local-devices", "2"],
    ["optimum", _F, "--grad-tol", "1e-3", "--max-iterations", "1"],
    ["demo", "--poses", "2", "--robots", "1", "--iterations", "0", "--seed", "0"],
    ["bench", "--iterations", "1", "--robots", "1"],
    ["info", _F, "--robots", "1"],
])
def test_boundary_values_are_accepted(argv):
    build_parser().parse_args(argv)


def test_info_robots_more_than_poses(capsys):
    line = _error_line(capsys, main(["info", _F, "--robots", "5"]))
    assert line == "mmpgo: error: --robots must be between 1 and the number of poses (4), got 5"
    assert main(["info", _F, "--robots", "4"]) == 0


def test_help_returns_zero(capsys):
    assert main(["solve", "--help"]) == 0
    assert "--strict-information" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------
# 4. errors are one readable line
# --------------------------------------------------------------------------------------------


def test_one_line_shortens():
    assert one_line("a\nb\r\n\tc  d") == "a b c d"
    long = "x" * 1000
    out = one_line(f"file.g2o:3: bad token {long} here")
    assert out.startswith("file.g2o:3: bad token x") and out.endswith("x here") and "…" in out
    assert len(out) <= MAX_MESSAGE
    out = one_line("word " * 500)
    assert len(out) <= MAX_MESSAGE and "…" in out
    assert one_line("bell\x07 and esc\x1b[31m") == "bell? and esc?[31m"
    huge = one_line("y" * 3_000_000)
    assert len(huge) <= MAX_MESSAGE


def test_three_megabyte_token_in_a_g2o_file(capsys, tmp_path):
    for i, text in enumerate([
        "VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 " + "7" * 3_000_000 + "x 0 0 1 0 1\n",
        "Q" * 3_000_000 + " 1 2\n",
        "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1 " + "z" * 3_000_000 + "\n",
    ]):
        path = tmp_path / f"big{i}.g2o"
        path.write_text(text)
        for command in ("info", "solve"):
            line = _error_line(capsys, main([command, str(path), "--no-progress"] if command == "solve"
                                            else [command, str(path)]))
            assert line.startswith(f"mmpgo: error: {path}:"), line


def test_three_megabyte_argument(capsys, tmp_path):
    huge = "q" * 3_000_000
    line = _error_line(capsys, main(["optimum", _F, "--init", huge]))
    assert "qqq…qqq" in line
    line = _error_line(capsys, main(["info", huge]))
    assert line.startswith("mmpgo: error: 'qqq") and "qqq…qqq" in line and line.endswith(" more.")  # the list cut by whole names
    line = _error_line(capsys, main(["solve", _F, "--xi", huge]))
    assert line.startswith("mmpgo: error: argument --xi: must be a finite number >= 0")


def test_multi_line_error_becomes_one_line(capsys, monkeypatch):
    def boom(args):
        raise CLIError("first line\nsecond line\n" + "/very/long/" * 40 + "path.g2o")

    monkeypatch.setattr(info, "run", boom)
    line = _error_line(capsys, main(["info", _F]))
    assert line.startswith("mmpgo: error: first line second line /very/long/") and "…" in line


# --------------------------------------------------------------------------------------------
# 5. outputs: checked first, all or none, through symbolic links
# --------------------------------------------------------------------------------------------

SOLVE = ["solve", _F, "--robots", "2", "--iterations", "0", "--no-progress"]


@pytest.fixture
def work(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_missing_output_folder_before_solving(capsys, work):
    """`--out ok.g2o --tum missing/x` used to write ok.g2o and fail after the solve."""
    rc = main([*SOLVE, "--out", "ok.g2o", "--tum", "missing/x"])
    assert _error_line(capsys, rc) == "mmpgo: error: --tum missing/x: folder 'missing' does not exist"
    assert sorted(p.name for p in work.iterdir()) == []


@pytest.mark.parametrize("command", ["solve", "optimum"])
def test_outputs_are_checked_before_reading(capsys, work, command):
    """A bad output is reported before the (malformed) input is even read."""
    argv = [command, str(BAD / "field_count.g2o"), "--out", "nowhere/x.g2o"]
    assert _error_line(capsys, main(argv)) == "mmpgo: error: --out nowhere/x.g2o: folder 'nowhere' does not exist"


@pytest.mark.parametrize("extra, message", [
    (["--out", "."], "--out .: is a directory"),
    (["--history", "d"], "--history d: is a directory"),
    (["--plot", "f.txt/p.png"], "--plot f.txt/p.png: 'f.txt' is not a folder"),
    (["--out", "a.g2o", "--tum", "a.g2o"], "--out a.g2o and --tum a.g2o: the same file"),
    (["--out", "a.g2o", "--history", "./a.g2o"], "--out a.g2o and --history ./a.g2o: the same file"),
    (["--out", "a.g2o", "--plot", "link"], "--out a.g2o and --plot link: the same file"),
    (["--tum", "f.txt", "--plot", "hard"], "--tum f.txt and --plot hard: the same file"),
    (["--out", ""], "--out: empty file name"),
    (["--tum", "/dev/null"], "--tum /dev/null: not a regular file"),
])
def test_bad_outputs(capsys, work, extra, message):
    (work / "d").mkdir()
    (work / "f.txt").write_text("keep\n")
    os.symlink("a.g2o", work / "link")
    os.link(work / "f.txt", work / "hard")
    before = sorted(p.name for p in work.iterdir())
    line = _error_line(capsys, main(SOLVE + extra))
    assert line.startswith(f"mmpgo: error: {message}"), line
    assert sorted(p.name for p in work.iterdir()) == before
    assert (work / "f.txt").read_text() == "keep\n"


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output_folder(capsys, work):
    ro = work / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        line = _error_line(capsys, main([*SOLVE, "--out", "ro/x.g2o"]))
    finally:
        ro.chmod(0o700)
    assert line == "mmpgo: error: --out ro/x.g2o: folder 'ro' is not writable"


def test_optimum_outputs_checked(capsys, work):
    rc = main(["optimum", _F, "--out", "ok.g2o", "--tum", "missing/x.tum"])
    assert _error_line(capsys, rc) == "mmpgo: error: --tum missing/x.tum: folder 'missing' does not exist"
    assert list(work.iterdir()) == []


def test_sharded_solve_outputs_checked(capsys, work):
    rc = main([*SOLVE, "--devices", "1", "--out", "ok.g2o", "--tum", "missing/x"])
    assert _error_line(capsys, rc) == "mmpgo: error: --tum missing/x: folder 'missing' does not exist"
    assert list(work.iterdir()) == []


def _failing_write_tum(monkeypatch):
    def write_tum(path, poses, **kw):
        with atomic_write(path) as fh:
            fh.write("half a line")
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(g2o_mod, "write_tum", write_tum)


@pytest.mark.parametrize("command", ["solve", "optimum"])
def test_failure_in_second_writer_keeps_first_target(capsys, work, monkeypatch, command):
    (work / "est.g2o").write_text("precious\n")
    _failing_write_tum(monkeypatch)
    argv = (SOLVE if command == "solve" else ["optimum", _F, "--no-certify", "--max-iterations", "2"])
    line = _error_line(capsys, main([*argv, "--out", "est.g2o", "--tum", "est.tum"]))
    assert "No space left on device" in line
    assert (work / "est.g2o").read_text() == "precious\n"
    assert sorted(p.name for p in work.iterdir()) == ["est.g2o"]


def test_failure_in_last_writer_leaves_nothing_new(capsys, work, monkeypatch):
    def fail(path, result):
        with atomic_write(path) as fh:
            fh.write("iteration,f\n")
            raise OSError(5, "Input/output error")

    monkeypatch.setattr(outputs, "write_history_csv", fail)
    (work / "old.tum").write_text("old\n")
    line = _error_line(capsys, main([*SOLVE, "--out", "new.g2o", "--tum", "old.tum", "--history", "h.csv"]))
    assert "Input/output error" in line
    assert sorted(p.name for p in work.iterdir()) == ["old.tum"]
    assert (work / "old.tum").read_text() == "old\n"


def test_all_outputs_written_together(capsys, work):
    assert main([*SOLVE, "--out", "a.g2o", "--tum", "a.tum", "--history", "h.csv"]) == 0
    assert sorted(p.name for p in work.iterdir()) == ["a.g2o", "a.tum", "h.csv"]
    assert g2o_mod.read_g2o(work / "a.g2o").has_vertex.all()


def test_output_through_symlink(capsys, work):
    real = work / "real"
    real.mkdir()
    (real / "est.g2o").write_text("old\n")
    os.symlink(real / "est.g2o", work / "link.g2o")
    os.symlink("real/missing.tum", work / "dangling.tum")
    assert main([*SOLVE, "--out", "link.g2o", "--tum", "dangling.tum"]) == 0
    assert (work / "link.g2o").is_symlink() and (work / "dangling.tum").is_symlink()
    assert os.readlink(work / "link.g2o") == str(real / "est.g2o")
    assert g2o_mod.read_g2o(real / "est.g2o").has_vertex.all()
    assert len((real / "missing.tum").read_text().splitlines()) == 4
    assert _temp_files(work) == [] and _temp_files(real) == []


# ---------------------------------------------------------------------------- _atomic helpers


def test_atomic_group_commits_together(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    with atomic_group() as group:
        with atomic_write(a) as fh:
            fh.write("A")
        assert not a.exists()  # deferred
        with atomic_write(b, "wb") as fh:
            fh.write(b"B")
        assert len(group) == 2 and group.targets == [str(a), str(b)]
    assert a.read_text() == "A" and b.read_bytes() == b"B"
    assert _temp_files(tmp_path) == []


def test_atomic_group_failure_changes_nothing(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.write_text("old A")
    with pytest.raises(RuntimeError, match="second"), atomic_group():
        with atomic_write(a) as fh:
            fh.write("new A")
        with atomic_write(b) as fh:
            fh.write("half")
            raise RuntimeError("second writer fails")
    assert a.read_text() == "old A" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]
    # an exception after all writes finished also leaves everything as it was
    with pytest.raises(KeyError), atomic_group():
        with atomic_write(a) as fh:
            fh.write("newer")
        raise KeyError("later")
    assert a.read_text() == "old A" and sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_atomic_group_nested_and_rewrites(tmp_path):
    a = tmp_path / "a"
    with atomic_group() as outer:
        with atomic_group() as inner:
            assert inner is outer
            with atomic_write(a) as fh:
                fh.write("1")
        assert not a.exists()  # the inner group waits for the outer one
        with atomic_write(a) as fh:
            fh.write("2")  # the last write to a target wins
    assert a.read_text() == "2" and _temp_files(tmp_path) == []


def test_atomic_group_commit_failure_restores(tmp_path, monkeypatch):
    """A rename failing half-way through the commit restores the targets already replaced."""
    import mmpgo_jax._io.atomic as atomic_mod

    a, b = tmp_path / "a", tmp_path / "b"
    a.write_text("old A")
    real_replace = os.replace
    calls = []

    def flaky_replace(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise PermissionError(13, "Permission denied")
        return real_replace(src, dst)

    with pytest.raises(PermissionError) as exc, atomic_group():
        with atomic_write(a) as fh:
            fh.write("new A")
        with atomic_write(b) as fh:
            fh.write("new B")
        monkeypatch.setattr(atomic_mod.os, "replace", flaky_replace)
    monkeypatch.setattr(atomic_mod.os, "replace", real_replace)
    assert str(b) in str(exc.value) and ".tmp" not in str(exc.value)
    assert a.read_text() == "old A" and not b.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_atomic_write_through_symlink(tmp_path):
    target = tmp_path / "t" / "file.txt"
    target.parent.mkdir()
    target.write_text("old")
    os.chmod(target, 0o640)
    link = tmp_path / "link.txt"
    os.symlink(target, link)
    with atomic_write(link) as fh:
        fh.write("new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_text() == "new" and (os.stat(target).st_mode & 0o777) == 0o640
    assert _temp_files(tmp_path) == [] and _temp_files(target.parent) == []


def test_atomic_write_errors_name_the_target(tmp_path):
    with pytest.raises(FileNotFoundError) as exc, atomic_write(tmp_path / "missing" / "x.g2o") as fh:
        fh.write("x")
    assert str(tmp_path / "missing" / "x.g2o") in str(exc.value) and ".tmp" not in str(exc.value)
    with pytest.raises(IsADirectoryError), atomic_write(tmp_path) as fh:
        fh.write("x")
    with pytest.raises(OSError, match="not a regular file"), atomic_write(os.devnull) as fh:
        fh.write("x")
