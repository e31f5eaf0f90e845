#!/usr/bin/env bash
[ -n "${BASH_VERSION:-}" ] || exec bash "$0" "$@"   # also when started as `sh script`
# Prove the Pi binaries work on a real arm64 Linux kernel: boot Debian's arm64 kernel under
# qemu-system-aarch64 (-M virt -cpu cortex-a72, TCG) with the CAN modules loaded and vcan0 up, then run
# the static aarch64-musl binaries there:
#   1. an embedded MQTT broker on 127.0.0.1:1883 (mc-gateway's demo mode, the broker compiled into it);
#   2. sim-node with an island on vcan0;
#   3. the gateway under test on vcan0 (--can vcan0 --broker 127.0.0.1:1883, island prefix "arm64",
#      so the demo instance's own events cannot be mistaken for it);
#   4. ihex-provision wait-event, subscribed before 2 and 3 start, waiting for the first node_online
#      event of the arm64 island; then an LED command to the island's first node whose command_result must be "ok"
#      (MQTT -> CAN frame -> virtual SC -> ack frame -> MQTT); then `ihex-provision can` gives the
#      island's factory-fresh board its ID by UID (a taken ID refused first) and its node_online follows.
# Exit code 0 only if both arrived; the VM is killed after a bounded time (IHEX_ARM64_TIMEOUT s).
#
#   deploy/check-arm64.sh              # builds with deploy/build-pi.sh --musl, then boots
#   IHEX_ARM64_NO_BUILD=1 deploy/check-arm64.sh   # use the binaries already in target/
#   IHEX_ARM64_GNU=1 deploy/check-arm64.sh        # also build the glibc (Raspberry Pi OS) binaries and
#                                                 # run sim-node from that build, on Debian's arm64 glibc
# With IHEX_ARM64_GNU unset, glibc binaries already in target/aarch64-unknown-linux-gnu are used when
# present; IHEX_ARM64_GNU=0 never uses them.
#
# Needs (installed when missing, Debian/Ubuntu): qemu-system-arm, cpio, xz-utils; the arm64 kernel and
# busybox-static come from Debian's arm64 archive via `apt-get download` (after
# `dpkg --add-architecture arm64 && apt-get update`) and are cached in target/arm64-vm/.
set -euo pipefail

cd "$(dirname "$0")/.."
ROOT="$PWD"
TIMEOUT="${IHEX_ARM64_TIMEOUT:-240}"
WORK="$ROOT/target/arm64-vm"
BIN="$ROOT/target/aarch64-unknown-linux-musl/release"
ISLAND="${IHEX_ARM64_ISLAND:-$ROOT/deploy/arm64-island.toml}"
mkdir -p "$WORK"

say() { echo "check-arm64: $*" >&2; }
die() { say "FAIL: $*"; exit 1; }

# --- host tools ----------------------------------------------------------------------------------
need_apt=()
command -v qemu-system-aarch64 >/dev/null || need_apt+=(qemu-system-arm)
command -v cpio >/dev/null || need_apt+=(cpio)
command -v xz >/dev/null || need_apt+=(xz-utils)
if [ ${#need_apt[@]} -gt 0 ]; then
    command -v apt-get >/dev/null || die "missing ${need_apt[*]} (install them with your package manager)"
    say "installing ${need_apt[*]}"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need_apt[@]}" >/dev/null
fi

# --- arm64 kernel, CAN modules, busybox (cached) -------------------------------------------------
if [ ! -f "$WORK/rootfs/.complete" ]; then
    command -v dpkg >/dev/null || die "no dpkg: put an arm64 kernel + busybox in $WORK/rootfs by hand"
    if ! dpkg --print-foreign-architectures | grep -qx arm64 \
        || ! apt-cache show linux-image-arm64:arm64 >/dev/null 2>&1; then
        say "adding the arm64 architecture to apt"
        dpkg --add-architecture arm64
        apt-get update -qq
    fi
    kpkg="$(apt-cache depends linux-image-arm64:arm64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')"
    [ -n "$kpkg" ] || die "cannot find Debian's arm64 kernel package"
    rm -rf "$WORK/debs" "$WORK/rootfs"
    mkdir -p "$WORK/debs" "$WORK/rootfs"
    say "downloading ${kpkg%:arm64} and busybox-static (arm64)"
    # apt's sandbox user cannot write to every directory: download into a world-writable temp dir.
    dl="$(mktemp -d)"; chmod 777 "$dl"
    (cd "$dl" && apt-get download -qq "$kpkg" busybox-static:arm64)
    mv "$dl"/*.deb "$WORK/debs/"; rmdir "$dl"
    for d in "$WORK"/debs/*.deb; do dpkg-deb -x "$d" "$WORK/rootfs"; done
    touch "$WORK/rootfs/.complete"
fi
KERNEL="$(ls "$WORK"/rootfs/boot/vmlinuz-*-arm64 | head -1)"
KVER="$(basename "$KERNEL" | sed 's/^vmlinuz-//')"
MODDIR="$WORK/rootfs/lib/modules/$KVER/kernel"

# --- binaries ----------------------------------------------------------------------------------
GNU_MODE="${IHEX_ARM64_GNU:-auto}"
GNU_BIN="$ROOT/target/aarch64-unknown-linux-gnu/release"
if [ "${IHEX_ARM64_NO_BUILD:-0}" != 1 ]; then
    deploy/build-pi.sh --musl || say "some packages did not build (see above); using what exists"
    if [ "$GNU_MODE" = 1 ]; then
        deploy/build-pi.sh --gnu -p sim-node -p mc-gateway -p ihex-provision || die "glibc build failed"
    fi
fi
USE_GNU=0
if [ "$GNU_MODE" = 1 ] || { [ "$GNU_MODE" = auto ] && [ -x "$GNU_BIN/sim-node" ]; }; then
    for b in mc-gateway sim-node ihex-provision; do
        [ -x "$GNU_BIN/$b" ] || die "$GNU_BIN/$b missing (deploy/build-pi.sh --gnu)"
    done
    USE_GNU=1
    if [ ! -f "$WORK/rootfs/.complete-glibc" ]; then
        say "downloading Debian's arm64 glibc (libc6, libgcc-s1) for the glibc binaries"
        dl="$(mktemp -d)"; chmod 777 "$dl"
        (cd "$dl" && apt-get download -qq libc6:arm64 libgcc-s1:arm64)
        for d in "$dl"/*.deb; do dpkg-deb -x "$d" "$WORK/rootfs"; done
        rm -rf "$dl"
        touch "$WORK/rootfs/.complete-glibc"
    fi
fi
for b in mc-gateway sim-node ihex-provision; do
    [ -x "$BIN/$b" ] || die "$BIN/$b missing (deploy/build-pi.sh --musl)"
    # ELF e_machine (offset 18) 0xb7 = AArch64.
    [ "$(od -An -tx1 -j18 -N1 "$BIN/$b" | tr -d ' ')" = b7 ] || die "$BIN/$b is not an aarch64 binary"
done
[ -f "$ISLAND" ] || die "island file $ISLAND missing"
# The node the LED command goes to: the island's first element (`id = "111"`).
NODE="$(sed -n 's/^id *= *"\([0-9a-fA-F]*\)".*/\1/p' "$ISLAND" | head -1)"
[ -n "$NODE" ] || die "no element id found in $ISLAND"
# A factory-fresh element (`unconfigured = true` with a `uid`), if any: it is given its `id` over CAN.
read -r NEWID UID_HEX <<<"$(awk -F'"' '
    /^\[\[/ { if (un && uid != "") { print id, uid; found = 1; exit } id = ""; uid = ""; un = 0 }
    /^id *=/ { id = $2 } /^uid *=/ { uid = $2 } /^unconfigured *= *true/ { un = 1 }
    END { if (!found && un && uid != "") print id, uid }' "$ISLAND")" || true

# --- initramfs ---------------------------------------------------------------------------------
IR="$WORK/initramfs"
rm -rf "$IR"
mkdir -p "$IR"/{bin,sbin,proc,sys,dev,tmp,run,etc,lib/modules,ihex}
cp "$WORK/rootfs/bin/busybox" "$IR/bin/busybox"
for m in net/can/can.ko net/can/can-raw.ko drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko; do
    src="$MODDIR/$m"
    if [ -f "$src" ]; then cp "$src" "$IR/lib/modules/"
    elif [ -f "$src.xz" ]; then xz -dc "$src.xz" > "$IR/lib/modules/$(basename "$m")"
    else die "kernel module $m not in $KVER"; fi
done
cp "$BIN/mc-gateway" "$BIN/sim-node" "$BIN/ihex-provision" "$IR/ihex/"
if [ "$USE_GNU" = 1 ]; then
    mkdir -p "$IR/ihex/gnu" "$IR/lib/aarch64-linux-gnu"
    cp "$GNU_BIN/mc-gateway" "$GNU_BIN/sim-node" "$GNU_BIN/ihex-provision" "$IR/ihex/gnu/"
    cp -a "$WORK"/rootfs/lib/aarch64-linux-gnu/. "$IR/lib/aarch64-linux-gnu/"
    ln -sf aarch64-linux-gnu/ld-linux-aarch64.so.1 "$IR/lib/ld-linux-aarch64.so.1"
fi
cp "$ISLAND" "$IR/ihex/island.toml"
# The Pi's configuration file, so the check also proves the shipped file parses; flags override it.
cp deploy/etc/gateway.toml "$IR/ihex/gateway.toml"
cat > "$IR/init" <<'INIT'
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin:/sbin
mount -t proc proc /proc; mount -t sysfs sys /sys; mount -t devtmpfs dev /dev; mount -t tmpfs tmp /tmp
echo "ihex-vm: kernel $(uname -r) on $(uname -m)"
for m in can can-raw can-dev vcan; do insmod /lib/modules/$m.ko || echo "ihex-vm: insmod $m failed"; done
ip link set lo up
ip link add dev vcan0 type vcan && ip link set up vcan0
ip link show vcan0
cd /ihex
B=127.0.0.1:1883
# 1. the broker: mc-gateway's demo mode (embedded broker + in-memory island, nothing on vcan0)
./mc-gateway --broker-listen $B --log-dir /tmp/demo-log > /tmp/demo.out 2>&1 &
# 4. the client subscribes first, so no event is missed
./ihex-provision wait-event --broker $B --island arm64 --event node_online \
    --retry-connect --ready-file /tmp/ready --timeout-secs 150 > /tmp/event.json 2> /tmp/wait.err &
WAIT=$!
i=0; while [ ! -f /tmp/ready ] && [ $i -lt 600 ]; do sleep 0.2; i=$((i+1)); done
[ -f /tmp/ready ] && echo "ihex-vm: client subscribed" || echo "ihex-vm: client never subscribed"
# 2. + 3. the island on vcan0 and the gateway under test; the island from the glibc build when there is one
SIM=./sim-node
if [ -d gnu ]; then
    export LD_LIBRARY_PATH=/lib/aarch64-linux-gnu
    echo "ihex-vm: glibc $(/lib/ld-linux-aarch64.so.1 --version | head -n 1)"
    for b in mc-gateway sim-node ihex-provision; do
        echo "ihex-vm: glibc build: $(./gnu/$b --version 2>&1 | head -n 1)"
    done
    SIM=./gnu/sim-node
fi
echo "ihex-vm: island: $SIM"
$SIM --iface vcan0 --island island.toml > /tmp/sim.out 2>&1 &
./mc-gateway --config gateway.toml --can vcan0 --broker $B --island arm64 --log-dir /tmp/gw-log > /tmp/gw.out 2>&1 &
wait $WAIT; rc=$?
if [ $rc = 0 ]; then
    echo "ihex-vm: event: $(cat /tmp/event.json)"
    # 5. the other direction: a command over MQTT -> frame on vcan0 -> the node acks -> command_result ok
    ./ihex-provision wait-event --broker $B --island arm64 --event command_result \
        --match request_id=arm64-led --match result=ok --timeout-secs 60 \
        --send '{"cmd":"led","node":"@NODE@","color":"green","request_id":"arm64-led"}' \
        > /tmp/result.json 2> /tmp/wait.err; rc=$?
    [ $rc = 0 ] && echo "ihex-vm: event: $(cat /tmp/result.json)"
fi
# 6. CAN ID assignment by UID through the gateway (only if the island has a factory-fresh board)
if [ $rc = 0 ] && [ -n "@UID@" ]; then
    ./ihex-provision wait-event --broker $B --island arm64 --event node_online --match id=@NEWID@ \
        --ready-file /tmp/ready2 --timeout-secs 60 > /tmp/online2.json 2> /tmp/wait.err &
    WAIT=$!
    i=0; while [ ! -f /tmp/ready2 ] && [ $i -lt 300 ]; do sleep 0.2; i=$((i+1)); done
    if ./ihex-provision can --broker $B --island arm64 --uid @UID@ --id @NODE@ > /tmp/dup.out 2>&1; then
        echo "ihex-vm: FAIL: assigning the taken ID @NODE@ was not refused"; rc=1
    else
        echo "ihex-vm: duplicate refused: $(tail -n 1 /tmp/dup.out)"
    fi
    if [ $rc = 0 ]; then
        ./ihex-provision can --broker $B --island arm64 --uid @UID@ --id @NEWID@ --timeout-secs 30 \
            > /tmp/assign.out 2>&1; rc=$?
        echo "ihex-vm: assign: $(tail -n 1 /tmp/assign.out)"
    fi
    if [ $rc = 0 ]; then
        wait $WAIT; rc=$?
        [ $rc = 0 ] && echo "ihex-vm: event: $(cat /tmp/online2.json)"
    else
        kill $WAIT 2>/dev/null
    fi
fi
if [ $rc != 0 ]; then
    for f in /tmp/wait.err /tmp/gw.out /tmp/sim.out /tmp/demo.out; do
        echo "---- $f"; tail -n 25 $f
    done
fi
echo "ihex-vm: vcan0 frames: rx $(cat /sys/class/net/vcan0/statistics/rx_packets) tx $(cat /sys/class/net/vcan0/statistics/tx_packets)"
echo "IHEX-ARM64-RESULT rc=$rc"
poweroff -f
INIT
sed -i "s/@NODE@/$NODE/g; s/@NEWID@/${NEWID:-}/g; s/@UID@/${UID_HEX:-}/g" "$IR/init"
chmod +x "$IR/init"
(cd "$IR" && find . | cpio -o -H newc --quiet | gzip -1) > "$WORK/initrd.gz"

# --- boot --------------------------------------------------------------------------------------
say "booting $KVER under qemu-system-aarch64 (TCG, cortex-a72), at most ${TIMEOUT}s"
LOG="$WORK/console.log"
set +e
timeout --signal=KILL "$TIMEOUT" qemu-system-aarch64 -M virt -cpu cortex-a72 -smp 2 -m 1024 \
    -accel tcg -nographic -no-reboot -nic none \
    -kernel "$KERNEL" -initrd "$WORK/initrd.gz" \
    -append "console=ttyAMA0 quiet panic=-1 rdinit=/init" </dev/null 2>&1 | tee "$LOG" >&2
qrc=${PIPESTATUS[0]}
set -e
[ "$qrc" = 137 ] && die "VM did not finish within ${TIMEOUT}s (console: $LOG)"
grep -q "IHEX-ARM64-RESULT rc=0" "$LOG" || die "no event from the aarch64 gateway (console: $LOG)"
how="static musl binaries"
[ "$USE_GNU" = 1 ] && how="musl gateway, glibc sim-node ($(grep -o 'GLIBC [0-9.]*' "$LOG" | head -1))"
what="node_online from vcan0, LED command acknowledged"
[ -n "${UID_HEX:-}" ] && what="$what, node $NEWID assigned by UID over CAN"
say "OK ($how): on a real arm64 kernel the aarch64 gateway did it all: $what"
