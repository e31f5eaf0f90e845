#!/usr/bin/env bash
[ -n "${BASH_VERSION:-}" ] || exec bash "$0" "$@"   # also when started as `sh script`
# Cross-compile the iHEX host binaries for the Raspberry Pi (64-bit Raspberry Pi OS): mc-gateway,
# sim-node and ihex-provision, the gateway as deployed: without the demo (--no-default-features),
# with the island view (feature mc-gateway/web; --no-web leaves it out) and the SiLA 2 server
# (feature mc-gateway/sila; --no-sila leaves it out).
#
#   deploy/build-pi.sh                        # glibc (>= 2.29) and static musl builds
#   deploy/build-pi.sh --musl                 # only the static musl build
#   deploy/build-pi.sh --gnu -p mc-gateway    # one package, glibc only
#   deploy/build-pi.sh --musl --profile arm64-check   # what deploy/check-arm64.sh runs
#   deploy/build-pi.sh --features mc-gateway/demo   # with the demo (embedded broker, simulated island)
#   deploy/build-pi.sh --no-web               # a gateway without the island view (no axum)
#   deploy/build-pi.sh --no-sila              # a gateway without the SiLA 2 server (no tonic)
#
# musl is linked by rust-lld (shipped with rustup), its C code (ring, for the SiLA server's TLS)
# compiled by zig; glibc by cargo-zigbuild,
# which pins the glibc version (IHEX_PI_GLIBC, default 2.29; bullseye has 2.31, bookworm 2.36).
# Installs what is missing: the rustup targets, for --gnu cargo-zigbuild (cargo install --locked),
# and zig (pip install ziglang) for --gnu and the SiLA build's musl C code. Binaries land in
# target/<triple>/<profile>/ (release: release/) and are listed at the end. All packages build in
# one cargo run; if that fails, each is retried alone so one that does not build does not hide the
# others. The exit code is non-zero if any failed.
set -euo pipefail

cd "$(dirname "$0")/.."
GLIBC="${IHEX_PI_GLIBC:-2.29}"
GNU=1 MUSL=1
PROFILE=release
PACKAGES=()
FEATURES=()
WEB=1
SILA=1
while [ $# -gt 0 ]; do
    case "$1" in
        --gnu) MUSL=0 ;;
        --musl) GNU=0 ;;
        -p|--package) PACKAGES+=("$2"); shift ;;
        --profile) PROFILE="$2"; shift ;;
        --features) FEATURES+=(--features "$2"); shift ;;
        --no-web) WEB=0 ;;
        --no-sila) SILA=0 ;;
        -h|--help) sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"; exit 0 ;;
        *) echo "build-pi.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
[ ${#PACKAGES[@]} -gt 0 ] || PACKAGES=(mc-gateway sim-node ihex-provision)
# The gateway's own features (the island view, the SiLA server), named only when it is built.
GW_FEATURES=()
[ $WEB = 1 ] && GW_FEATURES+=(mc-gateway/web)
[ $SILA = 1 ] && GW_FEATURES+=(mc-gateway/sila)
GW_ARGS=()
[ ${#GW_FEATURES[@]} -gt 0 ] && GW_ARGS=(--features "$(IFS=,; echo "${GW_FEATURES[*]}")")
CARGO="${CARGO:-cargo}"
OUT_DIR="$PROFILE"
[ "$PROFILE" = dev ] && OUT_DIR=debug

say() { echo "build-pi: $*" >&2; }

# --- tools -------------------------------------------------------------------------------------
targets=()
[ $GNU = 1 ] && targets+=(aarch64-unknown-linux-gnu)
[ $MUSL = 1 ] && targets+=(aarch64-unknown-linux-musl)
installed="$(rustup target list --installed 2>/dev/null || true)"
for t in "${targets[@]}"; do
    grep -qx "$t" <<<"$installed" || { say "adding rustup target $t"; rustup target add "$t"; }
done
# The SiLA server's TLS (ring) has C and assembly: the musl build needs an aarch64 C compiler too,
# which zig provides (as it does for the glibc build).
MUSL_CC=0
[ $MUSL = 1 ] && [ $SILA = 1 ] && [ -z "${CC_aarch64_unknown_linux_musl:-}" ] && MUSL_CC=1
if [ $GNU = 1 ]; then
    if ! "$CARGO" zigbuild --help >/dev/null 2>&1; then
        say "installing cargo-zigbuild (cargo install cargo-zigbuild --locked; a few minutes)"
        "$CARGO" install cargo-zigbuild --locked
    fi
fi
if [ $GNU = 1 ] || [ $MUSL_CC = 1 ]; then
    if ! command -v zig >/dev/null 2>&1 && ! python3 -m ziglang version >/dev/null 2>&1; then
        say "installing zig (pip install ziglang)"
        python3 -m pip install --quiet ziglang || python3 -m pip install --quiet --break-system-packages ziglang
    fi
fi
if [ $MUSL_CC = 1 ]; then
    if command -v zig >/dev/null 2>&1; then ZIG="$(command -v zig)"; else ZIG="$(command -v python3) -m ziglang"; fi
    wrap="$PWD/target/zig-cc"
    mkdir -p "$wrap"
    # cc-rs passes its own --target= (a Rust triple), which zig does not parse: dropped here. zig
    # turns on UBSan at -O0 (the dev profile), whose runtime rust-lld does not link: off.
    {
        echo '#!/bin/sh'
        echo 'for a in "$@"; do shift; case "$a" in --target=*) ;; *) set -- "$@" "$a" ;; esac; done'
        echo "exec $ZIG cc -target aarch64-linux-musl -fno-sanitize=all \"\$@\""
    } >"$wrap/aarch64-linux-musl-cc"
    {
        echo '#!/bin/sh'
        echo "exec $ZIG ar \"\$@\""
    } >"$wrap/aarch64-linux-musl-ar"
    chmod +x "$wrap/aarch64-linux-musl-cc" "$wrap/aarch64-linux-musl-ar"
    export CC_aarch64_unknown_linux_musl="$wrap/aarch64-linux-musl-cc"
    export AR_aarch64_unknown_linux_musl="$wrap/aarch64-linux-musl-ar"
fi
# rust-lld links the static musl binaries with the musl CRT objects rustup ships (self-contained).
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_MUSL_LINKER="${CARGO_TARGET_AARCH64_UNKNOWN_LINUX_MUSL_LINKER:-rust-lld}"

# --- build -------------------------------------------------------------------------------------
failed=()
built=()
for t in "${targets[@]}"; do
    if [ "$t" = aarch64-unknown-linux-gnu ]; then
        # cargo-zigbuild reads the glibc version from a suffix of the gnu target; the output
        # directory is still target/aarch64-unknown-linux-gnu.
        build=("$CARGO" zigbuild --target "$t.$GLIBC")
    else
        build=("$CARGO" build --target "$t")
    fi
    build+=(--profile "$PROFILE" --no-default-features "${FEATURES[@]}" --bins)
    # One cargo invocation for all packages (shared dependencies are built once, with the same
    # features); only if that fails, one by one, so what does build is still produced and named.
    pkg_args=()
    for p in "${PACKAGES[@]}"; do
        pkg_args+=(-p "$p")
        [ "$p" = mc-gateway ] && pkg_args+=("${GW_ARGS[@]}")
    done
    say "building ${PACKAGES[*]} for $t ($PROFILE)"
    if "${build[@]}" "${pkg_args[@]}"; then
        built+=("$t:all")
        continue
    fi
    for p in "${PACKAGES[@]}"; do
        say "building $p alone for $t"
        gw=()
        [ "$p" = mc-gateway ] && gw=("${GW_ARGS[@]}")
        if "${build[@]}" -p "$p" "${gw[@]}"; then
            built+=("$t:$p")
        else
            failed+=("$p ($t)")
        fi
    done
done

echo
for entry in "${built[@]}"; do
    t="${entry%%:*}"
    for f in target/"$t"/"$OUT_DIR"/*; do
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
