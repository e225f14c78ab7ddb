#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite.  Extra arguments go to pytest.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
cd "$here"
exec python -m pytest test -q "$@"
