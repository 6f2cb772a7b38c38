"""Text of user-facing messages: lists and long texts shortened by whole items and words, never in
the middle of a name (a cut inside a list once merged "CSAIL" and "cubicle" into "C…icle")."""

from __future__ import annotations

from collections.abc import Iterable


def join_items(items: Iterable[object], limit: int = 100) -> str:
    """``items`` joined by ", " within about ``limit`` characters: the first ones that fit whole,
    then "and N more" (at least one item is always shown whole)."""
    words = [str(x) for x in items]
    shown: list[str] = []
    for k, word in enumerate(words):
        rest = len(words) - k - 1
        tail = f" and {rest} more" if rest else ""
        if shown and len(", ".join([*shown, word])) + len(tail) > limit:
            return f"{', '.join(shown)} and {len(words) - len(shown)} more"
        shown.append(word)
    return ", ".join(shown)


def shorten_words(text: str, limit: int) -> str:
    """``text`` within ``limit`` characters, dropping whole words in the middle (marked "…") so that
    its start and its end, where messages say what and where, stay readable."""
    if len(text) <= limit:
        return text
    words = text.split(" ")
    head, tail = [], []
    lo, hi = 0, len(words) - 1
    size = 1  # the "…"
    turn = 0
    while lo <= hi:  # two words of the start for one of the end
        from_end = turn % 3 == 2
        word = words[hi] if from_end else words[lo]
        if size + len(word) + 1 > limit:
            break
        size += len(word) + 1
        if from_end:
            tail.insert(0, word)
            hi -= 1
        else:
            head.append(word)
            lo += 1
        turn += 1
    if not head:  # a first word longer than the limit: its start
        return text[: limit - 1] + "…"
    return " ".join([*head, "…", *tail])
