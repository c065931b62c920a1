"""Exception and warning classes of ``inject``.

Which class to raise
--------------------
Every error ``inject`` raises on purpose is an :class:`InjectError`: the command line prints
its message as one line and exits with status 2, so the message must name the value, key or
file at fault and say what is wrong (``satellites[0].height=-5: must be > 0``). Raise

- :class:`InputError` ``(name, value, reason)`` for a bad value given by the user, through the
  Python API or a command-line option: out of its domain, of the wrong type, options that do
  not go together (``--json`` without ``--plan``), a name that names nothing (a detector, a
  masker).
- :class:`SceneError` for a scene file (or mapping): a missing or unknown key, a wrong type, a
  value out of range *as read from the scene*, YAML that does not parse. A parser that calls
  an API function raising :class:`InputError` re-raises it as a :class:`SceneError` that
  says where in the scene.
- :class:`FileFormatError` for an input file that cannot be read or is not of the kind
  expected: a FITS, EXR or star-catalog file that is missing, truncated, of another layout,
  without the HDU, part or column needed.
- :class:`OrbitError` for an orbit that cannot be used: a TLE with a bad checksum or line, an
  SGP4 error, a decayed orbit, an epoch too far from the exposure.
- ``inject.masking.MaskingError`` for an image that cannot be searched for streaks (not 2-D,
  too small, no usable pixels) or a masker that fails or cannot run.
- :class:`OutputError` for an output that cannot be written: it exists (without
  ``--overwrite``) or is a directory, its directory is missing or read-only, the disk is
  full, two outputs share a name.
- :class:`ResourceError` when the work cannot fit this machine (its estimated memory exceeds
  what is free).
- :class:`RunError` when some units of a run (the CCDs of a focal-plane run) failed and the
  others were kept; each unit's own message is in the run's manifest.

The first four and ``MaskingError`` are also subclasses of :class:`ValueError` (as GalSim's
``GalSimValueError`` is), so callers that catch ``ValueError`` for bad input keep working. The
conditions of the machine are not: :class:`OutputError` is also an :class:`OSError`,
:class:`ResourceError` also a :class:`MemoryError`. Those depend on the moment, not on the
input, so the focal-plane runner retries a CCD that failed with one of them (or with anything
unexpected), never one that failed on its input (the same input fails the same way again).

Warnings (:func:`warnings.warn`; the command line prints each as one line):
:class:`InputWarning` for a value that is accepted but outside the range where it is
physically plausible, :class:`OrbitWarning` for an orbit or time that is usable but less
accurate.

Anything else (a ``TypeError`` from numpy, an ``AssertionError``) is a bug, not a message.

Pickling
--------
Every error here survives :mod:`pickle` with its message and attributes, so that one raised in
a process-pool or Dask worker comes back to the caller as itself. Python rebuilds an exception
as ``cls(*err.args)``, and ``args`` holds what ``__init__`` passed on to ``Exception`` (the
message): a class whose ``__init__`` takes anything else defines ``__reduce__`` to return its
own arguments (as :class:`InputError` and :class:`RunError` do). Without it the unpickling
fails in the caller, and a process pool reports ``BrokenProcessPool`` for every task still
pending. ``tests/test_errors.py`` round-trips every class of this module.
"""


class InjectError(Exception):
    """Base class of every error ``inject`` raises on purpose (see the module's notes)."""

    def __reduce__(self):
        # Explicit, so that pickle and the reducers Dask installs (tblib's) rebuild the class
        # through its own constructor: tblib rebuilds a class with the builtin reducer by
        # calling ``cls.__new__`` bare, which a MemoryError subclass refuses.
        return type(self), self.args, self.__dict__ or None


class InputError(InjectError, ValueError):
    """A parameter is out of its domain (negative height, zenith >= 90 deg, NaN, ...).

    Parameters
    ----------
    name : str
        The parameter's name as the user wrote it (``height``, ``satellites[0].mag``).
    value : object
        The offending value.
    reason : str
        What is wrong with it, e.g. ``"must be > 0"``.
    """

    def __init__(self, name, value, reason):
        self.name, self.value, self.reason = name, value, reason
        super().__init__(f"{name}={value!r}: {reason}")

    def __reduce__(self):
        # The default, InputError(*self.args), would call __init__ with the message alone.
        return type(self), (self.name, self.value, self.reason), self.__dict__


class SceneError(InjectError, ValueError):
    """A scene file is missing keys, has unknown ones or wrong types."""


class FileFormatError(InjectError, ValueError):
    """An input file cannot be read or is not of the expected kind."""


class OrbitError(InjectError, ValueError):
    """An orbit cannot be used: a TLE with a bad checksum, a decayed orbit, an epoch too far
    from the exposure."""


class OutputError(InjectError, OSError):
    """An output cannot be written (exists without ``--overwrite``, unwritable, disk full).

    Also an :class:`OSError` (not a ``ValueError``): the input is fine, the file system is not.
    """


class ResourceError(InjectError, MemoryError):
    """The work asked for cannot fit this machine (its estimated memory exceeds what is free).

    Also a :class:`MemoryError` (not a ``ValueError``): the input is fine, the machine is too
    small for it now.
    """


class RunError(InjectError):
    """Some units of a run failed (CCDs of a focal-plane run); the others were kept.

    Parameters
    ----------
    message : str
        One line: how many failed, which, and their messages.
    failed : sequence of (str, str)
        ``(unit, its one-line error)`` for each failed unit, e.g. ``("R22_S11",
        "satellites[0].mag=99: must be <= 30")``.
    """

    def __init__(self, message, failed=()):
        self.failed = tuple(tuple(item) for item in failed)
        super().__init__(message)

    def __reduce__(self):
        return type(self), (str(self), self.failed), self.__dict__


class InputWarning(UserWarning):
    """A value is accepted but outside the range where it is physically plausible."""


class OrbitWarning(UserWarning):
    """An orbit or time is usable but less accurate (TLE epoch days from the exposure, a time
    beyond the bundled IERS table)."""
