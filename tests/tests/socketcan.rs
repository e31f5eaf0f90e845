//! Kernel-level SocketCAN tests: behaviour only a real Linux CAN stack (vcan) produces.
//!
//! Each test leases its own vcan interface(s). To prove a frame was *dropped* without waiting for
//! time to pass, every test ends its traffic with a sentinel frame that passes the filter under test:
//! the kernel delivers frames of one interface in order, so whatever has not arrived by the time the
//! sentinel does was filtered out.
#![cfg(feature = "vcan")]

use std::time::Duration;

use embedded_can::{ExtendedId, Id, StandardId};
use ihex_proto::filter::{self, Filter};
use ihex_proto::{AckResult, Header, Kind, LedCommand, Message, NodeId, Packet, Port, Rgb};
use ihex_tests::{can, id as node, within};
use socketcan::tokio::CanSocket;
use socketcan::{CanErrorFrame, CanFilter, CanFrame, EmbeddedFrame, Frame, SocketOptions};

const WAIT: Duration = Duration::from_secs(5);

fn open(iface: &str) -> CanSocket {
    CanSocket::open(iface).unwrap_or_else(|e| panic!("open {iface}: {e}"))
}

fn ext(raw: u32) -> Id {
    Id::Extended(ExtendedId::new(raw).expect("29-bit id"))
}

fn data_frame(id: Id, data: &[u8]) -> CanFrame {
    CanFrame::new(id, data).expect("valid frame")
}

/// A data frame of `kind` from `src` to `dest`.
fn addressed(kind: Kind, dest: u16, src: u16) -> CanFrame {
    let h = Header {
        kind,
        dest: node(dest),
        src: node(src),
    };
    data_frame(
        Id::Extended(h.to_id()),
        &[kind as u8, dest as u8, src as u8],
    )
}

/// Installs a filter set on `sock` exactly as the gateway would: the kernel plan and its join flag.
fn install(sock: &CanSocket, filters: &[Filter]) -> filter::KernelPlan {
    let plan = filter::to_kernel(filters).expect("filters fit the kernel");
    let kernel: Vec<CanFilter> = plan
        .filters
        .iter()
        .map(|k| CanFilter::new(k.can_id, k.can_mask))
        .collect();
    sock.set_filters(&kernel).expect("CAN_RAW_FILTER");
    sock.set_join_filters(plan.join)
        .expect("CAN_RAW_JOIN_FILTERS");
    plan
}

/// Reads frames until one equal to `sentinel` arrives; returns those before it.
async fn until_sentinel(sock: &CanSocket, sentinel: &CanFrame) -> Vec<CanFrame> {
    let mut got = Vec::new();
    loop {
        let f = within(WAIT, "waiting for the sentinel frame", sock.read_frame())
            .await
            .unwrap_or_else(|e| panic!("{e}; received so far: {got:?}"))
            .expect("read_frame");
        if f == *sentinel {
            return got;
        }
        got.push(f);
    }
}

async fn send_all(sock: &CanSocket, frames: &[CanFrame]) {
    for f in frames {
        sock.write_frame(*f).await.expect("write_frame");
    }
}

#[tokio::test]
async fn frame_sent_on_one_socket_arrives_on_another() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    let frame = data_frame(ext(0x1234_5678 & 0x1FFF_FFFF), &[1, 2, 3, 4, 5, 6, 7, 8]);
    tx.write_frame(frame).await.unwrap();
    let got = within(WAIT, "frame on the second socket", rx.read_frame())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(got, frame);
    assert!(got.is_extended());
    assert_eq!(got.data(), &[1, 2, 3, 4, 5, 6, 7, 8]);
}

#[tokio::test]
async fn frames_stay_on_their_own_interface() {
    let (a, b) = (can::lease(), can::lease());
    let (tx_a, rx_b) = (open(&a), open(&b));
    let tx_b = open(&b);
    tx_a.write_frame(data_frame(ext(0x100), &[0xAA]))
        .await
        .unwrap();
    let sentinel = data_frame(ext(0x1FF), &[0x55]);
    tx_b.write_frame(sentinel).await.unwrap();
    assert_eq!(
        until_sentinel(&rx_b, &sentinel).await,
        vec![],
        "{a}'s frame leaked onto {b}"
    );
}

#[tokio::test]
async fn sc_acceptance_filter_drops_what_it_must() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    let me = 0x111;
    let filters = filter::sc_filters(Some(node(me)));
    let plan = install(&rx, &filters);
    assert!(
        !plan.join && !plan.software_check,
        "accept-only sets are OR-ed: {plan:?}"
    );

    let to_me = addressed(Kind::LedSet, me, 0x000);
    let to_all = addressed(Kind::HealthCheck, 0xFFF, 0x000);
    let to_other = addressed(Kind::LedSet, 0x222, 0x000);
    let from_me = addressed(Kind::HealthReply, 0x000, me);
    // Same low 11 bits as a frame to me, but a standard ID: the EFF bit in the mask must drop it.
    let std_alias = data_frame(
        Id::Standard(StandardId::new((to_me.raw_id() & 0x7FF) as u16).unwrap()),
        &[9],
    );
    let h = Header {
        kind: Kind::LedSet,
        dest: node(me),
        src: NodeId::GATEWAY,
    };
    let remote_to_me = CanFrame::new_remote(Id::Extended(h.to_id()), 0).unwrap();
    let sentinel = addressed(Kind::Identify, me, 0x001);
    send_all(
        &tx,
        &[
            to_me,
            to_other,
            std_alias,
            to_all,
            from_me,
            remote_to_me,
            sentinel,
        ],
    )
    .await;

    let got = until_sentinel(&rx, &sentinel).await;
    assert_eq!(got, vec![to_me, to_all]);
    // The kernel agrees with the protocol crate's own rule, frame by frame.
    for f in [to_me, to_other, std_alias, to_all, from_me, remote_to_me] {
        let sw = filter::accepts(&filters, filter::word_of(&f));
        assert_eq!(
            got.contains(&f),
            sw,
            "kernel and filter::accepts disagree on {f:?}"
        );
    }
}

#[tokio::test]
async fn unconfigured_sc_hears_only_broadcasts() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    install(&rx, &filter::sc_filters(None));
    let to_all = addressed(Kind::AssignSelect, 0xFFF, 0x000);
    let to_unconfigured = addressed(Kind::LedSet, 0xFFE, 0x000);
    let to_node = addressed(Kind::LedSet, 0x001, 0x000);
    let sentinel = addressed(Kind::AssignCommit, 0xFFF, 0x000);
    send_all(&tx, &[to_unconfigured, to_all, to_node, sentinel]).await;
    assert_eq!(until_sentinel(&rx, &sentinel).await, vec![to_all]);
}

#[tokio::test]
async fn inverted_reject_filter_keeps_the_rest() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    // Everything except frames addressed to 0x222, and except anything from 0x333.
    let filters = [
        Filter {
            action: filter::Action::Reject,
            ..Filter::to_node(node(0x222))
        },
        Filter::reject(
            filter::EFF | 0x333,
            filter::EFF | filter::RTR | Header::NODE_MASK,
        ),
    ];
    let plan = install(&rx, &filters);
    assert!(plan.join, "reject-only sets are joined: {plan:?}");
    assert!(plan.filters.iter().all(|k| k.inverted()));

    let keep = [
        addressed(Kind::LedSet, 0x111, 0x000),
        addressed(Kind::HealthReply, 0x000, 0x111),
        data_frame(Id::Standard(StandardId::new(0x222).unwrap()), &[1]),
    ];
    let drop = [
        addressed(Kind::LedSet, 0x222, 0x000),
        addressed(Kind::Ack, 0x000, 0x333),
    ];
    let sentinel = addressed(Kind::Identify, 0x444, 0x000);
    send_all(
        &tx,
        &[drop[0], keep[0], drop[1], keep[1], keep[2], sentinel],
    )
    .await;
    assert_eq!(until_sentinel(&rx, &sentinel).await, keep.to_vec());
}

#[tokio::test]
async fn seed_example_mask_filter_in_the_kernel() {
    let iface = can::lease();
    let (tx, rx_accept, rx_reject) = (open(&iface), open(&iface), open(&iface));
    // The seed's worked example: mask 0x20000111, id 0xA0000431.
    install(&rx_accept, &[Filter::accept(0xA000_0431, 0x2000_0111)]);
    install(&rx_reject, &[Filter::reject(0xA000_0431, 0x2000_0111)]);
    let passes = data_frame(ext(0x2135_3011 & filter::ID_MASK), &[1]);
    let fails = data_frame(ext(0x2135_3110 & filter::ID_MASK), &[2]);
    // Bits 0, 4, 8 and EFF decide: 0x431 matches the example (the reject filter drops it too),
    // 0x430 does not.
    let sentinel_a = data_frame(ext(0x0000_0431), &[3]);
    let sentinel_r = data_frame(ext(0x0000_0430), &[4]);
    send_all(&tx, &[fails, passes, sentinel_a, sentinel_r]).await;
    assert_eq!(until_sentinel(&rx_accept, &sentinel_a).await, vec![passes]);
    assert_eq!(until_sentinel(&rx_reject, &sentinel_r).await, vec![fails]);
}

#[tokio::test]
async fn mixed_set_needs_and_gets_a_software_check() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    // Two accepts and a reject: the kernel cannot express it and lets a superset through.
    let bad_src = Filter::reject(
        filter::EFF | 0x333,
        filter::EFF | filter::RTR | Header::NODE_MASK,
    );
    let mut filters: Vec<Filter> = filter::sc_filters(Some(node(0x111))).into_iter().collect();
    filters.push(bad_src);
    let plan = install(&rx, &filters);
    assert!(plan.software_check, "{plan:?}");

    let good = addressed(Kind::LedSet, 0x111, 0x000);
    let good_bc = addressed(Kind::HealthCheck, 0xFFF, 0x000);
    let from_bad = addressed(Kind::LedSet, 0x111, 0x333);
    let elsewhere = addressed(Kind::LedSet, 0x222, 0x000);
    let sentinel = addressed(Kind::Identify, 0x111, 0x001);
    send_all(&tx, &[good, from_bad, elsewhere, good_bc, sentinel]).await;

    let kernel = until_sentinel(&rx, &sentinel).await;
    assert_eq!(kernel, vec![good, from_bad, good_bc], "kernel superset");
    let checked: Vec<CanFrame> = kernel
        .into_iter()
        .filter(|f| filter::accepts(&filters, filter::word_of(f)))
        .collect();
    assert_eq!(checked, vec![good, good_bc]);
}

#[tokio::test]
async fn error_frame_reaches_only_sockets_that_asked() {
    let iface = can::lease();
    let (tx, with_err, without_err) = (open(&iface), open(&iface), open(&iface));
    // ID filters do not apply to error frames: drop every data frame on the error listener.
    with_err.set_filter_drop_all().unwrap();
    with_err.set_error_filter_accept_all().unwrap();
    without_err.set_error_filter_drop_all().unwrap();

    // CAN_ERR_BUSOFF (0x40) and CAN_ERR_CRTL (0x04) with "TX error passive" (0x20) in data[1].
    let err = CanErrorFrame::new_error(0x40 | 0x04, &[0, 0x20]).unwrap();
    let sentinel = data_frame(ext(0x7), &[7]);
    tx.write_frame(CanFrame::Error(err))
        .await
        .expect("write error frame");
    tx.write_frame(sentinel).await.unwrap();

    let got = within(WAIT, "error frame", with_err.read_frame())
        .await
        .unwrap()
        .unwrap();
    assert!(got.is_error_frame(), "{got:?}");
    match got {
        CanFrame::Error(e) => {
            assert_eq!(e.error_bits(), 0x44);
            assert_eq!(e.data()[1], 0x20);
        }
        other => panic!("expected an error frame, got {other:?}"),
    }
    assert_eq!(until_sentinel(&without_err, &sentinel).await, vec![]);
}

#[tokio::test]
async fn ihex_packets_round_trip_through_the_kernel() {
    let iface = can::lease();
    let (tx, rx) = (open(&iface), open(&iface));
    let port = |p| Port::new(p).unwrap();
    let packets = [
        Packet::command(
            node(0x111),
            Message::LedSet {
                seq: 7,
                cmd: LedCommand::Steady {
                    color: Rgb::new(255, 16, 0),
                    brightness: 200,
                },
            },
        ),
        Packet::command(
            node(0x111),
            Message::DockConfirm {
                seq: 8,
                port: port(3),
            },
        ),
        Packet::report(node(0x2), Message::Handshake { port: port(0) }),
        Packet::report(node(0x111), Message::DockDetected { port: port(3) }),
        Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 255 }),
        Packet::command(node(0xFFD), Message::PowerSet { seq: 1, on: true }),
        Packet::report(
            node(0xFFD),
            Message::Ack {
                kind: Kind::PowerSet,
                seq: 1,
                result: AckResult::Ok,
                detail: 0,
            },
        ),
    ];
    for p in &packets {
        let frame: CanFrame = p.to_frame().expect("packet fits a frame");
        tx.write_frame(frame).await.unwrap();
    }
    for want in &packets {
        let f = within(WAIT, "packet frame", rx.read_frame())
            .await
            .unwrap()
            .unwrap();
        assert!(f.is_extended());
        assert_eq!(Packet::from_frame(&f).as_ref(), Ok(want));
    }
}
