#!/usr/bin/env bash
# Run the planning service on http://127.0.0.1:8000 (installs what it needs on first use).
source "$(dirname "$0")/_venv.sh" serve
cd "$ROOT"
exec "$VENV/bin/python" -m service "$@"
