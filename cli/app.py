"""The `rover` command: one module per subcommand (`rover.cli.run`, `rover.cli.check`, ...), each with
`add_parser` and `run`. Library errors become one line on stderr and an exit status: 2 for bad input,
1 for a failed run, 3 for partial results, 130/143 after an interrupt."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from types import FrameType

from rover import __version__
from rover.cli import aoa, calibrate, certs, check, convert, evaluate, graph, info, record, simulate, status
from rover.cli import run as run_command
from rover.cli.args import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_PARTIAL
from rover.errors import BadInput, Interrupted, PeerLost, RoverError, SpecError

COMMANDS = (run_command, record, check, certs, graph, status, convert, simulate, evaluate, calibrate, aoa, info)
"""in the order `rover --help` lists them"""


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="rover", description="Localize a robot and WiFi backscatter tags with AoA-IMU SLAM, as a Zenoh dataflow."
    )
    ap.add_argument("--version", action="version", version=f"rover {__version__}")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    ap.add_argument("-q", "--quiet", action="store_true", help="only errors")
    common = argparse.ArgumentParser(add_help=False)  # -v/-q work after the command too
    common.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS, help="more log output")
    common.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS, help="only errors")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub, common)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    level = logging.ERROR if args.quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="rover: %(levelname)s: %(message)s")
    if os.environ.get("RUST_LOG"):  # Zenoh's own log, e.g. its access-control decisions (docs/security.md)
        import zenoh

        zenoh.init_log_from_env_or("error")
    previous = (
        {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
        if threading.current_thread() is threading.main_thread()
        else {}
    )
    try:
        status: int = args.func(args)
        return status
    except Interrupted as exc:
        return 128 + exc.signum
    except SpecError as exc:
        for d in exc.diagnostics:
            print(d, file=sys.stderr)
        return EXIT_BAD_INPUT
    except BadInput as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except PeerLost as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_PARTIAL
    except RoverError as exc:
        print(f"rover: error: {_one_line(exc)}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        return 128 + signal.SIGINT
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _one_line(exc: Exception) -> str:
    """An error's message on one line, whatever a library put in it (a reason quoting a file's text)."""
    return " ".join(str(exc).split())


def _interrupt(signum: int, _frame: FrameType | None) -> None:
    """SIGINT and SIGTERM stop a command where it is; its outputs clean up on the way out
    (`rover run` has its own handlers, which let the operators drain and finish)."""
    raise Interrupted(signum)


if __name__ == "__main__":
    sys.exit(main())
