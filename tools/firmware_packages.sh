#!/usr/bin/env bash
# The Debian packages `make firmware` needs: avr-gcc, avr-libc and binutils-avr build the
# LED board's firmware; simavr (libsimavr-dev, libsimavrparts1) runs it in the tests.
# Missing ones are installed when run as root (as CI is, after an apt-get update if the
# package lists are stale); otherwise this stops with the one command to run.
set -euo pipefail
PACKAGES=(gcc-avr avr-libc binutils-avr simavr libsimavr-dev libsimavrparts1)
INSTALL=(apt-get install -y --no-install-recommends "${PACKAGES[@]}")

missing=()
for package in "${PACKAGES[@]}"; do
    status=$(dpkg-query -W -f='${Status}' "$package" 2>/dev/null || true)
    [[ $status == "install ok installed" ]] || missing+=("$package")
done
((${#missing[@]} == 0)) && exit 0

if ((EUID != 0)); then
    echo "firmware: Debian packages missing: ${missing[*]}; run:" >&2
    echo "  sudo ${INSTALL[*]}" >&2
    exit 1
fi
echo "firmware: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
"${INSTALL[@]}" || { apt-get update && "${INSTALL[@]}"; }
