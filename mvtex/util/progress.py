"""Progress bars on stderr for work counted in steps whose total is known only as it runs."""

from __future__ import annotations

import sys
from typing import Callable

from tqdm import tqdm


def step_bar(desc: str, progress: bool) -> tuple[tqdm, Callable[[int, int], None]]:
    """A tqdm bar on stderr (hidden without `progress`) and its `advance(done, total)`
    callback, which takes a total that may change between calls (a fit that learns how
    many steps it takes). Close the bar when the work is done."""
    bar = tqdm(desc=desc, unit="step", disable=not progress, file=sys.stderr)

    def advance(done: int, total: int) -> None:
        if bar.total != total:
            bar.total = total
            bar.refresh()
        bar.update(done - bar.n)

    return bar, advance
