"""Stop signals (SIGINT, SIGTERM, SIGHUP) at many moments: nothing left behind, exit 128 + N,
earlier outputs intact.

In-process tests send the signal to the test's own process from inside the command (after a
chosen call), which reaches exact moments deterministically: the temporary file just made,
half-written, each move of the final commit. Subprocess tests run the real command and signal
it from outside, when its handlers are installed or when a temporary file appears.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml
from astropy.io import fits

import inject.io.atomic as atomic
from inject.cli.main import main

SCENE = {"seed": 3, "detector": {"type": "itl", "nx": 96, "ny": 64}, "stars": False,
         "satellites": [{"height": 550, "shape": {"type": "box", "length": 7.25, "width": 2.65},
                         "mag": 8.0, "track": {"x0": 5, "y0": 10, "angle": 20}}]}
OUTPUTS = ("out.fits", "out.exr", "out.png", "out.csv")
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _default_handler(signum):
    return signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL


@pytest.fixture(autouse=True)
def _stop_signals_not_ignored():
    """A suite started in the background (``make test &``, ``nohup``) inherits SIGINT or
    SIGHUP ignored, and inject, as Unix tools do, leaves an ignored signal ignored: these
    tests need the ordinary dispositions, in this process and (see ``_default_signals``) in
    the commands they start."""
    saved = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    for signum, handler in saved.items():
        if handler is signal.SIG_IGN:
            signal.signal(signum, _default_handler(signum))
    yield
    for signum, handler in saved.items():
        signal.signal(signum, handler)


def _default_signals():
    """In a child before it runs the command: the stop signals at their defaults."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_DFL)


def _argv(tmp_path, *extra):
    return ["simulate", str(tmp_path / "scene.yaml"), "-o", str(tmp_path / "out.fits"),
            "--exr", str(tmp_path / "out.exr"), "--png", str(tmp_path / "out.png"),
            "--truth", str(tmp_path / "out.csv"), *extra]


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """The scene and the outputs of a first run: ``{name: bytes}``."""
    folder = tmp_path_factory.mktemp("first")
    (folder / "scene.yaml").write_text(yaml.safe_dump(SCENE))
    assert main(_argv(folder)) == 0
    return {name: (folder / name).read_bytes() for name in ["scene.yaml", *OUTPUTS]}


@pytest.fixture
def earlier(tmp_path, first_run):
    """``tmp_path`` holding the scene and the outputs of an earlier run: ``{name: bytes}``."""
    for name, content in first_run.items():
        (tmp_path / name).write_bytes(content)
    return first_run


def _assert_untouched(tmp_path, earlier):
    assert sorted(os.listdir(tmp_path)) == sorted(earlier)  # no .inject-* temporary left
    for name, content in earlier.items():
        assert (tmp_path / name).read_bytes() == content, name


def _signal_after(monkeypatch, owner, name, signum, nth=1):
    """Make the ``nth`` call of ``owner.name`` send ``signum`` to this process once it returns."""
    real = getattr(owner, name)
    calls = []

    def wrapper(*args, **kwargs):
        result = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == nth:
            os.kill(os.getpid(), signum)
        return result
    monkeypatch.setattr(owner, name, wrapper)
    return calls


MOMENTS = {
    # (object, attribute, nth call): the signal arrives just after that call returns.
    "scene parsed": ("inject.config", "parse_scene", 1),
    "simulated": ("inject.scene", "simulate", 1),
    "first temporary file made": ("inject.io.atomic", "_temporary", 1),  # the directory probe
    "FITS temporary made": ("inject.io.atomic", "_temporary", 5),
    "FITS written to its temporary": ("astropy.io.fits.HDUList", "writeto", 1),
    "quicklook drawn": ("inject.io.quicklook", "quicklook_figure", 1),
    "PNG temporary made": ("inject.io.atomic", "_temporary", 7),
    "first output moved": ("os", "replace", 1),
    "third output moved": ("os", "replace", 3),
    "last output moved": ("os", "replace", 4),
    "backup of an earlier output made": ("inject.io.atomic", "_keep_copy", 2),
}


def _owner(path):
    import importlib

    module, _, cls = path.partition(".HDUList")
    owner = importlib.import_module(module)
    return owner.HDUList if cls or path.endswith("HDUList") else owner


#: The default suite's cases; every other (signal, moment) pair runs with ``-m slow``.
FAST = {(signal.SIGTERM, m) for m in ("scene parsed", "FITS temporary made",
                                      "FITS written to its temporary", "PNG temporary made",
                                      "first output moved", "last output moved",
                                      "backup of an earlier output made")}
FAST |= {(signal.SIGINT, "third output moved"), (signal.SIGHUP, "first temporary file made")}
CASES = [pytest.param(n, m, id=f"{signal.Signals(n).name}-{m}",
                      marks=() if (n, m) in FAST else pytest.mark.slow)
         for n in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP) for m in MOMENTS]


@pytest.mark.parametrize("signum,moment", CASES)
def test_stop_at_any_moment_leaves_earlier_outputs(tmp_path, earlier, monkeypatch, capsys,
                                                   moment, signum):
    path, name, nth = MOMENTS[moment]
    calls = _signal_after(monkeypatch, _owner(path), name, signum, nth)
    status = main(_argv(tmp_path, "--overwrite", "seed=4"))
    assert calls, f"{moment}: never reached"
    assert len(calls) >= nth, f"{moment}: only {len(calls)} calls"
    assert status == 128 + signum
    err = capsys.readouterr().err
    assert f"stopped by {signal.Signals(signum).name}" in err and "Traceback" not in err
    _assert_untouched(tmp_path, earlier)


def test_stop_during_the_exr_write_is_clean(tmp_path, earlier, monkeypatch, capsys):
    """SIGINT while OpenImageIO writes (it used to end in UnboundLocalError from the finally)."""
    import OpenImageIO as oiio

    real_create = oiio.ImageOutput.create

    class Output:  # the real writer, signalled as its first image is written
        def __init__(self, out):
            self._out = out

        def write_image(self, *args):
            ok = self._out.write_image(*args)
            os.kill(os.getpid(), signal.SIGINT)
            return ok

        def __getattr__(self, name):
            return getattr(self._out, name)

    monkeypatch.setattr(oiio.ImageOutput, "create",
                        staticmethod(lambda *a: Output(real_create(*a))))
    assert main(_argv(tmp_path, "--overwrite", "seed=4")) == 128 + signal.SIGINT
    assert "UnboundLocalError" not in capsys.readouterr().err
    _assert_untouched(tmp_path, earlier)


def test_a_signal_inside_a_deferred_block_waits_for_its_end():
    from inject.signals import Stopped, deferred, handling

    done = []
    with handling(), pytest.raises(Stopped) as stop:
        with deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.01)  # the handler has run by now: it only recorded the signal
            done.append("rest of the block")
    assert done == ["rest of the block"] and stop.value.exit_status == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the old handler is back


def test_a_second_signal_does_not_cut_the_clean_up(tmp_path, earlier, monkeypatch):
    """Ctrl-C twice: the second arrives while the first's clean-up removes the temporaries."""
    real_remove = atomic._remove

    def remove(*paths):
        os.kill(os.getpid(), signal.SIGINT)
        return real_remove(*paths)
    monkeypatch.setattr(atomic, "_remove", remove)
    _signal_after(monkeypatch, _owner("inject.scene"), "simulate", signal.SIGINT)
    assert main(_argv(tmp_path, "--overwrite", "seed=4")) == 128 + signal.SIGINT
    monkeypatch.setattr(atomic, "_remove", real_remove)
    _assert_untouched(tmp_path, earlier)


def test_add_streak_stopped_while_writing(tmp_path, monkeypatch):
    image = tmp_path / "in.fits"
    fits.PrimaryHDU(np.zeros((50, 60), np.float32)).writeto(image)
    _signal_after(monkeypatch, fits.HDUList, "writeto", signal.SIGTERM)
    argv = ["add-streak", str(image), "-o", str(tmp_path / "out.fits"), "--height", "550",
            "--x0", "3", "--y0", "4", "--gain", "1", "--mag", "9"]
    assert main(argv) == 128 + signal.SIGTERM
    assert os.listdir(tmp_path) == ["in.fits"]


def test_evaluate_stopped_leaves_no_folder(tmp_path, monkeypatch):
    import inject.cli.evaluate as cli_evaluate

    def campaign(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGHUP)
        time.sleep(1)  # never finishes: the signal stops it
    monkeypatch.setattr(cli_evaluate, "run_campaign", campaign)
    out = tmp_path / "a" / "campaign"
    assert main(["evaluate", "--out", str(out)]) == 128 + signal.SIGHUP
    assert os.listdir(tmp_path) == []


# --- The real command, signalled from outside ----------------------------------------------

def _wait_for(condition, process, what, timeout=120.0):
    """Poll until ``condition()``; fail if the process ends first (the moment was missed)."""
    start = time.monotonic()
    while not condition():
        if process.poll() is not None:
            pytest.fail(f"the command ended (status {process.returncode}) before {what}")
        if time.monotonic() - start > timeout:  # a stuck command, not a timing check
            process.kill()
            pytest.fail(f"no {what} after {timeout} s")
        time.sleep(0.0005)


def _catches(pid, signum):
    """True once the process has a handler for ``signum`` (Linux: SigCgt in /proc/PID/status)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            caught = next(line for line in f if line.startswith("SigCgt:")).split()[1]
    except (OSError, StopIteration):
        return False
    return bool(int(caught, 16) >> (signum - 1) & 1)


def _hidden(folder, suffix):
    return any(n.startswith(".inject-") and n.endswith(suffix) for n in os.listdir(folder))


def _signal_at(tmp_path, signum, moment):
    """Run ``inject simulate`` into ``tmp_path`` and send ``signum`` at ``moment``;
    return the process, its stderr and the folder's files before."""
    scene = dict(SCENE, detector={"type": "itl", "nx": 1024, "ny": 1024})
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump(scene))
    (tmp_path / "out.png").write_bytes(b"an earlier quicklook")
    before = {n: (tmp_path / n).read_bytes() for n in os.listdir(tmp_path)}
    process = subprocess.Popen([sys.executable, "-m", "inject", *_argv(tmp_path, "--overwrite")],
                               cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               preexec_fn=_default_signals)
    if moment == "handlers installed":
        _wait_for(lambda: _catches(process.pid, signum), process, moment)
    else:
        suffix = {"FITS temporary": ".fits", "EXR temporary": ".exr",
                  "PNG temporary": ".png"}[moment]
        # Past the directory probes (which make and remove a temporary at once): the one being
        # written, still there a moment later.
        _wait_for(lambda: _catches(process.pid, signum), process, "handlers")
        _wait_for(lambda: _hidden(tmp_path, suffix) and (time.sleep(0.002) or
                                                         _hidden(tmp_path, suffix)),
                  process, moment)
    process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    return process, err, before


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux /proc")
@pytest.mark.parametrize("signum,moment", [
    (signal.SIGHUP, "handlers installed"),
    (signal.SIGTERM, "FITS temporary"),
    (signal.SIGINT, "EXR temporary"),
    (signal.SIGTERM, "PNG temporary"),
], ids=["SIGHUP-early", "SIGTERM-FITS", "SIGINT-EXR", "SIGTERM-PNG-late"])
def test_signalled_command(tmp_path, signum, moment):
    # A signal sent as the last temporary is renamed can land after the command has
    # finished its work (exit 0, every output written): a missed moment, tried again.
    for _ in range(3):
        process, err, before = _signal_at(tmp_path, signum, moment)
        if not (process.returncode == 0 and b"wrote" in err):
            break
        for name in set(os.listdir(tmp_path)) - set(before):
            os.remove(tmp_path / name)
    assert process.returncode == 128 + signum, err.decode()
    assert b"Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == sorted(before)
    assert all((tmp_path / n).read_bytes() == b for n, b in before.items())
