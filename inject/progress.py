"""Progress of a long loop (the CCDs of a focal plane, the visits of a night, the streaks of a
crowded scene): a bar where one can be drawn, a few log lines where it cannot.

- Where stderr is a terminal, or the code runs in a Jupyter kernel, a tqdm bar
  (``tqdm.auto``: a widget in a notebook, text on a terminal).
- Elsewhere (a log file, a batch job's output, a pipe) one INFO record on the caller's logger
  each time another tenth of the work is done, so that 189 CCDs give ten lines, not 189:
  ``[19/189] rendering CCDs: R13_S01 done 41.2 s``.

Progress counts as INFO: nothing is shown unless the caller's logger is enabled for INFO.
``inject -q`` sets WARNING, so it is silent; a program that uses the library sets the level
of the ``inject`` logger itself (``logging.getLogger("inject").setLevel(logging.INFO)``), as
for any other message of the package.
"""
import logging
import sys


def _stderr_is_terminal():
    try:
        return sys.stderr is not None and sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced by an object without it, or closed
        return False


def in_notebook():
    """Whether the code runs in a Jupyter kernel (IPython's ``IPKernelApp``), where stderr is
    no terminal but a bar can still be drawn."""
    ipython = sys.modules.get("IPython")  # never imported here: only if the caller has
    if ipython is None:
        return False
    try:
        shell = ipython.get_ipython()
        return shell is not None and "IPKernelApp" in shell.config
    except Exception:  # an IPython too old or too new for this test: no bar
        return False


def _bar(total, desc, unit):
    """A ``tqdm.auto`` bar, or None without tqdm."""
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True)


class Progress:
    """Progress over ``total`` items; :meth:`update` after each, :meth:`close` at the end (or
    use it as a context manager).

    Parameters
    ----------
    total : int
        Items in the loop.
    desc : str
        What the loop does, e.g. ``"rendering CCDs"``: the bar's label and each line's.
    unit : str
        One item, for the bar's rate (``"CCD"``: CCD/s).
    logger : logging.Logger
        Where the lines go, and whose level decides whether anything is shown (INFO or
        lower).
    enabled : bool
        False: nothing at all (a loop too short to be worth a report).
    """

    def __init__(self, total, desc, unit, logger, enabled=True):
        self.total, self.done = int(total), 0
        self.desc, self.logger = desc, logger
        self.shown = bool(enabled) and self.total > 0 and logger.isEnabledFor(logging.INFO)
        self.bar = None
        if self.shown and (_stderr_is_terminal() or in_notebook()):
            self.bar = _bar(self.total, desc, unit)

    def update(self, note=None, n=1):
        """``n`` more items done (one by default); ``note`` (e.g. ``"R22_S11 done"``) goes on
        the bar, or on the line if these items complete a tenth."""
        self.done += n
        if not self.shown:
            return
        if self.bar is not None:
            if note:
                self.bar.set_postfix_str(note, refresh=False)
            self.bar.update(n)
            return
        # A line when the count enters a new tenth of the total: ten lines for any total of
        # ten or more, one per item below that.
        if self.done * 10 // self.total > (self.done - n) * 10 // self.total:
            self.logger.info("[%d/%d] %s%s", self.done, self.total, self.desc,
                             f": {note}" if note else "")

    def close(self):
        """End the bar (a no-op for lines)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
