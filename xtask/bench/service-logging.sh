#!/bin/sh
# The benchmark's gateway (this tree's static musl build) with the logging of the service
# (deploy/systemd/ihex-gateway.service): IHEX_LOG=info and a log directory, so a line per event on
# stderr and in the JSON file, and the audit trail beside them. The benchmark's own `--log-dir -`
# and `--log warn` are dropped; every other argument is passed on. Measured beside the benchmark's
# configuration in one boot of the VM (docs/benchmarks.md, first finding):
#
#   cargo xtask bench --only-live --baseline-gateway xtask/bench/service-logging.sh
#
# The VM holds the gateway at its host path, under the default target directory.
case "${1:-}" in -h|--help) sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"; exit 0 ;; esac
gateway="$(cd "$(dirname "$0")/../.." && pwd)/target/x86_64-unknown-linux-musl/release/mc-gateway"
skip=
for a do
  shift
  if [ -n "$skip" ]; then skip=; continue; fi
  case "$a" in
    --log-dir|--log) skip=1; continue ;;
  esac
  set -- "$@" "$a"
done
mkdir -p /tmp/ihex-service-log
exec "$gateway" "$@" --log info --log-dir /tmp/ihex-service-log
