#!/usr/bin/env bash
# The Raspberry Pi's lock file, requirements-pi.txt: every runtime dependency pinned, with
# hashes, for the robot's computer (aarch64, CPython 3.11, Raspberry Pi OS Bookworm:
# glibc 2.36, so manylinux_2_28 wheels), wheels only (nothing compiles on the Pi).
# Left out: what Adafruit Blinka requires for other boards and never imports for the
# motor HAT on a Pi (FTDI and Binho USB adapters, pulseio, CircuitPython's HTTP types);
# docs/benchmarks-history.md "Dependencies on the Pi" has the sizes and the check. The README's
# deployment installs it with `pip install --no-deps --require-hashes -r requirements-pi.txt`.
#
#   tools/lock-pi.sh           write requirements-pi.txt (newest versions today)
#   tools/lock-pi.sh --check   resolve pyproject.toml against the committed file: exit 1
#                              if it does not resolve or the result differs from the file
# Needs uv (PyPI: `pip install uv`); reaches PyPI.
set -euo pipefail
cd "$(dirname "$0")/.."
UV=${UV:-uv}
LOCK=requirements-pi.txt
TRIM=(pyftdi pyusb binho-host-adapter sysv-ipc adafruit-circuitpython-requests
      adafruit-circuitpython-connectionmanager setuptools)
compile() {
    "$UV" pip compile pyproject.toml --quiet --python-platform aarch64-manylinux_2_28 --python-version 3.11 \
        --no-build --generate-hashes --custom-compile-command "tools/lock-pi.sh" \
        "${TRIM[@]/#/--no-emit-package=}" "$@"
}
if [[ ${1:-} == --check ]]; then
    fresh=$(mktemp)
    trap 'rm -f "$fresh"' EXIT
    compile --constraints "$LOCK" --output-file "$fresh"
    # the pins and hashes must agree; comments (which package wants which) may differ
    if ! diff -u <(grep -v '^ *#' "$LOCK") <(grep -v '^ *#' "$fresh"); then
        echo "$LOCK does not match pyproject.toml: run tools/lock-pi.sh and commit the result" >&2
        exit 1
    fi
    echo "$LOCK: resolves for aarch64 / CPython 3.11 (manylinux_2_28), wheels only"
else
    compile --upgrade --output-file "$LOCK"  # --upgrade: not the versions already in the file
    echo "wrote $LOCK"
fi
