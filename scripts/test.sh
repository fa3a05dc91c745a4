#!/usr/bin/env bash
# Run the whole test suite (installs what it needs on first use).
source "$(dirname "$0")/_venv.sh" test
cd "$ROOT"
# Bytecode caches on (PYTHONDONTWRITEBYTECODE is set on some machines): the suite starts many
# Python processes (servers, their forkservers, CLI runs), each of which compiled the project's
# sources again, and pytest rewrote its plugins' modules (hundreds) anew at every collection
# (collecting the suite: 32 s of CPU without the caches, 22 s with them). The caches are written
# to __pycache__ folders, which git ignores.
unset PYTHONDONTWRITEBYTECODE
exec "$VENV/bin/python" -m pytest "$@"
