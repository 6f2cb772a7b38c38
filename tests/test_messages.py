"""User-facing messages are shortened by whole items and words, never inside a name; a missing
file names what the data folder holds; a mistyped option gets the closest one of its command."""

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mmpgo_jax._core.messages import join_items, shorten_words
from mmpgo_jax._io.datasets import BENCHMARKS, DatasetNotFoundError, find_benchmark
from mmpgo_jax.cli import main
from mmpgo_jax.cli.errors import MAX_MESSAGE, one_line

NAMES = st.lists(st.text(st.characters(categories=("L", "N"), max_codepoint=0x7F), min_size=1, max_size=12),
                 min_size=0, max_size=40)


@given(NAMES, st.integers(10, 200))
def test_join_items_keeps_whole_items_and_counts_the_rest(items, limit):
    text = join_items(items, limit)
    more = re.search(r" and (\d+) more$", text)
    shown = (text[: more.start()] if more else text).split(", ") if items else []
    assert shown == items[: len(shown)]  # whole items, in order
    assert len(shown) + (int(more.group(1)) if more else 0) == len(items)
    if items:
        assert len(shown) >= 1
    if len(shown) > 1:
        assert len(text) <= limit


def test_join_items_examples():
    assert join_items(["a", "b", "c"], 100) == "a, b, c"
    assert join_items(["alpha", "beta", "gamma", "delta"], 22) == "alpha, beta and 2 more"
    assert join_items(["alpha", "beta", "gamma", "delta"], 21) == "alpha and 3 more"
    assert join_items([], 10) == ""


@given(st.lists(st.text(st.characters(categories=("L", "N")), min_size=1, max_size=15), min_size=1, max_size=80),
       st.integers(20, 300))
def test_shorten_words_drops_whole_words(words, limit):
    text = " ".join(words)
    short = shorten_words(text, limit)
    assert len(short) <= limit
    if short == text:
        return
    if "…" in short.split(" "):
        head, tail = (part.split() for part in short.split("…"))
        assert words[: len(head)] == head and words[len(words) - len(tail):] == tail  # whole words
        assert len(head) >= 1
    else:  # a single word longer than the limit
        assert short.endswith("…") and text.startswith(short[:-1])


def test_one_line_never_cuts_inside_a_name():
    names = [f"name{k:03d}" for k in range(100)]
    line = one_line("registered: " + ", ".join(names) + ". End.")
    assert len(line) <= MAX_MESSAGE and line.endswith("End.")
    assert all(re.fullmatch(r"name\d{3}[,.]?|…|registered:|End\.", w) for w in line.split())


def test_missing_file_lists_whole_names_and_the_folder(tmp_path, capsys):
    for name in ("b.g2o", "a.g2o", "notes.txt"):
        (tmp_path / name).write_text("")
    with pytest.raises(DatasetNotFoundError) as err:
        find_benchmark("nosuch", tmp_path)
    text = str(err.value)
    assert f"searched {tmp_path} (--data) (it holds a.g2o, b.g2o)" in text  # only .g2o files, sorted
    listed = text.split("registered: ")[1]
    shown = re.sub(r" and \d+ more\.$", "", listed).split(", ")
    assert set(shown) <= set(BENCHMARKS) and len(shown) < len(BENCHMARKS)
    assert f"and {len(BENCHMARKS) - len(shown)} more." in listed
    # through the CLI: one line, within the cap, every listed name whole
    assert main(["info", "nosuch", "--data", str(tmp_path)]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and len(line) <= len("mmpgo: error: ") + MAX_MESSAGE
    assert "…" not in line and "registered:" in line


def test_mistyped_option_suggests_the_commands_own(capsys):
    assert main(["solve", "nosuch", "--iters", "5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("mmpgo: error: unrecognized arguments --iters 5 (did you mean --iterations?) "
                   "(see 'mmpgo solve --help')")
    assert main(["info", "nosuch", "--robots-frm", "metis"]) == 2
    assert "(did you mean --robots-from?) (see 'mmpgo info --help')" in capsys.readouterr().err
    assert main(["solve", "nosuch", "--zzzzzz"]) == 2
    assert capsys.readouterr().err.strip() == "mmpgo: error: unrecognized argument --zzzzzz (see 'mmpgo solve --help')"
