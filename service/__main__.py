"""``python -m service``: run the planning service with uvicorn on the configured host/port."""

from __future__ import annotations

import uvicorn

from .logs import configure_logging
from .settings import Settings


def main() -> None:
    """Read the settings from the environment, set up JSON logs and serve ``service.main:app``."""
    settings = Settings()
    configure_logging(settings.log_level)
    uvicorn.run("service.main:app", host=settings.host, port=settings.port,
                log_level=settings.log_level, log_config=None, access_log=False,
                proxy_headers=True, server_header=False)


if __name__ == "__main__":
    main()
