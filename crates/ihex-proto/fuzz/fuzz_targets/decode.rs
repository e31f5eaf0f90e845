//! Fuzz target `decode`: arbitrary identifiers, flags and data through `Packet::decode`,
//! `Packet::from_frame` and the UART decoder. Nothing may panic, and whatever decodes must
//! re-encode to exactly the input.
//!
//! Input layout: `id: u32 le`, `flags: u8` (bit 0 extended, bit 1 remote), then the data bytes
//! (the first 8 go into the frame, all of them into `Packet::decode`); the whole input is also fed
//! to the UART decoder byte by byte.
#![no_main]

use embedded_can::{ExtendedId, Frame, Id, StandardId};
use ihex_proto::filter::ID_MASK;
use ihex_proto::uart::{UartDecoder, UartReply, UartRequest};
use ihex_proto::Packet;
use libfuzzer_sys::fuzz_target;

#[path = "../../tests/common/mod.rs"]
mod common;
use common::TestFrame as FuzzFrame;

fuzz_target!(|input: &[u8]| {
    uart(input);
    if input.len() < 5 {
        return;
    }
    let raw = u32::from_le_bytes([input[0], input[1], input[2], input[3]]);
    let flags = input[4];
    let data = &input[5..];

    if let Ok(p) = Packet::decode(raw, data) {
        assert_eq!(p.validate(), Ok(()));
        let (id, bytes) = p.encode();
        assert_eq!(id, raw & ID_MASK);
        assert_eq!(bytes.as_slice(), data);
    }

    let data = &data[..data.len().min(8)];
    let id: Id = if flags & 1 != 0 {
        ExtendedId::new(raw & ID_MASK).unwrap().into()
    } else {
        StandardId::new((raw & 0x7FF) as u16).unwrap().into()
    };
    let frame = if flags & 2 != 0 {
        FuzzFrame::new_remote(id, data.len()).unwrap()
    } else {
        FuzzFrame::new(id, data).unwrap()
    };
    if let Ok(p) = Packet::from_frame(&frame) {
        assert!(frame.is_extended() && !frame.is_remote_frame());
        assert_eq!(Packet::decode(raw & ID_MASK, data), Ok(p));
        let back: FuzzFrame = p.to_frame().unwrap();
        assert_eq!(back, frame);
    }
});

fn uart(input: &[u8]) {
    let mut dec = UartDecoder::new();
    for &b in input {
        if let Some(Ok(req)) = dec.push(b) {
            // A request that decodes is one the host could have sent.
            let mut fresh = UartDecoder::new();
            let [a, b] = req.encode();
            assert_eq!(fresh.push(a), None);
            assert_eq!(fresh.push(b), Some(Ok(req)));
            if let UartRequest::SetId(id) = req {
                assert!(id.is_sc());
            }
        }
    }
    for pair in input.chunks_exact(2) {
        if let Some(reply) = UartReply::decode([pair[0], pair[1]]) {
            assert_eq!(reply.encode(), [pair[0], pair[1]]);
        }
    }
}
