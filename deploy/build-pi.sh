#!/usr/bin/env bash
[ -n "${BASH_VERSION:-}" ] || exec bash "$0" "$@"   # also when started as `sh script`
# Cross-compile the iHEX host binaries for the Raspberry Pi (64-bit Raspberry Pi OS) with cargo-zigbuild.
#
#   deploy/build-pi.sh                 # gnu (glibc >= 2.29) and static musl builds of every binary
#   deploy/build-pi.sh --musl          # only the static musl build (what deploy/check-arm64.sh runs)
#   deploy/build-pi.sh --gnu -p mc-gateway
#
# Installs what is missing: the two rustup targets, cargo-zigbuild (cargo install --locked) and zig
# (pip install ziglang). Binaries land in target/<triple>/release/ and are listed at the end.
# All packages build in one cargo run; if that fails, each is retried alone so one that does not build
# does not hide the others. The exit code is non-zero if any failed.
set -euo pipefail

cd "$(dirname "$0")/.."
GLIBC="${IHEX_PI_GLIBC:-2.29}"          # bullseye has 2.31, bookworm 2.36
GNU=1 MUSL=1
PACKAGES=()
while [ $# -gt 0 ]; do
    case "$1" in
        --gnu) MUSL=0 ;;
        --musl) GNU=0 ;;
        -p|--package) PACKAGES+=("$2"); shift ;;
        -h|--help) sed -n '3,13p' "$0"; exit 0 ;;
        *) echo "build-pi.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
[ ${#PACKAGES[@]} -gt 0 ] || PACKAGES=(mc-gateway sim-node ihex-provision)
CARGO="${CARGO:-cargo}"

say() { echo "build-pi: $*" >&2; }

# --- tools -------------------------------------------------------------------------------------
targets=()
[ $GNU = 1 ] && targets+=(aarch64-unknown-linux-gnu)
[ $MUSL = 1 ] && targets+=(aarch64-unknown-linux-musl)
installed="$(rustup target list --installed 2>/dev/null || true)"
for t in "${targets[@]}"; do
    grep -qx "$t" <<<"$installed" || { say "adding rustup target $t"; rustup target add "$t"; }
done
if ! "$CARGO" zigbuild --help >/dev/null 2>&1; then
    say "installing cargo-zigbuild (cargo install cargo-zigbuild --locked; a few minutes)"
    "$CARGO" install cargo-zigbuild --locked
fi
if ! command -v zig >/dev/null 2>&1 && ! python3 -m ziglang version >/dev/null 2>&1; then
    say "installing zig (pip install ziglang)"
    python3 -m pip install --quiet ziglang || python3 -m pip install --quiet --break-system-packages ziglang
fi

# --- build -------------------------------------------------------------------------------------
failed=()
built=()
for t in "${targets[@]}"; do
    # cargo-zigbuild reads the glibc version from a suffix of the gnu target; the output directory
    # is still target/aarch64-unknown-linux-gnu.
    zt="$t"
    [ "$t" = aarch64-unknown-linux-gnu ] && zt="$t.$GLIBC"
    # One cargo invocation for all packages (shared dependencies are built once, with the same
    # features); only if that fails, one by one, so what does build is still produced and named.
    pkg_args=()
    for p in "${PACKAGES[@]}"; do pkg_args+=(-p "$p"); done
    say "building ${PACKAGES[*]} for $zt"
    if "$CARGO" zigbuild --release --target "$zt" "${pkg_args[@]}" --bins; then
        built+=("$t:all")
        continue
    fi
    for p in "${PACKAGES[@]}"; do
        say "building $p alone for $zt"
        if "$CARGO" zigbuild --release --target "$zt" -p "$p" --bins; then
            built+=("$t:$p")
        else
            failed+=("$p ($t)")
        fi
    done
done

echo
for entry in "${built[@]}"; do
    t="${entry%%:*}"
    for f in target/"$t"/release/*; do
        # Executables produced by this build, not build scripts or deps.
        if [ -f "$f" ] && [ -x "$f" ]; then
            case "$(basename "$f")" in *.d|*.so) ;; *) echo "  $f" ;; esac
        fi
    done
done | sort -u
if [ ${#failed[@]} -gt 0 ]; then
    say "FAILED: ${failed[*]}"
    exit 1
fi
say "done"
