"""One progress bar for every chunked solve (CLI, bench, demo, sharded CLI).

The jitted loop runs in chunks and calls ``callback(done, f_chunk)`` after each; the bar advances
to ``done`` and shows the latest objective. tqdm is imported lazily so library users who never
ask for progress do not pay for it.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager


@contextmanager
def progress_bar(desc: str, total: int, *, disable: bool = False, leave: bool = True):
    """Yield a chunk callback driving a tqdm bar on stderr, or ``None`` when disabled."""
    if disable or total <= 0:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit="it", file=sys.stderr, leave=leave, dynamic_ncols=True)

    def callback(done, f_chunk):
        bar.update(done - bar.n)
        bar.set_postfix(f=f"{f_chunk[-1]:.7g}")

    try:
        yield callback
    finally:
        bar.close()
