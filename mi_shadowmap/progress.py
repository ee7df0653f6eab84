"""Progress bars of :func:`~mi_shadowmap.harness.compare`, :func:`~mi_shadowmap.sweep.sweep`
and :func:`~mi_shadowmap.tune`: tqdm's redrawn bar on a terminal and in Jupyter; in a
log (stderr redirected to a file or a pipe: a batch job, CI) plain ASCII lines, one at
the start, then at most one every :data:`LOG_INTERVAL` seconds, and the last: tqdm drew
its bar there too, each redraw after a carriage return, so a log held one line of
hundreds of bars (and, after a bar that does not stay, a line of blanks)."""
from __future__ import annotations

import sys

#: Seconds between two progress lines in a log.
LOG_INTERVAL = 10.0


class _Lines:
    """A stream for tqdm that writes each redraw as a line of its own, blanks dropped,
    and a redraw that repeats the previous line but for its times (a bar's close repeated
    its last update's line when that came after the log interval: only the rate
    differed). A new postfix at the same count is a line (the sweep's reference bar names
    the render that runs next so)."""

    def __init__(self, stream):
        self._stream = stream
        self._last = None      # the previous line's _key()

    @staticmethod
    def _key(line: str) -> tuple:
        """``line`` without its times: tqdm's "desc: pct|bar| n/total [elapsed<left,
        rate, postfix]" as ("desc: pct|bar| n/total", "postfix")."""
        head, _, times = line.partition("[")
        fields = times.rstrip().removesuffix("]").split(", ", 2)
        return head.rstrip(), fields[2] if len(fields) > 2 else ""

    def write(self, text: str) -> None:
        for part in text.split("\r"):
            if part.strip():
                key = self._key(part)
                if key == self._last:
                    continue
                self._last = key
                self._stream.write(part.rstrip() + "\n")

    def flush(self) -> None:
        self._stream.flush()

    def isatty(self) -> bool:
        return False


def interactive(stream) -> bool:
    """Whether ``stream`` shows a redrawn bar: a terminal, or a Jupyter kernel's output."""
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):    # no isatty, or a closed stream
        pass
    return type(stream).__module__.split(".")[0] == "ipykernel"


def bar(iterable=None, **kwargs):
    """``tqdm(iterable, **kwargs)`` on ``kwargs["file"]`` (default: ``sys.stderr`` now),
    as lines where that is not :func:`interactive`."""
    from tqdm import tqdm
    stream = kwargs.pop("file", None) or sys.stderr
    if stream is not None and not interactive(stream):
        # a log keeps its last line (a bar that does not stay wrote blanks over it)
        kwargs.update(file=_Lines(stream), mininterval=LOG_INTERVAL, ascii=True, leave=True)
    else:
        kwargs["file"] = stream
    return tqdm(iterable, **kwargs)
