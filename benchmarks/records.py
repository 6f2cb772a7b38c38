"""Writing a benchmark's record without losing what was written beside it.

The ``.md`` records in this folder hold a script's generated run and, below it, sections added later
(a run on another machine, a finding, an A/B): ``write_record`` writes the new run and keeps every
``## `` section of the old file whose heading the new text does not have, so rerunning a documented
command never erases that history. All or nothing (``atomic_write``).
"""

from __future__ import annotations

import re
from pathlib import Path


def kept_sections(old: str, new: str) -> str:
    """The ``## `` sections of ``old`` (each up to the next ``## `` heading) whose heading line ``new``
    does not contain, in their order; "" when none."""
    headings = set(re.findall(r"^## .*$", new, re.M))
    parts = re.split(r"(?m)^(?=## )", old)[1:]  # the text before the first heading is the old run
    return "".join(p for p in parts if p.splitlines()[0] not in headings)


def write_record(path, text: str) -> None:
    """``text`` to ``path``, followed by the old file's sections it does not replace."""
    from mmpgo_jax._io.atomic import atomic_write  # here: a driver script that starts children imports no JAX

    path = Path(path)
    old = path.read_text() if path.is_file() else ""
    kept = kept_sections(old, text)
    with atomic_write(path) as fh:
        fh.write(text.rstrip("\n") + "\n" + ("\n" + kept if kept else ""))
