//! Decoding of SocketCAN error frames (`linux/can/error.h`) into the names used by `bus_error` events.

use crate::event::BusError;

/// `CAN_ERR_*` class bits of the error frame's identifier, with their event names.
pub const CLASSES: [(u32, &str); 10] = [
    (0x0001, "tx_timeout"),
    (0x0002, "lost_arbitration"),
    (0x0004, "controller"),
    (0x0008, "protocol"),
    (0x0010, "transceiver"),
    (0x0020, "no_ack"),
    (0x0040, "bus_off"),
    (0x0080, "bus_error"),
    (0x0100, "restarted"),
    (0x0200, "counters"),
];

/// `CAN_ERR_CRTL_*` bits of `data[1]`.
const CONTROLLER: [(u8, &str); 7] = [
    (0x01, "rx_overflow"),
    (0x02, "tx_overflow"),
    (0x04, "rx_warning"),
    (0x08, "tx_warning"),
    (0x10, "rx_passive"),
    (0x20, "tx_passive"),
    (0x40, "active"),
];

/// `CAN_ERR_PROT_*` bits of `data[2]`.
const PROTOCOL: [(u8, &str); 8] = [
    (0x01, "bit"),
    (0x02, "form"),
    (0x04, "stuff"),
    (0x08, "bit0"),
    (0x10, "bit1"),
    (0x20, "overload"),
    (0x40, "active"),
    (0x80, "tx"),
];

/// Only the class bits: the frame-format flags (`CAN_ERR_FLAG` and the like) are not part of it.
const CLASS_MASK: u32 = 0x1FFF_FFFF;

fn names<T: Copy + std::ops::BitAnd<Output = T> + PartialEq + Default>(
    bits: T,
    table: &[(T, &str)],
) -> Vec<String> {
    table
        .iter()
        .filter(|(b, _)| bits & *b != T::default())
        .map(|(_, n)| (*n).to_string())
        .collect()
}

/// The `bus_error` payload of an error frame (without `suppressed`).
pub fn decode(class: u32, data: [u8; 8]) -> BusError {
    let class = class & CLASS_MASK;
    let classes = names(class, &CLASSES);
    let has = |bit: u32| class & bit != 0;
    let message = if classes.is_empty() {
        "error frame without class bits".to_string()
    } else {
        format!("error frame: {}", classes.join(", "))
    };
    BusError {
        error: "error_frame".into(),
        message,
        classes: Some(classes),
        controller: has(0x0004).then(|| names(data[1], &CONTROLLER)),
        protocol: has(0x0008).then(|| names(data[2], &PROTOCOL)),
        tec: has(0x0200).then_some(data[6]),
        rec: has(0x0200).then_some(data[7]),
        data: Some(ihex_proto::Hex(&data).to_string()),
        ..BusError::default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decodes_controller_protocol_and_counters() {
        // CAN_ERR_FLAG | CRTL | PROT | CNT; rx_passive + tx_warning, stuff error, tec 130, rec 7.
        let e = decode(
            0x2000_0000 | 0x4 | 0x8 | 0x200,
            [0, 0x18, 0x04, 0, 0, 0, 130, 7],
        );
        assert_eq!(
            e.classes.as_deref(),
            Some(
                &[
                    "controller".to_string(),
                    "protocol".into(),
                    "counters".into()
                ][..]
            )
        );
        assert_eq!(
            e.controller,
            Some(vec!["tx_warning".to_string(), "rx_passive".into()])
        );
        assert_eq!(e.protocol, Some(vec!["stuff".to_string()]));
        assert_eq!((e.tec, e.rec), (Some(130), Some(7)));
        assert_eq!(e.data.as_deref(), Some("0018040000008207"));
    }

    #[test]
    fn absent_classes_leave_details_out() {
        let e = decode(0x40, [0xff; 8]);
        assert_eq!(e.classes, Some(vec!["bus_off".to_string()]));
        assert_eq!((e.controller, e.protocol, e.tec), (None, None, None));
        assert_eq!(decode(0, [0; 8]).message, "error frame without class bits");
    }
}
