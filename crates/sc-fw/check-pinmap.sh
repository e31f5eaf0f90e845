#!/usr/bin/env bash
# Proves that the firmware build rejects a pin map that disagrees with the chip or with sc-fw:
# builds once with hw/pinmap.toml (must succeed), then with mutated copies (each must fail with the
# expected message). Only the build script reruns for the broken copies, so this is quick once the
# firmware has been built. Usage: crates/sc-fw/check-pinmap.sh
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"; exit 0 ;; esac
cd "$(dirname "$0")"
CARGO=${CARGO:-cargo}
map=../../hw/pinmap.toml
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
fail=0

"$CARGO" build --release --quiet || { echo "FAIL: the real pin map does not build"; exit 1; }
echo "ok   hw/pinmap.toml builds"

# name | python expression turning the text `s` into the broken variant | expected message
cases=(
  "wrong AF|s.replace('pin = \"PB15\"\nperipheral = \"TIM15\"\nfunction = \"CH2\"\naf = 1', 'pin = \"PB15\"\nperipheral = \"TIM15\"\nfunction = \"CH2\"\naf = 2')|TIM15_CH2 on PB15 is AF1, not AF2"
  "pin without that function|s.replace('pin = \"PA6\"', 'pin = \"PB5\"', 1)|cannot be TIM3_CH1"
  "pin used twice|s.replace('pin = \"PB15\"', 'pin = \"PA3\"').replace('function = \"CH2\"\naf = 1', 'function = \"CH2\"\naf = 9')|is already used by"
  "missing signal|s.replace('name = \"relay\"', 'name = \"relay_old\"')|signal \`relay\` (GPIO) is missing"
  "EXTI line mismatch|s.replace('exti = 5', 'exti = 4')|EXTI line"
  "config page inside a partition|s.replace('config_page_addr = 0x0807_F800', 'config_page_addr = 0x0804_7000')|must be the layout's config page"
  "relay moved away from the bootloader's pin|s.replace('pin = \"PB5\"', 'pin = \"PB6\"')|but the bootloader keeps it on as PB5 active high"
  "wrong peripheral for a signal|s.replace('peripheral = \"TIM3\"\nfunction = \"CH1\"\naf = 2', 'peripheral = \"TIM16\"\nfunction = \"CH1\"\naf = 1')|but sc-fw drives it as TIM3 CH1"
)
for c in "${cases[@]}"; do
  IFS='|' read -r name expr want <<<"$c"
  python3 - "$map" "$tmp/map.toml" "$expr" <<'PY'
import sys
s = open(sys.argv[1]).read()
t = eval(sys.argv[3])
assert t != s, "mutation did not apply"
open(sys.argv[2], "w").write(t)
PY
  if out=$(IHEX_PINMAP="$tmp/map.toml" "$CARGO" build --release --quiet 2>&1); then
    echo "FAIL $name: the build accepted a broken pin map"; fail=1
  elif grep -qF -- "$want" <<<"$out"; then
    echo "ok   $name: rejected ($(grep -F -- "$want" <<<"$out" | head -1 | sed 's/^ *//'))"
  else
    echo "FAIL $name: rejected, but without \"$want\":"; echo "$out" | grep -- '- ' | head -5; fail=1
  fi
done
# Leave the build script's output generated from the real map again.
"$CARGO" build --release --quiet
exit $fail
