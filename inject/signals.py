"""Clean stops on SIGINT, SIGTERM and SIGHUP: outputs are cleaned up, the exit status is 128 + N.

:func:`handling` (around every ``inject`` command) makes each of these signals raise
:class:`Stopped` in the main thread, so that the ``finally`` blocks and context managers of
:mod:`inject.io.atomic` remove their temporary files and undo half-made moves as they do for
any error. Once a stop is under way, further signals are only recorded: a second Ctrl-C
cannot interrupt the clean-up. Code that must not be cut in two (create a temporary file *and*
register it for removal; move a file *and* record the move) runs inside :func:`deferred`: a
signal arriving there is raised when the block ends.

Python runs signal handlers between bytecodes of the main thread, so a signal during a long C
call (a FITS or EXR write) takes effect when that call returns.
"""
import contextlib
import signal
import threading

#: The signals that stop a command cleanly (SIGHUP: the terminal closed; SIGTERM: what batch
#: systems and ``kill`` send).
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP")
                     if hasattr(signal, name))


class Stopped(KeyboardInterrupt):
    """Raised in the main thread when a stop signal arrives (a :class:`KeyboardInterrupt`, so
    code that already treats Ctrl-C as a stop treats every stop signal the same way).

    Attributes
    ----------
    signum : int
        The signal.
    """

    def __init__(self, signum):
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")

    @property
    def exit_status(self):
        """``128 + signum``, as a shell reports a command killed by the signal."""
        return 128 + self.signum


class _State:
    depth = 0          # nesting of deferred() blocks
    pending = None     # a signal that arrived inside one
    stopping = False   # a Stopped was raised: later signals are ignored


_state = _State()


def _handler(signum, frame):
    if _state.stopping:
        return  # the clean-up of the first stop is running: let it finish
    if _state.depth > 0:
        if _state.pending is None:
            _state.pending = signum
        return
    _state.stopping = True
    raise Stopped(signum)


@contextlib.contextmanager
def handling():
    """Inside the block, :data:`STOP_SIGNALS` raise :class:`Stopped`; the previous handlers
    are restored at its end. Signals the parent process ignores (``nohup`` ignores SIGHUP)
    stay ignored. Outside the main thread (where Python cannot set handlers) it does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    _state.depth, _state.pending, _state.stopping = 0, None, False
    try:
        for signum in STOP_SIGNALS:
            handler = signal.getsignal(signum)
            if handler is not signal.SIG_IGN:
                previous[signum] = handler
                signal.signal(signum, _handler)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        _state.depth, _state.pending, _state.stopping = 0, None, False


@contextlib.contextmanager
def deferred():
    """Hold stop signals until the block ends, then raise the first that arrived.

    Nestable; only the outermost block raises, even if the block itself failed (the stop
    takes precedence). Outside :func:`handling`, and outside the main thread (where Python
    delivers no signal: a worker thread's block must not hold, or raise, the main thread's
    stop), it changes nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state.depth += 1
    try:
        yield
    finally:
        _state.depth -= 1
        if _state.depth == 0 and _state.pending is not None and not _state.stopping:
            signum, _state.pending = _state.pending, None
            _state.stopping = True
            raise Stopped(signum)
