"""``dragd``: the parser assembled from the command modules, and ``main`` (the entry point).

Every subcommand lives in the module named for its subject; ``COMMANDS`` lists them in ``dragd --help`` order.
Operator errors (bad input, missing or unreadable files, an absent CAN interface) end as one line on stderr,
``dragd: ...``, with a non-zero exit status.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

from dragd.cli import (
    bench,
    can,
    contact,
    daemon,
    experiment,
    gap,
    identify,
    log,
    model,
    payload,
    ros2,
    sim,
    teach,
    view,
)
from dragd.cli.common import EXIT_FAIL, EXIT_USAGE, CliError, Parser

COMMANDS: tuple[ModuleType, ...] = (model, bench, sim, daemon, payload, view, can, log, identify, teach, gap,
                                    contact, experiment, ros2)


def version() -> str:
    """The installed distribution's version, else the source tree's ``dragd.__version__``."""
    import dragd

    return dragd.__version__


class _Version(argparse.Action):
    """``--version``: the version looked up only when asked for."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, **kw: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help="show the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *_: Any) -> None:
        print(f"dragd {version()}")
        parser.exit()


def build_parser() -> Parser:
    parser = Parser(prog="dragd", description="Sensorless hand-guiding daemon for CiA 402 cobot arms.")
    parser.add_argument("--version", action=_Version)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMANDS:
        module.register(sub)
    return parser


def _os_error(exc: OSError) -> str:
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        message, status = str(exc), exc.status
    except FileNotFoundError as exc:
        message, status = _os_error(exc), EXIT_USAGE
    except BrokenPipeError:  # the reader went away (dragd ... | head): no message, no flush error at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_FAIL
    except OSError as exc:  # unreadable file, socket directory missing, permission denied, ...
        message, status = _os_error(exc), EXIT_FAIL
    except UnicodeDecodeError as exc:
        message, status = f"a file is not UTF-8 text ({exc})", EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    except ValueError as exc:  # a ConfigError (not imported here: `dragd status` must not pay for the schema)
        config = sys.modules.get("dragd.config")
        if config is None or not isinstance(exc, config.ConfigError):
            raise
        message, status = str(exc), EXIT_USAGE
    print(f"dragd: {message}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
