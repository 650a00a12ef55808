#!/usr/bin/env bash
# Makes sure the Cortex-M toolchain and emulator that tests/test_embedded_qemu.py needs are
# present: qemu-system-arm, arm-none-eabi-gcc and newlib (nano + rdimon specs). Installs the
# missing Debian packages with apt-get when it can (root, apt available: CI), quietly.
# Exit codes: 0 all present (or installed); 3 something missing and not installable here
# (one line on stderr naming the tool and the command that installs it).
# COCHLEA_NO_INSTALL=1: report what is missing, install nothing.
set -u
PKGS=()
command -v qemu-system-arm >/dev/null 2>&1 || PKGS+=(qemu-system-arm)
command -v arm-none-eabi-gcc >/dev/null 2>&1 || PKGS+=(gcc-arm-none-eabi)
# newlib: the specs files the firmware links with.
if ! ls /usr/lib/arm-none-eabi/newlib/nano.specs >/dev/null 2>&1 \
   || ! ls /usr/lib/arm-none-eabi/newlib/rdimon.specs >/dev/null 2>&1; then
    PKGS+=(libnewlib-arm-none-eabi)
fi
[ ${#PKGS[@]} -eq 0 ] && exit 0

HOW="apt-get install -y --no-install-recommends ${PKGS[*]}"
if [ "${COCHLEA_NO_INSTALL:-0}" = 1 ] || [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null 2>&1; then
    echo "ensure_tools: missing ${PKGS[*]} (install as root: $HOW)" >&2
    exit 3
fi
export DEBIAN_FRONTEND=noninteractive
if ! { apt-get install -y -qq --no-install-recommends "${PKGS[@]}" >/dev/null 2>&1 \
       || { apt-get update -qq >/dev/null 2>&1 \
            && apt-get install -y -qq --no-install-recommends "${PKGS[@]}" >/dev/null 2>&1; }; }; then
    echo "ensure_tools: could not install ${PKGS[*]} (try: apt-get update && $HOW)" >&2
    exit 3
fi
exit 0
