#!/usr/bin/env bash
[ -n "${BASH_VERSION:-}" ] || exec bash "$0" "$@"   # also when started as `sh script`
# Prove the Pi binaries work on a real arm64 Linux kernel: boot Debian's arm64 kernel under
# qemu-system-aarch64 (-M virt -cpu cortex-a72, TCG) with the CAN modules loaded and vcan0 up, then run
# the static aarch64-musl binaries there, against a Mosquitto broker on the host (started here on a free
# loopback port; the guest reaches it as 10.0.2.2 through QEMU user networking):
#   1. ihex-provision wait-event, subscribed before anything else starts, waiting for the first
#      node_online event of the island "arm64";
#   2. sim-node with the island deploy/arm64-island.toml on vcan0;
#   3. the gateway under test on vcan0, built as for the Pi (without the demo), with the Pi's
#      deploy/etc/gateway.toml and --can vcan0 --island arm64;
#   4. an LED command to the island's first element whose command_result must be "ok"
#      (MQTT -> CAN frame -> virtual SC -> ack frame -> MQTT); the island view (gateway.toml's
#      http = 0.0.0.0:8080) lists that element in GET /api/island; then `ihex-provision can` gives the
#      island's factory-fresh board its ID by UID (a taken ID refused first) and its node_online follows.
# Exit code 0 only if all of it happened; the VM is killed after a bounded time (IHEX_ARM64_TIMEOUT s).
#
#   deploy/check-arm64.sh                          # builds with deploy/build-pi.sh --musl, then boots
#   IHEX_ARM64_NO_BUILD=1 deploy/check-arm64.sh    # use the binaries already in target/
#   IHEX_ARM64_PROFILE=release deploy/check-arm64.sh   # the shipped profile instead of arm64-check
#   IHEX_ARM64_GNU=1 deploy/check-arm64.sh         # also build the glibc (Raspberry Pi OS) binaries and
#                                                  # run sim-node from that build, on Debian's arm64 glibc
# With IHEX_ARM64_GNU unset, glibc binaries already in target/aarch64-unknown-linux-gnu are used when
# present; IHEX_ARM64_GNU=0 never uses them. IHEX_ARM64_BROKER=HOST:PORT uses a broker already running
# on the host's loopback instead of starting one.
#
# Needs (installed when missing, Debian/Ubuntu): qemu-system-arm, cpio, xz-utils, mosquitto; the arm64
# kernel and busybox-static come from Debian's arm64 archive via `apt-get download` (after
# `dpkg --add-architecture arm64 && apt-get update`) and are cached in target/arm64-vm/.
set -euo pipefail
case "${1:-}" in -h|--help) sed -n '/^# /,/^[^#]/{/^[^#]/q;s/^# \{0,1\}//p}' "$0"; exit 0 ;; esac

cd "$(dirname "$0")/.."
ROOT="$PWD"
TIMEOUT="${IHEX_ARM64_TIMEOUT:-240}"
WORK="$ROOT/target/arm64-vm"
PROFILE="${IHEX_ARM64_PROFILE:-arm64-check}"
OUT_DIR="$PROFILE"
[ "$PROFILE" = dev ] && OUT_DIR=debug
BIN="$ROOT/target/aarch64-unknown-linux-musl/$OUT_DIR"
ISLAND="${IHEX_ARM64_ISLAND:-$ROOT/deploy/arm64-island.toml}"
mkdir -p "$WORK"

say() { echo "check-arm64: $*" >&2; }
die() { say "FAIL: $*"; exit 1; }

# --- host tools ----------------------------------------------------------------------------------
need_apt=()
command -v qemu-system-aarch64 >/dev/null || need_apt+=(qemu-system-arm)
command -v cpio >/dev/null || need_apt+=(cpio)
command -v xz >/dev/null || need_apt+=(xz-utils)
[ -n "${IHEX_ARM64_BROKER:-}" ] || command -v mosquitto >/dev/null || [ -x /usr/sbin/mosquitto ] \
    || need_apt+=(mosquitto)
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
GNU_BIN="$ROOT/target/aarch64-unknown-linux-gnu/$OUT_DIR"
if [ "${IHEX_ARM64_NO_BUILD:-0}" != 1 ]; then
    deploy/build-pi.sh --musl --profile "$PROFILE" || say "some packages did not build (see above); using what exists"
    if [ "$GNU_MODE" = 1 ]; then
        deploy/build-pi.sh --gnu --profile "$PROFILE" || die "glibc build failed"
    fi
fi
USE_GNU=0
if [ "$GNU_MODE" = 1 ] || { [ "$GNU_MODE" = auto ] && [ -x "$GNU_BIN/sim-node" ]; }; then
    for b in mc-gateway sim-node ihex-provision; do
        [ -x "$GNU_BIN/$b" ] || die "$GNU_BIN/$b missing (deploy/build-pi.sh --gnu --profile $PROFILE)"
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
    [ -x "$BIN/$b" ] || die "$BIN/$b missing (deploy/build-pi.sh --musl --profile $PROFILE)"
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

# --- broker on the host ------------------------------------------------------------------------
# The guest reaches the host's loopback as 10.0.2.2 (QEMU user networking), like the x86_64 test VM.
if [ -n "${IHEX_ARM64_BROKER:-}" ]; then
    BROKER_PORT="${IHEX_ARM64_BROKER##*:}"
else
    MOSQUITTO="$(command -v mosquitto || echo /usr/sbin/mosquitto)"
    mkdir -p "$WORK/broker"
    BROKER_PID=
    for _ in 1 2 3 4 5 6 7 8 9 10; do
        BROKER_PORT=$((20000 + RANDOM % 40000))
        printf 'listener %s 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\nlog_dest stderr\nlog_type error\nlog_type warning\n' \
            "$BROKER_PORT" > "$WORK/broker/mosquitto.conf"
        "$MOSQUITTO" -c "$WORK/broker/mosquitto.conf" 2> "$WORK/broker/mosquitto.log" &
        BROKER_PID=$!
        for _ in $(seq 100); do
            (exec 3<>"/dev/tcp/127.0.0.1/$BROKER_PORT") 2>/dev/null && break 2
            kill -0 "$BROKER_PID" 2>/dev/null || break
            sleep 0.1
        done
        kill "$BROKER_PID" 2>/dev/null || true
        wait "$BROKER_PID" 2>/dev/null || true
        BROKER_PID=
    done
    [ -n "$BROKER_PID" ] || die "mosquitto did not start on a free port (see $WORK/broker/mosquitto.log)"
    trap 'kill "$BROKER_PID" 2>/dev/null || true' EXIT
    say "host mosquitto on 127.0.0.1:$BROKER_PORT (10.0.2.2:$BROKER_PORT in the guest)"
fi

# --- initramfs ---------------------------------------------------------------------------------
IR="$WORK/initramfs"
rm -rf "$IR"
mkdir -p "$IR"/{bin,sbin,proc,sys,dev,tmp,run,etc,lib/modules,ihex}
cp "$WORK/rootfs/bin/busybox" "$IR/bin/busybox"
# Loaded in this order (dependencies first): the CAN stack, then virtio-net on the virt machine's
# virtio-mmio transport for user networking (the host's broker).
for m in net/can/can.ko net/can/can-raw.ko drivers/net/can/dev/can-dev.ko drivers/net/can/vcan.ko \
    net/core/failover.ko drivers/net/net_failover.ko drivers/virtio/virtio_mmio.ko drivers/net/virtio_net.ko; do
    src="$MODDIR/$m"
    if [ -f "$src" ]; then cp "$src" "$IR/lib/modules/"
    elif [ -f "$src.xz" ]; then xz -dc "$src.xz" > "$IR/lib/modules/$(basename "$m")"
    else die "kernel module $m not in $KVER"; fi
    basename "$m" .ko >> "$IR/lib/modules/order"
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
while read -r m; do insmod /lib/modules/$m.ko || echo "ihex-vm: insmod $m failed"; done < /lib/modules/order
ip link set lo up
ip link add dev vcan0 type vcan && ip link set up vcan0
ip link show vcan0
cd /ihex
# The host's broker through QEMU user networking.
ip link set eth0 up && ip addr add 10.0.2.15/24 dev eth0 && ip route add default via 10.0.2.2
B=10.0.2.2:@PORT@
# 1. the client subscribes first, so no event is missed
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
    # 4. the other direction: a command over MQTT -> frame on vcan0 -> the node acks -> command_result ok
    ./ihex-provision wait-event --broker $B --island arm64 --event command_result \
        --match request_id=arm64-led --match result=ok --timeout-secs 60 \
        --send '{"cmd":"led","node":"@NODE@","color":"green","request_id":"arm64-led"}' \
        > /tmp/result.json 2> /tmp/wait.err; rc=$?
    [ $rc = 0 ] && echo "ihex-vm: event: $(cat /tmp/result.json)"
fi
# 5. the island view of the Pi's gateway.toml (http = 0.0.0.0:8080): its snapshot lists the node
if [ $rc = 0 ]; then
    # busybox's nc, not its wget: the static wget crashes in this initramfs (no NSS files). Its
    # input stays open a while: nc may give up on the connection as soon as its input ends; the
    # answer (HTTP/1.0) ends with the connection.
    { printf 'GET /api/island HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n'; sleep 5; } \
        | nc 127.0.0.1 8080 > /tmp/island.json
    if grep -q '"id":"@NODE@"' /tmp/island.json; then
        echo "ihex-vm: island view: $(head -n 1 /tmp/island.json | tr -d '\r'), $(grep -o '"id":"@NODE@"[^}]\{0,100\}' /tmp/island.json | head -n 1)"
    else
        echo "ihex-vm: FAIL: GET /api/island did not list @NODE@: $(head -c 400 /tmp/island.json 2>/dev/null)"; rc=1
    fi
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
    for f in /tmp/wait.err /tmp/gw.out /tmp/sim.out; do
        echo "---- $f"; tail -n 25 $f
    done
fi
echo "ihex-vm: vcan0 frames: rx $(cat /sys/class/net/vcan0/statistics/rx_packets) tx $(cat /sys/class/net/vcan0/statistics/tx_packets)"
echo "IHEX-ARM64-RESULT rc=$rc"
poweroff -f
INIT
sed -i "s/@NODE@/$NODE/g; s/@NEWID@/${NEWID:-}/g; s/@UID@/${UID_HEX:-}/g; s/@PORT@/$BROKER_PORT/g" "$IR/init"
chmod +x "$IR/init"
(cd "$IR" && find . | cpio -o -H newc --quiet | gzip -1) > "$WORK/initrd.gz"

# --- boot --------------------------------------------------------------------------------------
say "booting $KVER under qemu-system-aarch64 (TCG, cortex-a72), at most ${TIMEOUT}s"
LOG="$WORK/console.log"
set +e
timeout --signal=KILL "$TIMEOUT" qemu-system-aarch64 -M virt -cpu cortex-a72 -smp 2 -m 1024 \
    -accel tcg -nographic -no-reboot -netdev user,id=n0 -device virtio-net-device,netdev=n0 \
    -kernel "$KERNEL" -initrd "$WORK/initrd.gz" \
    -append "console=ttyAMA0 quiet panic=-1 rdinit=/init" </dev/null 2>&1 | tee "$LOG" >&2
qrc=${PIPESTATUS[0]}
set -e
[ "$qrc" = 137 ] && die "VM did not finish within ${TIMEOUT}s (console: $LOG)"
grep -q "IHEX-ARM64-RESULT rc=0" "$LOG" || die "no event from the aarch64 gateway (console: $LOG)"
how="static musl binaries"
[ "$USE_GNU" = 1 ] && how="musl gateway, glibc sim-node ($(grep -o 'GLIBC [0-9.]*' "$LOG" | head -1))"
what="node_online from vcan0, LED command acknowledged, island view served"
[ -n "${UID_HEX:-}" ] && what="$what, node $NEWID assigned by UID over CAN"
say "OK ($how): on a real arm64 kernel the aarch64 gateway did it all: $what"
