"""``python -m service``: run the planning service with uvicorn on the configured host/port."""

from __future__ import annotations

import math
import signal
from types import FrameType

import uvicorn

from .logs import configure_logging
from .settings import Settings


def _exit_cleanly(signum: int, frame: FrameType | None) -> None:
    """SIGTERM outside uvicorn's own handling: exit with status 0.

    uvicorn handles SIGTERM while it serves (it stops accepting connections, lets requests in
    flight finish and runs the lifespan shutdown, which stops the workers), then restores this
    handler and raises the signal again; ending here with 0 reports the graceful stop as a
    success to the supervisor. A SIGTERM before uvicorn serves ends the process the same way.
    """
    raise SystemExit(0)


def main() -> None:
    """Read the settings from the environment, set up JSON logs and serve ``service.main:app``."""
    settings = Settings()
    configure_logging(settings.log_level)
    signal.signal(signal.SIGTERM, _exit_cleanly)
    uvicorn.run("service.main:app", host=settings.host, port=settings.port,
                log_level=settings.log_level, log_config=None, access_log=False,
                proxy_headers=True, server_header=False,
                # SIGTERM: stop accepting, let requests in flight finish (at most this long),
                # then the lifespan stops the workers; the exit status is 0
                timeout_graceful_shutdown=int(math.ceil(settings.shutdown_timeout)))


if __name__ == "__main__":
    main()
