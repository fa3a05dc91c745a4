#!/usr/bin/env bash
# Run the planning service, by default on 0.0.0.0:8000 (installs what it needs on first use).
# Arguments go to `python -m service`: --host, --port, --help.
source "$(dirname "$0")/_venv.sh" serve
cd "$ROOT"
exec "$VENV/bin/python" -m service "$@"
