"""Progress of a tuning run on stderr: one line per iteration (a bar where the stream is a terminal) with the
objective, the best so far, the time per iteration and the time left."""

from __future__ import annotations

import sys
import warnings
from typing import Callable


def progress_line(desc: str, done: int, total: int, summary: str, elapsed: float, first: tuple[int, float]) -> str:
    """One line of progress: ``tune [start 1/1] [#####.....] 12/25 J=0.7342 best=0.7310 3.1 s/it, ETA 40 s``.

    ``first``: ``(iterations done, elapsed s)`` at the first iteration this process ran, whose time includes the
    compile: the rate and the ETA leave it out, and that first line gives its time instead.
    """
    filled = round(20 * done / total)
    if done > first[0]:
        rate = (elapsed - first[1]) / (done - first[0])
        timing = f"{rate:.1f} s/it, ETA {rate * (total - done):.0f} s"
    else:
        timing = f"first iteration (with the compile) {elapsed:.0f} s"
    return f"{desc} [{'#' * filled}{'.' * (20 - filled)}] {done}/{total} {summary} {timing}"


def interactive(stream) -> bool:
    """Whether progress on ``stream`` is best a bar: a terminal, or the standard streams of a Jupyter kernel.

    Elsewhere (a log file, a pipe, a test's capture) progress stays one line per iteration.
    """
    if stream is sys.stderr or stream is sys.stdout:
        shell = getattr(sys.modules.get("IPython"), "get_ipython", lambda: None)()
        if shell is not None and "IPKernelApp" in getattr(shell, "config", {}):
            return True
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


class ProgressBar:
    """A tqdm bar (:mod:`tqdm.auto`: a widget in a notebook) of iterations, started at the first one reported.

    That first iteration, which includes the compile, is kept apart: its time shows in the bar's postfix, and the
    bar's clock starts after it, so that its rate (s/it) and ETA are those of the compiled iterations.
    """

    def __init__(self, total: int, stream=sys.stderr):
        self.total, self.stream = total, stream
        self.bar, self.first = None, ""

    def update(self, done: int, elapsed: float, desc: str, postfix: str) -> None:
        if self.bar is None:
            with warnings.catch_warnings():  # a notebook without ipywidgets: tqdm's text bar, without its warning
                warnings.simplefilter("ignore")
                from tqdm.auto import tqdm

            self.first = f"first iteration (with the compile) {elapsed:.0f} s"
            self.bar = tqdm(
                total=self.total,
                initial=done,
                desc=desc,
                file=self.stream,
                unit="it",
                dynamic_ncols=True,
                postfix=f"{postfix}, {self.first}",
            )
        else:
            self.bar.set_description_str(desc, refresh=False)
            self.bar.set_postfix_str(f"{postfix}, {self.first}", refresh=False)
            self.bar.update(done - self.bar.n)
        if done >= self.total:
            self.close()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


class Progress:
    """Progress over iterations: a :class:`ProgressBar` where :func:`interactive`, else a :func:`progress_line` per
    iteration (logs of batch jobs keep the history). Both keep the first iteration this process ran, with the
    compile, out of the rate and the ETA. Call it with ``(done, total, elapsed s, description, summary)``."""

    def __init__(self, stream=sys.stderr):
        self.stream, self.first, self.bar = stream, None, None

    def __call__(self, done: int, total: int, elapsed: float, desc: str, summary: str) -> None:
        if self.first is None:
            self.first = (done, elapsed)
            self.bar = ProgressBar(total, self.stream) if interactive(self.stream) else None
        if self.bar is not None:
            return self.bar.update(done, elapsed, desc, summary)
        print(progress_line(desc, done, total, summary, elapsed, self.first), file=self.stream, flush=True)


def progress_reporter(starts: int = 1, stream=sys.stderr) -> Callable:
    """The ``progress`` callback of :func:`optimise` for ``pusupu tune`` and notebooks (:class:`Progress`); the
    bar covers every start."""
    report = Progress(stream)

    def progress(start, iteration, iterations, value, best, aux, elapsed):
        report(
            start * iterations + iteration,
            starts * iterations,
            elapsed,
            f"tune [start {start + 1}/{starts}]",
            f"J={value:.4f} best={best:.4f}",
        )

    return progress
