//! Property test: any sequence of frames, UART bytes, loop levels, CAN status and ticks never makes
//! the core panic, emit an undecodable frame, speak while unconfigured or leave a deadline overdue.

use ihex_proto::{
    BootRole, DockPartner, DockRefuseReason, FirmwareVersion, Header, Kind, Message, NodeId,
    Packet, Port, ResetReason, StateParts, StateReport, Uid,
};
use ihex_sc_core::{
    Config, FirmwareIdentity, FlashError, Millis, Node, Output, UpdateConfig, CHUNK_LEN,
    OUTPUT_QUEUE_LEN,
};
use proptest::prelude::*;

const UID: [u8; 12] = [0xA5, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11];
const UPDATE: UpdateConfig = UpdateConfig {
    board: ihex_image::Board::NUCLEO_F303RE,
    key: ihex_image::test_key::PUBLIC,
    layout: &ihex_image::board::F303RE,
    reverted: false,
};

#[derive(Clone, Debug)]
enum Dest {
    Own,
    Broadcast,
    Other(u16),
}

#[derive(Clone, Debug)]
enum Input {
    /// Anything at all on the bus.
    RawFrame {
        raw_id: u32,
        extended: bool,
        remote: bool,
        data: Vec<u8>,
    },
    /// A frame with a real kind and the right length for it, mostly from the gateway: most decode.
    Command {
        kind: u8,
        dest: Dest,
        src: u16,
        data: [u8; 8],
    },
    /// Select + commit aimed at this node's UID (or a near miss).
    Assign {
        head_ok: bool,
        tail_ok: bool,
        new_id: u16,
        seq: u8,
    },
    /// A dock command (confirm, refuse or link) for a port, so that links get made and broken.
    Dock {
        what: u8,
        port: u8,
        partner: Option<(u16, u8)>,
    },
    /// A state query of any groups, to the node or to all.
    Query {
        parts: u8,
        broadcast: bool,
    },
    Loop {
        port: u8,
        closed: bool,
    },
    Uart(u8),
    CanStatus {
        tec: u8,
        rec: u8,
        bus_off: bool,
    },
    StoreFailed,
    BuzzerDone,
    Tick,
    /// A step of a firmware transfer of a good image, or an adapter's report.
    Fw(Fw),
}

#[derive(Clone, Debug)]
enum Fw {
    Begin {
        force: bool,
        broadcast: bool,
    },
    Header,
    Data(u16),
    Payload,
    End {
        commit: bool,
    },
    Query,
    Erased(bool),
    WriteFailed,
    /// The digest of the header block (0), of the payload (1), or garbage (2), or a read failure.
    Hashed(Option<u8>),
    Marked(bool),
    Confirmed(bool),
    SelfTest(bool),
}

/// A good image for every node of this test (newest possible version: never a downgrade).
fn good_image() -> &'static (Vec<u8>, u32) {
    static IMAGE: std::sync::OnceLock<(Vec<u8>, u32)> = std::sync::OnceLock::new();
    IMAGE.get_or_init(|| {
        let payload: Vec<u8> = (0..500u32).map(|i| (i * 7) as u8).collect();
        let bytes = ihex_image::pack(
            ihex_image::Board::NUCLEO_F303RE,
            ihex_proto::PROTOCOL_VERSION,
            FirmwareVersion::new(255, 255, 255),
            &payload,
            &ihex_image::SigningKey::test_key(),
        )
        .unwrap();
        let id = ihex_image::Header::parse(&bytes).unwrap().image_id();
        (bytes, id)
    })
}

fn fw() -> impl Strategy<Value = Fw> {
    prop_oneof![
        2 => (any::<bool>(), any::<bool>()).prop_map(|(force, broadcast)| Fw::Begin { force, broadcast }),
        2 => Just(Fw::Header),
        2 => (0u16..180).prop_map(Fw::Data),
        1 => Just(Fw::Payload),
        2 => any::<bool>().prop_map(|commit| Fw::End { commit }),
        1 => Just(Fw::Query),
        1 => prop_oneof![4 => Just(true), 1 => Just(false)].prop_map(Fw::Erased),
        1 => Just(Fw::WriteFailed),
        2 => prop::option::of(0u8..3).prop_map(Fw::Hashed),
        1 => prop_oneof![4 => Just(true), 1 => Just(false)].prop_map(Fw::Marked),
        1 => prop_oneof![4 => Just(true), 1 => Just(false)].prop_map(Fw::Confirmed),
        1 => any::<bool>().prop_map(Fw::SelfTest),
    ]
}

fn dest() -> impl Strategy<Value = Dest> {
    prop_oneof![
        4 => Just(Dest::Own),
        3 => Just(Dest::Broadcast),
        1 => (0u16..0x1000).prop_map(Dest::Other),
    ]
}

/// Any input, firmware-transfer steps included.
fn input() -> impl Strategy<Value = Input> {
    prop_oneof![
        12 => input_no_fw(),
        3 => fw().prop_map(Input::Fw),
    ]
}

/// Any input but the scripted firmware-transfer steps (a random frame may still be one).
fn input_no_fw() -> impl Strategy<Value = Input> {
    prop_oneof![
        2 => (any::<u32>(), any::<bool>(), any::<bool>(), prop::collection::vec(any::<u8>(), 0..=10))
            .prop_map(|(raw_id, extended, remote, data)| Input::RawFrame { raw_id, extended, remote, data }),
        6 => (0u8..32, dest(), prop_oneof![5 => Just(0u16), 1 => 0u16..0x1000], any::<[u8; 8]>())
            .prop_map(|(kind, dest, src, data)| Input::Command { kind, dest, src, data }),
        1 => (any::<bool>(), any::<bool>(), 0u16..0x1000, any::<u8>())
            .prop_map(|(head_ok, tail_ok, new_id, seq)| Input::Assign { head_ok, tail_ok, new_id, seq }),
        2 => (0u8..3, 0u8..8, prop::option::of((1u16..0xFFE, 0u8..8)))
            .prop_map(|(what, port, partner)| Input::Dock { what, port, partner }),
        2 => (any::<u8>(), any::<bool>()).prop_map(|(parts, broadcast)| Input::Query { parts, broadcast }),
        4 => (0u8..8, any::<bool>()).prop_map(|(port, closed)| Input::Loop { port, closed }),
        3 => prop_oneof![
            any::<u8>(),
            Just(0xA1u8), Just(0x11), Just(0xB0), Just(0x00), Just(0xAF), Just(0xFF)
        ].prop_map(Input::Uart),
        1 => (any::<u8>(), any::<u8>(), any::<bool>())
            .prop_map(|(tec, rec, bus_off)| Input::CanStatus { tec, rec, bus_off }),
        1 => Just(Input::StoreFailed),
        1 => Just(Input::BuzzerDone),
        3 => Just(Input::Tick),
    ]
}

fn config() -> impl Strategy<Value = Config> {
    (
        prop_oneof![Just(BootRole::Static), Just(BootRole::Mobile)],
        prop_oneof![4 => 0u8..=8, 1 => any::<u8>()],
        prop_oneof![1 => Just(None), 3 => (0u16..0x1000).prop_map(NodeId::new)],
        any::<u8>(),
    )
        .prop_map(|(role, ports, node_id, reset)| Config {
            role,
            ports,
            uid: Uid(UID),
            node_id,
            reset: ResetReason::from_raw(reset),
            firmware: FirmwareIdentity {
                version: FirmwareVersion::new(reset, 1, 2),
                image_hash: [reset; 7],
                trial: reset & 1 != 0,
            },
            update: UPDATE,
        })
}

/// Feeds one input. Steps made of several frames drain the node after each into `between`, as an
/// adapter does (the core's contract); `None` leaves them in the queue.
fn apply(n: &mut Node, input: &Input, now: Millis, between: Option<&mut Vec<Output>>) {
    let own = n.node_id().map_or(0x123, NodeId::get);
    match input {
        Input::RawFrame {
            raw_id,
            extended,
            remote,
            data,
        } => n.handle_frame(*raw_id, *extended, *remote, data, now),
        Input::Command {
            kind,
            dest,
            src,
            data,
        } => {
            let dest = match dest {
                Dest::Own => own,
                Dest::Broadcast => 0xFFF,
                Dest::Other(d) => *d,
            };
            let len = Kind::from_raw(*kind).map_or(3, |k| Message::len_of(k) as usize);
            let raw = (u32::from(*kind) << Header::KIND_SHIFT)
                | (u32::from(dest) << Header::DEST_SHIFT)
                | u32::from(*src);
            n.handle_frame(raw, true, false, &data[..len], now);
        }
        Input::Assign {
            head_ok,
            tail_ok,
            new_id,
            seq,
        } => {
            let mut head: [u8; 8] = UID[..8].try_into().unwrap();
            let mut tail: [u8; 4] = UID[8..].try_into().unwrap();
            head[0] ^= u8::from(!head_ok);
            tail[3] ^= u8::from(!tail_ok);
            let sel = Packet::command(NodeId::BROADCAST, Message::AssignSelect { uid_head: head });
            let (raw, d) = sel.encode();
            n.handle_frame(raw, true, false, &d, now);
            // Raw bytes, so out-of-range IDs are exercised too.
            let [lo, hi] = new_id.to_le_bytes();
            let d = [tail[0], tail[1], tail[2], tail[3], lo, hi, *seq];
            let raw = (Kind::AssignCommit as u32) << 24 | 0xFFF << 12;
            n.handle_frame(raw, true, false, &d, now);
        }
        Input::Dock {
            what,
            port,
            partner,
        } => {
            let port = Port::new(*port).unwrap();
            let msg = match what {
                0 => Message::DockConfirm { seq: 1, port },
                1 => Message::DockRefuse {
                    seq: 2,
                    port,
                    reason: DockRefuseReason::Busy,
                },
                _ => Message::DockLink {
                    seq: 3,
                    port,
                    partner: partner.map(|(node, p)| DockPartner {
                        node: NodeId::new_sc(node).unwrap(),
                        port: Port::new(p).unwrap(),
                    }),
                },
            };
            let (raw, d) = Packet::command(NodeId::new(own).unwrap(), msg).encode();
            n.handle_frame(raw, true, false, &d, now);
        }
        Input::Query { parts, broadcast } => {
            let dest = if *broadcast {
                NodeId::BROADCAST
            } else {
                NodeId::new(own).unwrap()
            };
            let q = Message::StateQuery {
                seq: *parts,
                parts: StateParts(*parts),
            };
            let (raw, d) = Packet::command(dest, q).encode();
            n.handle_frame(raw, true, false, &d, now);
        }
        Input::Loop { port, closed } => {
            n.handle_loop_level(Port::new(*port).unwrap(), *closed, now)
        }
        Input::Uart(b) => n.handle_uart_byte(*b, now),
        Input::CanStatus { tec, rec, bus_off } => n.handle_can_status(*tec, *rec, *bus_off, now),
        Input::StoreFailed => n.handle_store_failed(now),
        Input::BuzzerDone => n.handle_buzzer_done(now),
        Input::Tick => n.tick(now),
        Input::Fw(step) => apply_fw(n, step, own, now, between),
    }
}

fn apply_fw(n: &mut Node, step: &Fw, own: u16, now: Millis, mut between: Option<&mut Vec<Output>>) {
    use ihex_image::{header_block_digest, Hasher, HEADER_BLOCK, SIGNED_LEN};
    use ihex_proto::{FwAction, FW_DATA_LEN};
    let (img, image_id) = good_image();
    let frame = |i: u16| {
        let mut data = [0u8; FW_DATA_LEN];
        for (k, b) in data.iter_mut().enumerate() {
            *b = img.get(i as usize * FW_DATA_LEN + k).copied().unwrap_or(0);
        }
        Message::FwData { index: i, data }
    };
    let frames = img.len().div_ceil(FW_DATA_LEN) as u16;
    let send = |n: &mut Node, msg: Message, broadcast: bool| {
        let dest = if broadcast {
            NodeId::BROADCAST
        } else {
            NodeId::new(own).unwrap()
        };
        let (raw, d) = Packet::command(dest, msg).encode();
        n.handle_frame(raw, true, false, &d, now);
    };
    let mut burst = |n: &mut Node, range: std::ops::Range<u16>| {
        for i in range {
            send(n, frame(i), true);
            if let Some(out) = between.as_deref_mut() {
                out.extend(std::iter::from_fn(|| n.poll_output()));
            }
        }
    };
    match *step {
        Fw::Begin { force, broadcast } => send(
            n,
            Message::FwBegin {
                image_id: *image_id,
                len: img.len() as u32,
                force,
            },
            broadcast,
        ),
        Fw::Header => burst(n, 0..32),
        Fw::Data(i) => send(n, frame(i), true),
        Fw::Payload => burst(n, 32..frames),
        Fw::End { commit } => {
            let action = if commit {
                FwAction::Commit
            } else {
                FwAction::Abort
            };
            send(
                n,
                Message::FwEnd {
                    image_id: *image_id,
                    action,
                },
                true,
            )
        }
        Fw::Query => send(
            n,
            Message::FwQuery {
                image_id: *image_id,
            },
            false,
        ),
        Fw::Erased(ok) => n.handle_fw_erased(if ok { Ok(()) } else { Err(FlashError) }, now),
        Fw::WriteFailed => n.handle_fw_write_failed(now),
        Fw::Hashed(which) => {
            let d = match which {
                Some(0) => Ok(header_block_digest(img[..SIGNED_LEN].try_into().unwrap())),
                Some(1) => Ok(Hasher::digest(&img[HEADER_BLOCK..])),
                Some(_) => Ok(Hasher::digest(b"garbage")),
                None => Err(FlashError),
            };
            n.handle_fw_hashed(d, now)
        }
        Fw::Marked(ok) => n.handle_fw_marked(if ok { Ok(()) } else { Err(FlashError) }, now),
        Fw::Confirmed(ok) => n.handle_fw_confirmed(if ok { Ok(()) } else { Err(FlashError) }, now),
        Fw::SelfTest(ok) => n.handle_self_test(ok, now),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 500, ..ProptestConfig::default() })]

    #[test]
    fn never_panics_and_only_emits_valid_frames(
        cfg in config(),
        start in 0u64..1_000_000,
        steps in prop::collection::vec((input(), prop_oneof![4 => 0u64..20, 2 => 20u64..400, 1 => 0u64..100_000]), 0..80),
    ) {
        let mut now = Millis(start);
        let mut n = Node::new(cfg, now);
        let (mut confirmed_asked, mut reset_asked) = (false, false);
        let ports = cfg.ports.min(8);
        let has_relay = cfg.role == BootRole::Static && ports > 0;
        for (input, dt) in std::iter::once((Input::Tick, 0)).chain(steps) {
            now = now.add_ms(dt);
            let before = n.node_id();
            let mut outs = Vec::new();
            apply(&mut n, &input, now, Some(&mut outs));
            outs.extend(std::iter::from_fn(|| n.poll_output()));
            let mut reports = 0u32;
            for out in outs {
                if let Output::Frame(p) = out {
                    // A state reply is whole and closed by an End that counts it.
                    match p.msg {
                        Message::StateReport(StateReport::End { count, .. }) => {
                            prop_assert_eq!(u32::from(count), reports, "End count after {:?}", input);
                            reports = 0;
                        }
                        Message::StateReport(StateReport::Dock { state, .. }) => {
                            reports += 1;
                            prop_assert!(state.closed || !state.confirmed, "confirmed only while docked: {:?}", p);
                            prop_assert!(state.confirmed || state.partner.is_none(), "linked only while confirmed: {:?}", p);
                        }
                        Message::StateReport(_) => reports += 1,
                        _ => {}
                    }
                    prop_assert_eq!(p.validate(), Ok(()), "{:?} after {:?}", p, input);
                    let (raw, data) = p.encode();
                    prop_assert_eq!(Packet::decode(raw, &data), Ok(p));
                    // Timers run before the input, so one call may report under the old ID first.
                    prop_assert!(
                        Some(p.src) == n.node_id() || Some(p.src) == before,
                        "frames come from the ID in force: {:?}", p
                    );
                    prop_assert_eq!(p.dest, NodeId::GATEWAY);
                }
                if let Output::StoreId(id) = out {
                    prop_assert!(id.is_sc());
                }
                let dfu = UPDATE.layout.dfu.len;
                match out {
                    Output::EraseDfu { len } => prop_assert!(len <= dfu && len % CHUNK_LEN as u32 == 0),
                    Output::WriteDfu { offset, .. } => prop_assert!(
                        offset % CHUNK_LEN as u32 == 0 && offset + CHUNK_LEN as u32 <= dfu
                    ),
                    Output::HashDfu { offset, len } => prop_assert!(offset + len <= dfu),
                    Output::MarkBooted => {
                        prop_assert!(cfg.firmware.trial, "only an image on trial is confirmed");
                        prop_assert!(!confirmed_asked, "asked to confirm once");
                        confirmed_asked = true;
                    }
                    Output::Reset => {
                        prop_assert!(!reset_asked, "one reset");
                        reset_asked = true;
                    }
                    _ => {}
                }
            }
            prop_assert_eq!(reports, 0, "state reports without their End after {:?}", input);
            prop_assert!(n.node_id().is_none_or(|id| id.is_sc()));
            prop_assert_eq!(n.dropped_outputs(), 0, "drained after every call, the queue never fills");
            if let Some(t) = n.poll_at() {
                prop_assert!(t > now, "deadline {:?} overdue at {:?}", t, now);
            }
            let a = n.actuators();
            prop_assert!(!a.relay || has_relay, "only a static element with ports has a relay");
            prop_assert_eq!(n.loops() & !((1u16 << ports) - 1) as u8, 0);
            if let Some((_, duty)) = a.led.blink {
                prop_assert!((1..=99).contains(&duty));
            }
            let _ = n.actuators_changed();
        }
    }

    #[test]
    fn full_queue_keeps_every_ack_fault_and_adapter_request(
        steps in prop::collection::vec(input_no_fw(), 0..200),
    ) {
        // Two identical nodes: one drained after every call (sees everything), one never drained.
        let cfg = Config {
            role: BootRole::Static,
            ports: 6,
            uid: Uid(UID),
            node_id: NodeId::new_sc(0x111),
            reset: ResetReason::PowerOn,
            firmware: FirmwareIdentity::default(),
            update: UPDATE,
        };
        let mut drained = Node::new(cfg, Millis(0));
        let mut stuck = Node::new(cfg, Millis(0));
        let mut all: Vec<Output> = std::iter::from_fn(|| drained.poll_output()).collect();
        for (i, input) in steps.iter().enumerate() {
            apply(&mut drained, input, Millis(i as u64 * 7), None);
            apply(&mut stuck, input, Millis(i as u64 * 7), None);
            all.extend(std::iter::from_fn(|| drained.poll_output()));
        }
        let kept: Vec<Output> = std::iter::from_fn(|| stuck.poll_output()).collect();
        prop_assert!(kept.len() <= OUTPUT_QUEUE_LEN);
        let essentials = |v: &[Output]| -> Vec<Output> {
            v.iter().copied().filter(|o| !matches!(o, Output::Frame(p) if !matches!(p.msg, Message::Ack { .. } | Message::Fault { .. }))).collect()
        };
        let want = essentials(&all);
        if want.len() <= OUTPUT_QUEUE_LEN {
            prop_assert_eq!(essentials(&kept), want, "essentials are never sacrificed while others remain");
        }
        // What was kept is a subsequence of what was produced.
        let mut it = all.iter();
        for k in &kept {
            prop_assert!(it.any(|o| o == k), "{:?} kept out of order or invented", k);
        }
        prop_assert_eq!(stuck.dropped_outputs() as usize, all.len() - kept.len());
    }
}
