//! The `serde` feature: validated newtypes stay valid when deserialised. Runs whenever the feature
//! is on (`cargo test -p ihex-proto --features serde`, and `cargo test --workspace`, where the
//! gateway and the tools enable it).
#![cfg(feature = "serde")]

use ihex_proto::{NodeId, Port, ResetReason};

#[test]
fn node_id_and_port_serialise_as_plain_numbers() {
    assert_eq!(
        serde_json::to_string(&NodeId::new(0x111).unwrap()).unwrap(),
        "273"
    );
    assert_eq!(serde_json::to_string(&Port::new(3).unwrap()).unwrap(), "3");
    assert_eq!(
        serde_json::from_str::<NodeId>("273").unwrap(),
        NodeId::new(0x111).unwrap()
    );
    assert_eq!(
        serde_json::from_str::<NodeId>("4095").unwrap(),
        NodeId::BROADCAST
    );
    assert_eq!(
        serde_json::from_str::<Port>("7").unwrap(),
        Port::new(7).unwrap()
    );
}

/// Regression: the derived impls accepted any u16/u8, and a node ID above 12 bits then spilled into
/// the kind field of the identifier.
#[test]
fn out_of_range_values_are_refused() {
    let e = serde_json::from_str::<NodeId>("4096")
        .unwrap_err()
        .to_string();
    assert!(e.contains("12-bit node ID"), "{e}");
    let e = serde_json::from_str::<Port>("8").unwrap_err().to_string();
    assert!(e.contains("dock port"), "{e}");
    assert!(serde_json::from_str::<NodeId>("-1").is_err());
    assert!(serde_json::from_str::<NodeId>("\"111\"").is_err());
}

/// Wire enumerations travel as their event text, unknown values included.
#[test]
fn enumerations_serialise_as_their_text() {
    assert_eq!(
        serde_json::to_string(&ResetReason::Watchdog).unwrap(),
        "\"watchdog\""
    );
    assert_eq!(
        serde_json::to_string(&ResetReason::Other(42)).unwrap(),
        "\"other_42\""
    );
    assert_eq!(
        serde_json::from_str::<ResetReason>("\"other_42\"").unwrap(),
        ResetReason::Other(42)
    );
    assert_eq!(
        serde_json::from_str::<ResetReason>("\"pin\"").unwrap(),
        ResetReason::Pin
    );
    let e = serde_json::from_str::<ResetReason>("\"reboot\"")
        .unwrap_err()
        .to_string();
    assert!(e.contains("ResetReason name or other_<0-255>"), "{e}");
    assert!(serde_json::from_str::<ResetReason>("3").is_err());
}
