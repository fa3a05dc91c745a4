#!/usr/bin/env bash
# Run the whole test suite (installs what it needs on first use).
source "$(dirname "$0")/_venv.sh" test
cd "$ROOT"
exec "$VENV/bin/python" -m pytest "$@"
