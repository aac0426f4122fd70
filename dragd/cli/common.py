"""What every ``dragd`` command shares: the parser class, errors, number lists, output, common options."""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

EXIT_USAGE = 2
EXIT_FAIL = 1
DEFAULT_SOCKET = "/run/dragd/dragd.sock"

_NUMBER = r"-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# "-0.5" and "-0.5,0.2,0": a value, never an option (argparse's own matcher takes single numbers only)
_NEGATIVE_NUMBERS = re.compile(rf"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?:,\s*(?:{_NUMBER})?)*$")


class CliError(Exception):
    """A user-facing error: printed as ``dragd: <message>`` with exit status 2 (bad input) or 1."""

    def __init__(self, message: str, status: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.status = status


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` that reads a comma-separated list of numbers starting with '-' as a value.

    ``--q -0.5,0.2,0`` would otherwise fail with "expected one argument". Subcommand parsers inherit the class.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBERS


def floats(text: str, what: str) -> list[float]:
    """``text`` as comma-separated finite numbers; ``what`` (the option) names it in the error."""
    try:
        values = [float(x) for x in text.split(",") if x.strip() != ""]
    except ValueError:
        raise CliError(f"{what}: expected comma-separated numbers, got '{text}'") from None
    if any(v != v or v in (float("inf"), float("-inf")) for v in values):
        raise CliError(f"{what}: expected finite numbers, got '{text}'")
    return values


def emit(args: argparse.Namespace, data: dict[str, Any], text: Callable[[dict[str, Any]], str]) -> None:
    """Print ``data`` as one JSON line with ``--json``, else ``text(data)``."""
    if getattr(args, "json", False):
        print(json.dumps(data))
    else:
        print(text(data))


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A right-aligned text table; floats with 4 decimals."""
    cells = [list(map(str, headers))] + [[f"{c:.4f}" if isinstance(c, float) else str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def add_config(p: argparse.ArgumentParser, params: bool = True) -> None:
    """``--config`` (and ``--params`` unless ``params`` is false)."""
    p.add_argument("--config", type=Path, default=None, help="configuration YAML (default: $DRAGD_CONFIG, "
                   "/etc/dragd/dragd.yaml, else the shipped config/default.yaml)")
    if params:
        p.add_argument("--params", type=Path, default=None, help="identified-parameters file overriding the config's")


def absolute(path: Path | None) -> Path | None:
    """``path`` made absolute for the simulator and daemon processes a command starts (their working folder differs)."""
    return None if path is None else path.expanduser().absolute()


def default_socket() -> str:
    """The daemon's control socket for clients: ``$DRAGD_SOCKET``, else /run/dragd/dragd.sock."""
    return os.environ.get("DRAGD_SOCKET") or DEFAULT_SOCKET


def add_socket(p: argparse.ArgumentParser, timeout: float = 10.0, json_flag: bool = True) -> None:
    """``--socket`` (default :func:`default_socket`), ``--timeout`` and, unless ``json_flag`` is false, ``--json``."""
    p.add_argument("--socket", default=default_socket(),
                   help=f"daemon control socket (default: $DRAGD_SOCKET, else {DEFAULT_SOCKET})")
    p.add_argument("--timeout", type=float, default=timeout,
                   help=f"seconds to wait for the daemon's answer (default {timeout:g})")
    if json_flag:
        p.add_argument("--json", action="store_true", help="print JSON")


class Stages:
    """Progress of a long offline command on stderr, one stage at a time (quiet with ``--json``).

    A terminal shows rich's spinner with the stage and, as each ends, a line with its elapsed time
    (``identify fit: reading log.mcap ... 2.1 s``). Not a terminal (a pipe, a log file): silent, so an error stays
    the one line on stderr, unless ``DRAGD_PROGRESS=1`` asks for the stage lines::

        with Stages(args, "identify fit") as st:
            st.stage("reading log.mcap")
            ...
            st.stage("fitting")
    """

    def __init__(self, args: argparse.Namespace, command: str) -> None:
        import sys

        self.command = command
        self.quiet = bool(getattr(args, "json", False)) or not (
            sys.stderr.isatty() or os.environ.get("DRAGD_PROGRESS") == "1")
        self._stream = sys.stderr
        self._status: Any = None
        self._name: str | None = None
        self._t0 = 0.0
        self.done: list[tuple[str, float]] = []

    def __enter__(self) -> Stages:
        if not self.quiet and self._stream.isatty():
            from rich.console import Console

            self._status = Console(stderr=True).status("")
            self._status.start()
        return self

    def _end(self) -> None:
        import time

        if self._name is None:
            return
        dt = time.perf_counter() - self._t0
        self.done.append((self._name, dt))
        if not self.quiet:
            if self._status is not None:
                self._status.console.print(f"{self.command}: {self._name} ... {dt:.1f} s")
            else:
                print(f"{self.command}: {self._name} ... {dt:.1f} s", file=self._stream, flush=True)
        self._name = None

    def stage(self, name: str) -> None:
        import time

        self._end()
        self._name, self._t0 = name, time.perf_counter()
        if self._status is not None:
            self._status.update(f"{self.command}: {name} ...")

    def __exit__(self, *exc: object) -> None:
        if exc[0] is None:
            self._end()
        if self._status is not None:
            self._status.stop()
