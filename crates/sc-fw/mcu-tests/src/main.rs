//! The SC core's behaviour and the firmware's pure modules, executed on the Cortex-M4 instruction set
//! (QEMU mps2-an386, `thumbv7em-none-eabihf`, hard float, overflow checks on).
//!
//! The host tests prove the logic; this binary proves that the same code, compiled exactly as for the
//! firmware's target, behaves the same on the real instruction set (32-bit `usize`, Thumb-2 codegen,
//! u64 arithmetic on a 32-bit core). Each check prints `ok`/`FAIL` over semihosting; the exit status
//! is the verdict.
#![no_std]
#![no_main]

#[path = "../../src/bank.rs"]
mod bank;
#[path = "../../src/record.rs"]
mod record;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use ihex_proto::filter::{sc_filters, to_bxcan};
use ihex_proto::{
    AckResult, BootRole, DockPartner, DockState, FirmwareVersion, Kind, Message, NodeId, Packet,
    Port, ResetReason, StateParts, StateReport, Uid,
};
use ihex_proto::{FwAction, FwPhase, FwRefusal, FW_DATA_LEN};
use ihex_sc_core::{
    Config, FirmwareIdentity, FlashError, Millis, Node, Output, UpdateConfig, DEBOUNCE_MS,
    RESET_DELAY_MS,
};

struct Suite {
    passed: u32,
    failed: u32,
}

impl Suite {
    fn check(&mut self, name: &str, ok: bool) {
        if ok {
            self.passed += 1;
            hprintln!("ok   {}", name);
        } else {
            self.failed += 1;
            hprintln!("FAIL {}", name);
        }
    }
}

fn id(raw: u16) -> NodeId {
    NodeId::new_sc(raw).expect("valid SC id")
}

fn port(raw: u8) -> Port {
    Port::new(raw).expect("valid port")
}

fn config(node_id: Option<NodeId>, role: BootRole) -> Config {
    Config {
        role,
        ports: 6,
        uid: Uid([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]),
        node_id,
        reset: ResetReason::PowerOn,
        firmware: FirmwareIdentity {
            version: FirmwareVersion::new(1, 2, 3),
            image_hash: [7; 7],
            trial: false,
        },
        update: UpdateConfig {
            board: ihex_image::Board::NUCLEO_F303RE,
            key: ihex_image::test_key::PUBLIC,
            layout: &ihex_image::board::F303RE,
            reverted: false,
        },
    }
}

type Outs = heapless::Vec<Output, 32>;

fn drain(n: &mut Node) -> Outs {
    let mut v = Outs::new();
    while let Some(o) = n.poll_output() {
        let _ = v.push(o);
    }
    v
}

/// Delivers a packet as the CAN receive task would (encoded, then raw id + data).
fn deliver(n: &mut Node, p: Packet, t: u64) -> Outs {
    let (raw_id, data) = p.encode();
    n.handle_frame(raw_id, true, false, &data, Millis(t));
    drain(n)
}

fn has_frame(outs: &Outs, want: &Packet) -> bool {
    outs.iter()
        .any(|o| matches!(o, Output::Frame(p) if p == want))
}

/// Runs timers up to `t` as the node task does (tick whenever the core's deadline is due).
fn run_until(n: &mut Node, t: u64) -> Outs {
    let mut all = Outs::new();
    while let Some(at) = n.poll_at() {
        if at.0 > t {
            break;
        }
        n.tick(at);
        for o in drain(n) {
            let _ = all.push(o);
        }
    }
    n.tick(Millis(t));
    for o in drain(n) {
        let _ = all.push(o);
    }
    all
}

fn static_node(s: &mut Suite) {
    let own = id(0x111);
    let mut n = Node::new(config(Some(own), BootRole::Static), Millis(0));
    s.check("first actuators_changed after new", n.actuators_changed());
    s.check("relay off at boot", !n.actuators().relay);
    let boot = Packet::report(
        own,
        Message::BootUp {
            version: ihex_proto::PROTOCOL_VERSION,
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::PowerOn,
        },
    );
    let outs = drain(&mut n);
    s.check(
        "BootUp announced from the stored ID",
        has_frame(&outs, &boot),
    );

    let outs = deliver(
        &mut n,
        Packet::command(own, Message::HealthCheck { seq: 7 }),
        10,
    );
    let health = outs.iter().any(|o| {
        matches!(o, Output::Frame(Packet { src, dest, msg: Message::HealthReply(h) })
            if *src == own && *dest == NodeId::GATEWAY && h.seq == 7)
    });
    s.check("HealthCheck answered with HealthReply seq 7", health);

    let outs = deliver(
        &mut n,
        Packet::command(id(0x112), Message::HealthCheck { seq: 8 }),
        20,
    );
    s.check("a command for another node is ignored", outs.is_empty());

    // Docking on port 3: debounced detect, confirm -> relay on, debounced open -> relay off + removed.
    n.handle_loop_level(port(3), true, Millis(1_000));
    let early = drain(&mut n);
    s.check("no DockDetected before the debounce time", early.is_empty());
    let outs = run_until(&mut n, 1_000 + DEBOUNCE_MS);
    let detected = Packet::report(own, Message::DockDetected { port: port(3) });
    s.check(
        "DockDetected after DEBOUNCE_MS",
        has_frame(&outs, &detected),
    );
    s.check("relay still off after detection", !n.actuators().relay);

    let outs = deliver(
        &mut n,
        Packet::command(
            own,
            Message::DockConfirm {
                seq: 9,
                port: port(3),
            },
        ),
        1_100,
    );
    let acked = outs.iter().any(|o| {
        matches!(
            o,
            Output::Frame(Packet {
                msg: Message::Ack {
                    kind: Kind::DockConfirm,
                    seq: 9,
                    result: AckResult::Ok,
                    ..
                },
                ..
            })
        )
    });
    s.check("DockConfirm acknowledged Ok", acked);
    s.check("relay on after DockConfirm", n.actuators().relay);

    n.handle_loop_level(port(3), false, Millis(2_000));
    let _ = drain(&mut n);
    s.check(
        "relay stays on until the open loop is debounced",
        n.actuators().relay,
    );
    let outs = run_until(&mut n, 2_000 + DEBOUNCE_MS);
    let removed = Packet::report(own, Message::DockRemoved { port: port(3) });
    s.check(
        "DockRemoved after the debounced open",
        has_frame(&outs, &removed),
    );
    s.check("relay off after undocking", !n.actuators().relay);
}

/// A docked, confirmed and linked port read back with a full state query.
fn state_read_back(s: &mut Suite) {
    let own = id(0x111);
    let mut n = Node::new(config(Some(own), BootRole::Static), Millis(0));
    let _ = drain(&mut n);
    n.handle_loop_level(port(2), true, Millis(0));
    let _ = run_until(&mut n, DEBOUNCE_MS);
    let partner = Some(DockPartner {
        node: id(0x002),
        port: port(1),
    });
    let cmd = |msg| Packet::command(own, msg);
    let _ = deliver(
        &mut n,
        cmd(Message::DockConfirm {
            seq: 1,
            port: port(2),
        }),
        100,
    );
    let outs = deliver(
        &mut n,
        cmd(Message::DockLink {
            seq: 2,
            port: port(2),
            partner,
        }),
        100,
    );
    let ack = Packet::report(
        own,
        Message::Ack {
            kind: Kind::DockLink,
            seq: 2,
            result: AckResult::Ok,
            detail: 0,
        },
    );
    s.check(
        "DockLink on a confirmed port acknowledged Ok",
        has_frame(&outs, &ack),
    );

    let outs = deliver(
        &mut n,
        cmd(Message::StateQuery {
            seq: 5,
            parts: StateParts::ALL,
        }),
        200,
    );
    let report = |r| Packet::report(own, Message::StateReport(r));
    let dock = StateReport::Dock {
        port: port(2),
        state: DockState {
            closed: true,
            confirmed: true,
            partner,
        },
    };
    s.check(
        "state reply reports the linked port",
        has_frame(&outs, &report(dock)),
    );
    let uid = Uid([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]);
    s.check(
        "state reply reports the UID",
        has_frame(&outs, &report(StateReport::UidLow(uid.low())))
            && has_frame(&outs, &report(StateReport::UidHigh(uid.high()))),
    );
    s.check(
        "state reply reports the protocol version",
        has_frame(
            &outs,
            &report(StateReport::Protocol {
                version: ihex_proto::PROTOCOL_VERSION,
            }),
        ),
    );
    let end = StateReport::End {
        seq: 5,
        parts: StateParts::ALL,
        count: 9,
    };
    s.check(
        "state reply closed by End counting 9 reports",
        outs.len() == 10 && outs.last() == Some(&Output::Frame(report(end))),
    );
}

fn unconfigured_node_gets_id_over_uart(s: &mut Suite) {
    let mut n = Node::new(config(None, BootRole::Static), Millis(0));
    let outs = run_until(&mut n, 500);
    s.check(
        "unconfigured node stays silent",
        !outs.iter().any(|o| matches!(o, Output::Frame(_))),
    );
    s.check("unconfigured node has no ID", n.node_id().is_none());

    n.handle_uart_byte(0xA1, Millis(600));
    n.handle_uart_byte(0x22, Millis(601));
    let outs = drain(&mut n);
    let new = id(0x122);
    s.check(
        "UART set-ID asks to store it",
        outs.contains(&Output::StoreId(new)),
    );
    s.check(
        "UART set-ID asks for new filters",
        outs.contains(&Output::FiltersChanged),
    );
    s.check(
        "UART set-ID replies 51 22",
        outs.contains(&Output::Uart([0x51, 0x22])),
    );
    s.check(
        "BootUp from the new ID",
        outs.iter().any(|o| matches!(o, Output::Frame(Packet { src, msg: Message::BootUp { .. }, .. }) if *src == new)),
    );
    s.check("the new ID is in force at once", n.node_id() == Some(new));

    n.handle_uart_byte(0x00, Millis(700));
    let outs = drain(&mut n);
    s.check(
        "a stray byte is answered Malformed (E0 02)",
        outs.contains(&Output::Uart([0xE0, 0x02])),
    );
}

fn firmware_modules(s: &mut Suite) {
    s.check(
        "CRC-32 check value",
        record::crc32(b"123456789") == 0xCBF4_3926,
    );
    let mut all = true;
    for raw in (0x001..=0xFFD).step_by(7) {
        let r = record::Record {
            node_id: id(raw),
            role: BootRole::Mobile,
        };
        all &= record::Record::decode(&r.encode()) == Ok(r);
    }
    s.check("flash record round trip", all);
    s.check(
        "erased flash page reads as factory-fresh",
        record::Record::decode(&[0xFF; record::LEN]) == Err(record::RecordError::Erased),
    );

    let mut all = true;
    for raw in 0x001..=0xFFD {
        for b in to_bxcan(&sc_filters(Some(id(raw))))
            .expect("sc filters fit bxCAN")
            .iter()
        {
            all &= bank::plan(b).map(|p| bank::registers(&p)) == Ok(bank::bank_registers(b));
        }
    }
    s.check("filter bank plan round trip for every node ID", all);

    let p = Packet::command(
        id(0x123),
        Message::DockConfirm {
            seq: 200,
            port: port(5),
        },
    );
    let (raw, data) = p.encode();
    s.check(
        "packet encode/decode round trip",
        Packet::decode(raw, &data) == Ok(p),
    );
}

/// An update image packed on the host with the test key (build.rs, 4000-byte payload, version
/// 1.2.3, protocol 1.x).
static IMAGE: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/test-image.img"));

/// The image's checks, run with salty's Cortex-M4 field arithmetic, must agree with the host's.
fn image_checks(s: &mut Suite) {
    use ihex_image::{
        board::F303RE, check_signed, test_key, verify_image, Board, Hasher, ImageError, Policy,
        HEADER_BLOCK,
    };
    let policy = Policy::new(
        Board::NUCLEO_F303RE,
        &F303RE,
        1,
        FirmwareVersion::new(1, 0, 0),
    );
    let key = test_key::PUBLIC;
    s.check(
        "host-signed image verifies (ed25519 + SHA-512)",
        verify_image(IMAGE, &key, &policy)
            .is_ok_and(|h| h.version == FirmwareVersion::new(1, 2, 3)),
    );
    let mut buf = [0u8; 4512];
    buf.copy_from_slice(IMAGE);
    buf[HEADER_BLOCK + 17] ^= 0x40;
    s.check(
        "a changed payload byte is Corrupted",
        verify_image(&buf, &key, &policy) == Err(ImageError::Corrupted),
    );
    buf.copy_from_slice(IMAGE);
    buf[130] ^= 0x01;
    s.check(
        "a changed signature byte is BadSignature",
        check_signed(&buf, &key, &policy) == Err(ImageError::BadSignature),
    );
    let mut older = policy;
    older.running = FirmwareVersion::new(2, 0, 0);
    s.check(
        "an older image is a Downgrade",
        matches!(
            check_signed(IMAGE, &key, &older),
            Err(ImageError::Downgrade { .. })
        ),
    );
    let mut h = Hasher::new();
    h.update(b"a");
    h.update(b"bc");
    s.check(
        "SHA-512(abc) in pieces",
        h.finish().prefix::<4>() == [0xdd, 0xaf, 0x35, 0xa1],
    );
}

/// The adapter's flash for [`update_on_m4`]: the DFU slot in RAM (the image's chunks, rounded up).
struct Dfu {
    mem: [u8; 4608],
    marked: bool,
    reset: bool,
    refused: Option<FwRefusal>,
    complete: bool,
    rebooting: bool,
}

impl Dfu {
    /// Carries out the node's outputs as the node task does, reporting back.
    fn run(&mut self, n: &mut Node, t: u64) {
        let now = Millis(t);
        while let Some(o) = n.poll_output() {
            match o {
                Output::EraseDfu { len } => {
                    let ok = len as usize <= self.mem.len();
                    self.mem.fill(0xFF);
                    n.handle_fw_erased(if ok { Ok(()) } else { Err(FlashError) }, now);
                }
                Output::WriteDfu { offset, data } => {
                    let at = offset as usize;
                    match self.mem.get_mut(at..at + data.len()) {
                        Some(dst) if dst.iter().all(|&b| b == 0xFF) => dst.copy_from_slice(&data),
                        _ => n.handle_fw_write_failed(now),
                    }
                }
                Output::HashDfu { offset, len } => {
                    let r = self
                        .mem
                        .get(offset as usize..(offset + len) as usize)
                        .map(ihex_image::Hasher::digest)
                        .ok_or(FlashError);
                    n.handle_fw_hashed(r, now);
                }
                Output::MarkUpdated => {
                    self.marked = true;
                    n.handle_fw_marked(Ok(()), now);
                }
                Output::Reset => self.reset = true,
                Output::Frame(Packet {
                    msg: Message::FwStatus(st),
                    ..
                }) => match st.phase {
                    FwPhase::Refused => self.refused = Some(st.reason),
                    FwPhase::Complete => self.complete = true,
                    FwPhase::Rebooting => self.rebooting = true,
                    _ => {}
                },
                _ => {}
            }
        }
    }
}

/// The node's firmware-update receiver on the Cortex-M4: the host-signed image sent frame by frame,
/// checked, written, verified and installed; and a byte changed on the way refused at the commit.
fn update_on_m4(s: &mut Suite) {
    let own = id(0x111);
    let image_id = ihex_image::Header::parse(IMAGE).map_or(0, |h| h.image_id());
    let run = |corrupt: Option<usize>| -> Dfu {
        let mut n = Node::new(config(Some(own), BootRole::Static), Millis(0));
        let mut dfu = Dfu {
            mem: [0; 4608],
            marked: false,
            reset: false,
            refused: None,
            complete: false,
            rebooting: false,
        };
        let _ = drain(&mut n);
        let begin = Message::FwBegin {
            image_id,
            len: IMAGE.len() as u32,
            force: false,
        };
        let (raw, d) = Packet::command(NodeId::BROADCAST, begin).encode();
        n.handle_frame(raw, true, false, &d, Millis(1));
        dfu.run(&mut n, 1);
        for (i, chunk) in IMAGE.chunks(FW_DATA_LEN).enumerate() {
            let mut data = [0xFF; FW_DATA_LEN];
            data[..chunk.len()].copy_from_slice(chunk);
            if corrupt.is_some_and(|c| c / FW_DATA_LEN == i) {
                data[0] ^= 0x10;
            }
            let p = Packet::command(
                NodeId::BROADCAST,
                Message::FwData {
                    index: i as u16,
                    data,
                },
            );
            let (raw, d) = p.encode();
            n.handle_frame(raw, true, false, &d, Millis(2));
            dfu.run(&mut n, 2);
        }
        let commit = Message::FwEnd {
            image_id,
            action: FwAction::Commit,
        };
        let (raw, d) = Packet::command(own, commit).encode();
        n.handle_frame(raw, true, false, &d, Millis(3));
        dfu.run(&mut n, 3);
        n.tick(Millis(3 + RESET_DELAY_MS));
        dfu.run(&mut n, 3 + RESET_DELAY_MS);
        dfu
    };
    let good = run(None);
    s.check(
        "update: every frame written, the image in the DFU slot byte for byte",
        good.complete && good.mem[..IMAGE.len()] == *IMAGE,
    );
    s.check(
        "update: verified, marked for the bootloader, reset",
        good.rebooting && good.marked && good.reset && good.refused.is_none(),
    );
    let bad = run(Some(ihex_image::HEADER_BLOCK + 1000));
    s.check(
        "update: a payload byte changed on the way is refused corrupted at the commit",
        bad.complete && bad.refused == Some(FwRefusal::Corrupted) && !bad.marked && !bad.reset,
    );
}

/// The relay's block kept across a software reset: the same words on the M4 as on the host, and
/// nothing but an encoded block decodes.
fn retained_block(s: &mut Suite) {
    let mut r = ihex_sc_core::Retained {
        relay: true,
        confirmed: 0b10_0001,
        ..Default::default()
    };
    r.links[0] = Some(ihex_proto::DockPartner {
        node: id(0x002),
        port: port(3),
    });
    let w = r.encode();
    s.check(
        "Retained block: golden words (magic, relay + confirmed, link)",
        w[0] == 0x1E7A_5E1A && w[2] == 0x2101 && w[3] == 0x8003_0002,
    );
    s.check(
        "Retained block: round trip",
        ihex_sc_core::Retained::decode(&w) == Some(r),
    );
    let mut flipped = 0;
    for i in 0..w.len() {
        for bit in 0..32 {
            let mut b = w;
            b[i] ^= 1 << bit;
            if ihex_sc_core::Retained::decode(&b).is_some() {
                flipped += 1;
            }
        }
    }
    s.check(
        "Retained block: every single-bit flip refused",
        flipped == 0,
    );
    // A xorshift stream standing in for the SRAM content after a power cut.
    let mut x = 0x2545_F491u32;
    let mut decoded = 0;
    for _ in 0..2000 {
        let mut b = [0u32; ihex_sc_core::RETAINED_WORDS];
        for v in &mut b {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            *v = x;
        }
        if ihex_sc_core::Retained::decode(&b).is_some() {
            decoded += 1;
        }
    }
    s.check("Retained block: random RAM never decodes", decoded == 0);
}

#[entry]
fn main() -> ! {
    let mut s = Suite {
        passed: 0,
        failed: 0,
    };
    static_node(&mut s);
    state_read_back(&mut s);
    unconfigured_node_gets_id_over_uart(&mut s);
    firmware_modules(&mut s);
    image_checks(&mut s);
    update_on_m4(&mut s);
    retained_block(&mut s);
    hprintln!(
        "{} passed, {} failed (Cortex-M4, QEMU mps2-an386)",
        s.passed,
        s.failed
    );
    debug::exit(if s.failed == 0 {
        debug::EXIT_SUCCESS
    } else {
        debug::EXIT_FAILURE
    });
    // Not reached: QEMU ends at the semihosting exit.
    loop {
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("PANIC {}", info);
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfi();
    }
}
