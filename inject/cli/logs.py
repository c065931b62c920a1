"""The command line's logging: what ``inject CMD`` shows on stderr, and ``-q``/``-v``.

The library only logs (``logging.getLogger(__name__)`` in each module, all under ``inject``);
the command line alone decides what is shown. :func:`command_logging` puts one handler on the
``inject`` logger for the run of a command and sets its level: INFO by default (the command's
reports and its progress), WARNING with ``-q`` (warnings and errors only, no progress), DEBUG
with ``-v``. Messages keep the command line's plain form: an INFO record is its text alone, a
warning ``inject CMD: warning: TEXT``, an error ``inject CMD: error: TEXT``, a debug record
``inject CMD: debug: LOGGER: TEXT``.
"""
import contextlib
import logging
import sys

#: The level of each verbosity: ``-q``, none, ``-v``.
LEVELS = {"quiet": logging.WARNING, "normal": logging.INFO, "verbose": logging.DEBUG}


def level_of(args):
    """The logging level ``args`` asks for (``quiet``/``verbose`` from
    :func:`inject.cli.options.add_verbosity_options`)."""
    if getattr(args, "verbose", False):
        return LEVELS["verbose"]
    if getattr(args, "quiet", False):
        return LEVELS["quiet"]
    return LEVELS["normal"]


class _Formatter(logging.Formatter):
    """The command line's forms: INFO plain, the others named after the command."""

    def __init__(self, command):
        super().__init__("%(message)s")
        self.command = command

    def format(self, record):
        text = super().format(record)
        if record.levelno >= logging.ERROR:
            return f"{self.command}: error: {text}"
        if record.levelno >= logging.WARNING:
            return f"{self.command}: warning: {text}"
        if record.levelno < logging.INFO:
            return f"{self.command}: debug: {record.name}: {text}"
        return text


class _StderrHandler(logging.Handler):
    """Writes to whatever ``sys.stderr`` is when a record comes (a test's capture, a stream
    redirected after start-up), above any tqdm bar drawn there (the bar is redrawn below)."""

    def emit(self, record):
        try:
            text = self.format(record)
            stream = sys.stderr
            tqdm = sys.modules.get("tqdm")  # only if a bar may be on screen
            if tqdm is not None and getattr(tqdm.tqdm, "_instances", None):
                tqdm.tqdm.write(text, file=stream)
            else:
                stream.write(text + "\n")
                stream.flush()
        except RecursionError:
            raise
        except Exception:
            self.handleError(record)


@contextlib.contextmanager
def command_logging(command, level):
    """Show the ``inject`` loggers' records of ``level`` and above on stderr while the block
    runs (one command), in the command line's forms; the logger's handlers and level are put
    back after it, so that a program calling :func:`inject.cli.main.main` twice, or a test,
    sees no handler left over."""
    logger = logging.getLogger("inject")
    handler = _StderrHandler(level)
    handler.setFormatter(_Formatter(command))
    before = logger.level
    logger.addHandler(handler)
    logger.setLevel(level)
    try:
        yield logger
    finally:
        logger.removeHandler(handler)
        logger.setLevel(before)
