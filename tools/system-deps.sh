#!/usr/bin/env bash
# Installs the system packages the test suite drives, when they are missing: Debian's
# Chromium (the phone page in a real browser, through Playwright with
# executable_path=/usr/bin/chromium, never a downloaded browser) and systemd-analyze
# (checks the unit file). Uses sudo unless run as root. Part of `make test`.
set -euo pipefail
missing=()
command -v chromium >/dev/null || missing+=(chromium)
command -v chromedriver >/dev/null || missing+=(chromium-driver)
command -v systemd-analyze >/dev/null || missing+=(systemd)
if ((${#missing[@]})); then
    sudo_cmd=()
    [[ $(id -u) -eq 0 ]] || sudo_cmd=(sudo)
    "${sudo_cmd[@]}" apt-get update -qq
    "${sudo_cmd[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

