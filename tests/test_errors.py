"""The error classes: every one round-trips through pickle with its message and attributes (an
error raised in a process-pool or Dask worker must come back as itself, not break the pool);
input errors are ValueErrors, disk and memory conditions are not."""
import inspect
import pickle

import pytest

import inject.errors
from inject import MaskingError
from inject.errors import (
    FileFormatError,
    InjectError,
    InputError,
    InputWarning,
    OrbitError,
    OrbitWarning,
    OutputError,
    ResourceError,
    RunError,
    SceneError,
)


def _classes():
    """Every exception and warning class defined in inject.errors, and MaskingError."""
    found = [cls for _, cls in inspect.getmembers(inject.errors, inspect.isclass)
             if issubclass(cls, BaseException) and cls.__module__ == "inject.errors"]
    return sorted(found, key=lambda c: c.__name__) + [MaskingError]


#: Arguments of the classes whose __init__ takes more than a message (others get one).
ARGS = {InputError: ("satellites[0].mag", {"given": [99.5, None]}, "must be <= 30"),
        RunError: ("2 of 4 CCDs failed", [("R01_S00", "x=1: bad"), ("R22_S11", "MemoryError")])}


def _make(cls):
    if cls in ARGS:
        return cls(*ARGS[cls])
    init = inspect.signature(cls.__init__)
    own = [p for p in list(init.parameters.values())[1:]
           if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) and p.default is p.empty]
    if cls.__init__ is not BaseException.__init__ and len(own) > 1:
        pytest.fail(f"{cls.__name__}({', '.join(p.name for p in own)}): add its arguments to "
                    f"ARGS in {__name__}, and a __reduce__ to the class if it has none")
    return cls("scene.yaml: something is wrong with it")


def test_the_classes_are_found():
    names = {cls.__name__ for cls in _classes()}
    assert {"InjectError", "InputError", "SceneError", "FileFormatError", "OutputError",
            "ResourceError", "OrbitError", "RunError", "InputWarning", "OrbitWarning",
            "MaskingError"} <= names


@pytest.mark.parametrize("cls", _classes(), ids=lambda c: c.__name__)
@pytest.mark.parametrize("protocol", [2, pickle.HIGHEST_PROTOCOL])
def test_pickle_round_trip(cls, protocol):
    err = _make(cls)
    err.extra = "set after raising"  # attributes set later travel too
    err.add_note("a note")
    back = pickle.loads(pickle.dumps(err, protocol=protocol))
    assert type(back) is cls
    assert str(back) == str(err) and back.args == err.args
    assert vars(back) == vars(err)
    assert back.__notes__ == ["a note"]


@pytest.mark.parametrize("cls", _classes(), ids=lambda c: c.__name__)
def test_round_trip_under_the_reducers_dask_installs(cls):
    """Dask installs tblib's exception reducers process-wide; they rebuild a class that keeps
    the builtin ``__reduce__`` with a bare ``cls.__new__``, which a MemoryError subclass
    refuses. Each class must come back through them too."""
    pickling_support = pytest.importorskip("tblib.pickling_support")
    err = _make(cls)
    reduced = pickling_support.pickle_exception(err)
    back = reduced[0](*reduced[1])
    assert type(back) is cls and str(back) == str(err)


def test_input_error_keeps_its_parts():
    err = pickle.loads(pickle.dumps(InputError("height", -5.0, "must be > 0")))
    assert (err.name, err.value, err.reason) == ("height", -5.0, "must be > 0")
    assert str(err) == "height=-5.0: must be > 0"


def test_run_error_keeps_the_failed_units():
    err = pickle.loads(pickle.dumps(RunError("1 of 2 CCDs failed", [["R01_S00", "x=1: bad"]])))
    assert err.failed == (("R01_S00", "x=1: bad"),) and str(err) == "1 of 2 CCDs failed"


@pytest.mark.parametrize("cls", [InputError, SceneError, FileFormatError, OrbitError,
                                 MaskingError])
def test_input_errors_are_value_errors(cls):
    assert issubclass(cls, InjectError) and issubclass(cls, ValueError)


@pytest.mark.parametrize("cls, builtin", [(OutputError, OSError), (ResourceError, MemoryError)])
def test_disk_and_memory_are_not_value_errors(cls, builtin):
    assert issubclass(cls, InjectError) and issubclass(cls, builtin)
    assert not issubclass(cls, ValueError)
    err = cls("out.fits: cannot write (No space left on device)")
    assert str(err) == "out.fits: cannot write (No space left on device)"
    assert not issubclass(InjectError, ValueError)


def test_errors_and_warnings_are_apart():
    for cls in _classes():
        assert issubclass(cls, InjectError) != issubclass(cls, Warning), cls
    assert issubclass(InputWarning, UserWarning) and issubclass(OrbitWarning, UserWarning)


def _raise_input_error(name):
    raise InputError(name, 99.5, "must be <= 30")


def test_an_input_error_comes_back_from_a_worker_process():
    """Before: the pool's result thread failed to unpickle it, and every pending task
    failed with BrokenProcessPool."""
    from inject.exposure.runner import process_pool

    with process_pool(1) as pool:
        failing = pool.submit(_raise_input_error, "satellites[0].mag")
        after = pool.submit(pow, 2, 10)
        err = failing.exception(timeout=120)
        assert type(err) is InputError and str(err) == "satellites[0].mag=99.5: must be <= 30"
        assert err.name == "satellites[0].mag" and err.value == 99.5
        assert after.result(timeout=120) == 1024  # the pool is not broken


# --- OutputError is an OSError now: code that turns an OSError into an OutputError must let
# an OutputError through as it is.

def test_output_error_inside_atomic_path_keeps_its_message(tmp_path):
    from inject.io.atomic import atomic_path

    path = tmp_path / "out.exr"
    with pytest.raises(OutputError) as info:
        with atomic_path(path):
            raise OutputError(f"{path}: cannot write EXR (no writer)")
    assert str(info.value) == f"{path}: cannot write EXR (no writer)"
    assert not path.exists() and not list(tmp_path.iterdir())


def test_output_appearing_during_a_group_is_reported_once(tmp_path):
    from inject.io.atomic import atomic_path, output_group

    path = tmp_path / "out.fits"
    with pytest.raises(OutputError) as info:
        with output_group([path]):
            with atomic_path(path) as tmp:
                with open(tmp, "w") as stream:
                    stream.write("ours")
            path.write_text("another process's")
    assert str(info.value) == f"{path}: exists; pass --overwrite to replace it"
    assert path.read_text() == "another process's"
