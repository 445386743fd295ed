"""``dresg <command> ...`` (or ``python -m dresg_addon <command> ...``): one sub-command per module in
``dresg_addon/commands``.

Each command module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
Engine errors (:class:`~dresg_addon.util.errors.DresgError`) become one line on stderr and exit code 2.
``main`` owns the process: it applies the thread policy (:mod:`dresg_addon.util.threads`), hides torch's
note that CSR tensors are beta, and hands each command a :class:`~dresg_addon.util.threads.ThreadAdapter`
for torch's thread count (``args.threads``).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from . import __version__
from .util.errors import DresgError
from .util.threads import ThreadAdapter, apply_thread_policy

COMMAND_MODULES = (
    "info",
    "convert",
    "render",
    "evaluate",
    "select_views",
    "stylize",
    "demo",
    "report",
)


def program_name() -> str:
    """How the user called us: ``dresg`` (the console command) or ``python -m dresg_addon``."""
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    return "python -m dresg_addon" if name in ("", "__main__.py", "-c") else name


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=program_name(),
        description="Stylize 3D Gaussian Splatting scenes after a reference image (DReSG).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(f".commands.{name}", __package__)
        command_parser = sub.add_parser(
            module.NAME,
            help=module.HELP,
            description=module.HELP,
            formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        )
        module.add_arguments(command_parser)
        command_parser.set_defaults(run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    apply_thread_policy()  # before any command loads torch: libgomp reads it once
    # torch's once-a-process note that its CSR tensors (the colour maps') are beta: nothing a user can act on
    warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
    args = build_parser().parse_args(argv)
    args.threads = ThreadAdapter()  # the commands call it between views and steps, on this thread
    try:
        return int(args.run(args) or 0)
    except DresgError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
