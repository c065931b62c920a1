"""Exception hierarchy of ``inject``.

Every error raised for bad input is an :class:`InjectError`, which also subclasses
:class:`ValueError` (as GalSim's ``GalSimValueError`` does), so callers that already catch
``ValueError`` keep working and the CLI can turn any of them into a one-line message.
"""


class InjectError(ValueError):
    """Base class of every error ``inject`` raises on purpose."""


class InputError(InjectError):
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


class SceneError(InjectError):
    """A scene file is missing keys, has unknown ones or wrong types."""


class FileFormatError(InjectError):
    """An input file cannot be read or is not of the expected kind."""


class OutputError(InjectError):
    """An output cannot be written (exists without ``--overwrite``, unwritable, disk full)."""


class ResourceError(InjectError):
    """The work asked for cannot fit this machine (its estimated memory exceeds what is free)."""


class InputWarning(UserWarning):
    """A value is accepted but outside the range where it is physically plausible."""


class OrbitError(InjectError):
    """An orbit cannot be used: a TLE with a bad checksum, a decayed orbit, an epoch too far
    from the exposure."""


class OrbitWarning(UserWarning):
    """An orbit or time is usable but less accurate (TLE epoch days from the exposure, a time
    beyond the bundled IERS table)."""
