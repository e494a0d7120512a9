"""`crchfl-sumo <subcommand>`: parses arguments, calls the library, prints results.

Thin on purpose: every subcommand is a pair (add its arguments, run it) and the
work happens in the library modules. A CrchflError is printed as one line on
stderr with exit status 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys

from .errors import CrchflError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crchfl-sumo",
        description="Hierarchical federated learning for end-to-end driving on SUMO.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text, add_arguments, run in _commands():
        command = sub.add_parser(name, help=help_text, description=help_text)
        add_arguments(command)
        command.set_defaults(run=run)
    return parser


def _commands():
    """(name, help, add_arguments, run) for each subcommand, in the order --help lists them."""
    return []


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    try:
        return int(args.run(args) or 0)
    except CrchflError as exc:
        print(f"crchfl-sumo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("crchfl-sumo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
