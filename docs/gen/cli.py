"""Write reference/cli.md from the ``inject`` command's own argparse parsers at build time, so
the page shows exactly the options and defaults the installed code accepts."""
import argparse
import os
import sys
from pathlib import Path

import mkdocs_gen_files

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import importable  # noqa: E402

importable()
from inject.cli.main import build_parser  # noqa: E402

os.environ["COLUMNS"] = "96"  # argparse wraps the help to the terminal's width: fix it


def subcommands(parser):
    """``[(name, one-line help, subparser), ...]`` in the order ``inject --help`` lists them."""
    for action in parser._actions:  # argparse has no public accessor for these
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            return [(name, helps.get(name, ""), sub) for name, sub in action.choices.items()]
    return []


parser = build_parser()
commands = subcommands(parser)
lines = [
    "# Command line",
    "",
    "Generated from the `inject` command's own parsers when this site is built: each block",
    "is what `inject COMMAND --help` prints. Every command also takes `--traceback` (before",
    "or after the command's name) to show the full stack of an error, and `-q`/`--quiet` or",
    "`-v`/`--verbose` (the same) for less or more on stderr: see",
    "[messages and progress](../getting-started.md#messages-and-progress).",
    "",
    "| command | what it does |",
    "|---|---|",
]
for name, summary, _ in commands:
    lines.append(f"| [`inject {name}`](#inject-{name}) | {summary} |")
lines += [
    "",
    "Exit status: 0 on success; 2 for bad input (a one-line message naming the value);",
    "128 + the signal's number when stopped by Ctrl-C (130), SIGTERM (143) or SIGHUP (129);",
    "141 when the reading end of a pipe closes (`inject profile --json | head`).",
    "",
    "## `inject`",
    "",
    "```text",
    parser.format_help().rstrip(),
    "```",
    "",
]
for name, _, sub in commands:
    lines += [f"## `inject {name}`", "", "```text", sub.format_help().rstrip(), "```", ""]

with mkdocs_gen_files.open("reference/cli.md", "w") as f:
    f.write("\n".join(lines))
