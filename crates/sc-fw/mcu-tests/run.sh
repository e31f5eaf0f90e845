#!/usr/bin/env bash
# Builds the Cortex-M4 test binary and runs it in QEMU mps2-an386; exits with its status.
# Needs qemu-system-arm (Debian: qemu-system-arm). Usage: crates/sc-fw/mcu-tests/run.sh
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"; exit 0 ;; esac
cd "$(dirname "$0")"
exec timeout 300 "${CARGO:-cargo}" run --release
