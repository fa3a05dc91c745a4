"""``python -m service``: run the planning service with uvicorn on the configured host/port.

The workers' forkserver is started first, before the server imports its web stack, so that the
solver modules load and warm up (:mod:`service.preload`) on another core while uvicorn and the
app load here: the service is ready about as soon as the slower of the two is done.
"""

from __future__ import annotations

import argparse
import os
import signal
from collections.abc import Sequence
from types import FrameType


def _exit_cleanly(signum: int, frame: FrameType | None) -> None:
    """SIGTERM outside uvicorn's own handling: exit with status 0.

    uvicorn handles SIGTERM while it serves (it stops accepting connections, lets requests in
    flight finish and runs the lifespan shutdown, which stops the workers), then restores this
    handler and raises the signal again; ending here with 0 reports the graceful stop as a
    success to the supervisor. A SIGTERM before uvicorn serves ends the process the same way.
    """
    raise SystemExit(0)


def start_forkserver() -> None:
    """Start the workers' forkserver now (it imports :data:`service.workers.PRELOAD`).

    Only with the ``forkserver`` start method (``PLANNER_START_METHOD``, the default); the pool
    then uses this forkserver. Failing here is harmless: the pool starts it when it needs it.
    """
    if os.environ.get("PLANNER_START_METHOD", "forkserver") != "forkserver":
        return
    try:
        import multiprocessing
        from multiprocessing import forkserver

        from .workers import PRELOAD

        multiprocessing.get_context("forkserver").set_forkserver_preload(PRELOAD)
        forkserver.ensure_running()
    except Exception:  # noqa: BLE001 - an optimisation only
        pass


def _port(text: str) -> int:
    port = int(text) if text.isdigit() else 0
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number in 1..65535")
    return port


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line: ``--host``, ``--port`` override ``PLANNER_HOST``, ``PLANNER_PORT``."""
    parser = argparse.ArgumentParser(
        prog="python -m service",
        description="Run the planning service (uvicorn and a pool of solver workers). Every "
                    "setting is an environment variable PLANNER_*, see docs/settings.md; "
                    "the options below override theirs.")
    parser.add_argument("--host", help="listen address (PLANNER_HOST, default 0.0.0.0)")
    parser.add_argument("--port", type=_port,
                        help="listen port, 1..65535 (PLANNER_PORT, default 8000)")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> None:
    """Read the settings from the environment, set up JSON logs and serve ``service.main:app``
    (:func:`service.server.serve`)."""
    args = parse_args(argv)
    # the app (service.main:app, imported by uvicorn) reads its settings from the environment
    if args.host is not None:
        os.environ["PLANNER_HOST"] = args.host
    if args.port is not None:
        os.environ["PLANNER_PORT"] = str(args.port)
    signal.signal(signal.SIGTERM, _exit_cleanly)
    start_forkserver()
    from .logs import configure_logging
    from .server import serve
    from .settings import Settings

    settings = Settings()
    configure_logging(settings.log_level)
    serve(settings)


if __name__ == "__main__":
    main()
