"""``dragd``: the parser assembled from the command modules, and ``main`` (the entry point).

Every subcommand lives in the module named for its subject; ``COMMANDS`` lists them in ``dragd --help`` order.
Operator errors (bad input, missing or unreadable files, an absent CAN interface) end as one line on stderr,
``dragd: ...``, with a non-zero exit status.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from types import ModuleType

from dragd.cli import bench, can, daemon, experiment, gap, identify, log, model, payload, sim, teach, view
from dragd.cli.common import EXIT_FAIL, EXIT_USAGE, CliError, Parser

COMMANDS: tuple[ModuleType, ...] = (model, bench, sim, daemon, payload, view, can, log, identify, teach, gap,
                                    experiment)


def version() -> str:
    """The installed distribution's version, else the source tree's ``dragd.__version__``."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("dragd")
    except PackageNotFoundError:
        import dragd

        return dragd.__version__


def build_parser() -> Parser:
    parser = Parser(prog="dragd", description="Sensorless hand-guiding daemon for CiA 402 cobot arms.")
    parser.add_argument("--version", action="version", version=f"dragd {version()}")
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
    from dragd.config import ConfigError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        message, status = str(exc), exc.status
    except ConfigError as exc:
        message, status = str(exc), EXIT_USAGE
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
    print(f"dragd: {message}", file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
