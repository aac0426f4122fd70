"""``dragd config init --robot PATH [--out FILE]``: a starting configuration for any robot from its URDF
(joint names from the URDF, node ids 1..N, drives sized from its effort limits and gravity; docs in README)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, floats


def cmd_config_init(args: argparse.Namespace) -> int:
    from dragd.robots.starter import starting_config

    gravity = (0.0, 0.0, -9.81)
    if args.gravity:
        values = floats(args.gravity, "--gravity")
        if len(values) != 3:
            raise CliError(f"--gravity: expected three numbers GX,GY,GZ [m/s²], got '{args.gravity}'")
        gravity = (values[0], values[1], values[2])
    if args.eds is None and (args.buses is not None or args.rate is not None):
        raise CliError("--buses and --rate go with --eds (dragd's own drive: one CAN FD bus at 1 kHz)")
    out_dir = Path(args.out).expanduser().absolute().parent if args.out else Path.cwd()
    try:
        text = starting_config(args.robot, Path.cwd(), gravity, eds=args.eds, out_dir=out_dir, buses=args.buses,
                               rate_Hz=args.rate)
    except (FileNotFoundError, ValueError) as exc:
        raise CliError(f"{'--eds' if args.eds and '--eds' in str(exc) else '--robot'}: {exc}".replace(
            "--eds: --eds", "--eds")) from None
    if args.out is None:
        sys.stdout.write(text)
        return 0
    out = Path(args.out)
    if out.exists() and not args.force:
        raise CliError(f"--out {out}: exists; --force overwrites it")
    out.write_text(text)
    print(f"{out}: starting configuration for {args.robot}; check the drives, then 'dragd config check --config {out}'",
          file=sys.stderr)
    return 0


def register_config(csub: Any) -> None:
    """Add ``init`` to the ``dragd config`` subcommands (``csub``: their subparsers action)."""
    p = csub.add_parser("init", help="print a starting configuration for a robot from its URDF (joint names, node ids "
                                     "1..N, drives sized from its effort limits and gravity)")
    p.add_argument("--robot", required=True, help="bundled robot name or URDF path")
    p.add_argument("--gravity", help="gravity vector GX,GY,GZ [m/s²] in the URDF's base frame (default 0,0,-9.81)")
    p.add_argument("--eds", type=Path, help="the joints' drive: its vendor's EDS file (classic CAN or FD, layout, "
                                            "buses and loop rate as the EDS and the bus budget allow; docs/DRIVES.md)")
    p.add_argument("--buses", type=int, help="with --eds: this many buses (the loop rate lowered until they fit); "
                                             "default: the fewest buses that carry the joints at 1 kHz")
    p.add_argument("--rate", type=float, help="with --eds: the loop rate [Hz] (default 1000)")
    p.add_argument("--out", help="write the configuration to this file instead of standard output")
    p.add_argument("--force", action="store_true", help="overwrite --out")
    p.set_defaults(func=cmd_config_init)
