#!/usr/bin/env bash
# Installs the Debian packages the project needs (AVR firmware toolchain, simavr; libfaketime
# for the tests that set a node's system clock back).
# Idempotent: does nothing when every package is already installed.
set -euo pipefail
pkgs=(gcc-avr avr-libc binutils-avr arduino-core-avr simavr libsimavr-dev libfaketime)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null; then
  echo "error: missing Debian packages ${missing[*]} and no apt-get on this machine" >&2
  exit 1
fi
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || { echo "error: need root (or sudo) to install ${missing[*]}" >&2; exit 1; }
  SUDO=sudo
fi
echo "installing Debian packages: ${missing[*]}"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
