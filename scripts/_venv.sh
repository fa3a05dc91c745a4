# Sourced by serve.sh and test.sh: create .venv at the repository root and install the
# project into it on first use (or when pyproject.toml changed since the last install).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3}"
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
  "$VENV/bin/python" -m pip install -q --upgrade pip
fi
STAMP="$VENV/.installed-$1"
current() { [ -f "$1" ] && ! [ "$ROOT/pyproject.toml" -nt "$1" ]; }
# the test install (the project plus its test extras) holds everything the service needs
if ! current "$STAMP" && ! { [ "$1" = "serve" ] && current "$VENV/.installed-test"; }; then
  if [ "$1" = "test" ]; then EXTRA="[test]"; else EXTRA=""; fi
  "$VENV/bin/python" -m pip install -q -e "$ROOT$EXTRA"
  touch "$STAMP"
fi
