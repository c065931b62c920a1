"""Command-line interface: ``inject profile``, ``inject simulate``, ...

The ``inject`` parser and entry point; each command is a module of :mod:`inject.cli` (its
parser and its run: :mod:`~inject.cli.profile`, :mod:`~inject.cli.simulate`,
:mod:`~inject.cli.add_streak`, :mod:`~inject.cli.mask`, :mod:`~inject.cli.evaluate`,
:mod:`~inject.cli.focalplane`, :mod:`~inject.cli.satellite_pass`, :mod:`~inject.cli.survey`),
which imports the engine only when it runs, so that ``inject --help`` stays quick.

Each subcommand parses its options, calls the engine and prints or writes the result. Any
:class:`~inject.errors.InjectError` becomes a one-line message on stderr and exit status 2
(``--traceback``, before or after the subcommand, shows the full stack instead); so do
argparse's usage errors (without the usage block: ``inject simulate --help`` shows it).
Every warning is one line too, ``inject CMD: warning: ...``, each text once (a library's,
such as ERFA's for a time beyond its tables, by its class name or reason, without a path).
Reports and progress are the ``inject`` loggers' (:mod:`inject.cli.logs`): ``-q`` shows
warnings and errors only, ``-v`` debugging messages too, before or after the subcommand.
SIGINT, SIGTERM and SIGHUP stop a command cleanly (:mod:`inject.signals`: no temporary or
half-moved file is left) with exit status 128 + the signal's number; a closed pipe on stdout
(``inject profile --json | head``) ends it quietly, as Unix tools do.
"""
import argparse
import functools
import logging
import os
import re
import signal
import sys
import warnings

import inject
from inject.cli.add_streak import add_add_streak_parser
from inject.cli.evaluate import add_evaluate_parser
from inject.cli.focalplane import add_focalplane_parser
from inject.cli.logs import command_logging, level_of
from inject.cli.mask import add_mask_parser
from inject.cli.options import add_verbosity_options
from inject.cli.profile import add_profile_parser
from inject.cli.satellite_pass import add_pass_parser
from inject.cli.simulate import add_simulate_parser
from inject.cli.survey import add_survey_parser
from inject.errors import InjectError, InputWarning, OrbitWarning
from inject.signals import Stopped, handling

log = logging.getLogger(__name__)


def _one_line(text):
    """``text`` with every run of whitespace (newlines included) as one space."""
    return " ".join(str(text).split())


def _usage_error(prog, message):
    """Exit with status 2 (argparse's, for usage errors) after ``PROG: error: MESSAGE``."""
    print(f"{prog}: error: {_one_line(message)}", file=sys.stderr)
    sys.exit(2)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` with each option's default, except where there is none to show (None,
    False for a flag, an empty list)."""

    def _get_help_string(self, action):
        default = action.default
        if default is None or default is False or default == [] or default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr, exit status 2.

    argparse prints the whole usage block before the error; that block is what ``--help``
    is for. Sub-parsers are of the same class (``add_subparsers`` uses the parent's), so
    their errors name the subcommand: ``inject simulate: error: argument --seed: ...``, and
    their help shows the defaults.
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        _usage_error(self.prog, message)


class _VersionAction(argparse.Action):
    """``--version``: print ``inject VERSION`` and exit; the version is read only then (it may
    run git), not for every parse."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0,
                         help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"inject {inject.__version__}")
        parser.exit()


def build_parser():
    """The ``inject`` argument parser with every subcommand."""
    parser = _Parser(
        prog="inject", description="Realistic satellite streaks for Rubin/LSSTCam images.")
    parser.add_argument("--version", action=_VersionAction,
                        help="show inject's version (from git in a checkout) and exit")
    parser.add_argument("--traceback", action="store_true",
                        help="show the full traceback on errors")
    add_verbosity_options(parser)
    sub = parser.add_subparsers(dest="command", required=True)
    for add_parser in (add_profile_parser, add_simulate_parser, add_add_streak_parser,
                       add_mask_parser, add_evaluate_parser, add_focalplane_parser,
                       add_pass_parser, add_survey_parser):
        add_parser(sub)
    for command in sub.choices.values():
        # After the subcommand too; SUPPRESS: not given there, the top-level value stands.
        command.add_argument("--traceback", action="store_true", default=argparse.SUPPRESS,
                             help="show the full traceback on errors")
        add_verbosity_options(command, after_command=True)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None, seen=None):
    """Every warning as one line, ``inject CMD: warning: ...`` (a WARNING record of this
    module's logger), each text once per command (``seen``: the texts shown so far); no file
    path or source line."""
    text = _warning_text(message, category)
    if seen is not None:
        if text in seen:
            return
        seen.add(text)
    log.warning("%s", text)


#: ERFA's reasons (``yielded N of "REASON"``), as one line each whatever function gave them.
_ERFA_REASONS = {
    "dubious year": "a time lies beyond the leap-second table bundled with astropy: UTC "
                    "after it is taken with the last leap second (ERFA: dubious year)",
    "date outside": "a time lies outside 1900-2100, where ERFA's Earth ephemeris (epv00) "
                    "is less accurate",
}


def _warning_text(message, category):
    """The one-line text of a warning: inject's own as they are, ERFA's by their reason (the
    same for every function and count), others after their class name."""
    text = _one_line(message)
    if issubclass(category, (InputWarning, OrbitWarning)):
        return text
    if category.__name__ == "ErfaWarning":
        match = re.match(r'ERFA function "(\w+)" yielded \d+ of "(.*)"', text)
        if match:
            function, reason = match.groups()
            for key, words in _ERFA_REASONS.items():
                if key in reason:
                    return words
            return f"ERFA {function}: {reason}"
    return f"{category.__name__}: {text}"


def _quiet_broken_pipe():
    """After EPIPE on stdout: point it at /dev/null, so the interpreter's final flush does not
    fail again (the recipe of Python's signal documentation)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # stdout replaced (tests) or closed
        pass


def main(argv=None):
    """Entry point of the ``inject`` console script; returns the exit status."""
    command = "inject"
    try:
        # The stop signals are handled from the start: a Ctrl-C while the parser is built or
        # a command imports the engine is a clean stop too, not a traceback.
        with handling():
            parser = build_parser()
            # Overrides (key.path=value) may come after options: argparse leaves them as extras.
            args, extra = parser.parse_known_args(argv)
            command = f"inject {args.command}"
            if extra:
                if not hasattr(args, "overrides") or any("=" not in item for item in extra):
                    # The subcommand's error, as argparse itself would word it.
                    _usage_error(command, f"unrecognized arguments: {' '.join(extra)}")
                args.overrides = list(args.overrides) + extra
            if args.quiet and args.verbose:  # one before the subcommand, one after
                _usage_error(command, "argument -v/--verbose: not allowed with argument "
                                      "-q/--quiet")
            with command_logging(command, level_of(args)):
                return _run(args, command)
    except BrokenPipeError:
        # The reader went away (| head): stop quietly, with the status of a process killed by
        # SIGPIPE, as Unix tools do.
        _quiet_broken_pipe()
        return 128 + signal.SIGPIPE
    except Stopped as stop:
        print(f"{command}: {stop}; no output left half-written", file=sys.stderr)
        return stop.exit_status
    except KeyboardInterrupt:  # raised by Python's own handler, outside inject.signals
        print(f"{command}: interrupted", file=sys.stderr)
        return 128 + signal.SIGINT


def _run(args, command):
    """Run the subcommand; an :class:`InjectError` is one line and status 2."""
    try:
        with warnings.catch_warnings():
            warnings.showwarning = functools.partial(_show_warning, seen=set())
            args.func(args)
            sys.stdout.flush()  # a closed pipe shows here, where main catches it
    except InjectError as err:
        if args.traceback:
            raise
        # One line, whatever the library said.
        print(f"{command}: error: {_one_line(err)}", file=sys.stderr)
        return 2
    return 0
