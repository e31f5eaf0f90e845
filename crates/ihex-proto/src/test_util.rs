//! Test support (feature `test-util`): node IDs and ports from literals, for the tests of every
//! crate, written once. A literal that is no valid ID panics naming it: a mistake in the test,
//! never input from outside. Not for product code: there, [`NodeId::new`] and [`Port::new`] make
//! the caller handle an invalid value.

use crate::{NodeId, Port};

/// The node ID `raw` (any valid ID, `NodeId::BROADCAST` included); panics when invalid.
#[track_caller]
pub const fn id(raw: u16) -> NodeId {
    match NodeId::new(raw) {
        Some(id) => id,
        None => panic!("not a valid node ID"),
    }
}

/// The sub-controller ID `raw` (an ID a node may have: not broadcast, not reserved); panics when
/// invalid.
#[track_caller]
pub const fn sc_id(raw: u16) -> NodeId {
    match NodeId::new_sc(raw) {
        Some(id) => id,
        None => panic!("not a valid sub-controller ID"),
    }
}

/// The dock port `raw`; panics when invalid.
#[track_caller]
pub const fn port(raw: u8) -> Port {
    match Port::new(raw) {
        Some(p) => p,
        None => panic!("not a valid port"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn literals_become_ids_and_ports() {
        assert_eq!(id(0x111), NodeId::new(0x111).unwrap());
        assert_eq!(sc_id(2), NodeId::new_sc(2).unwrap());
        assert_eq!(port(3), Port::new(3).unwrap());
    }

    #[test]
    #[should_panic(expected = "not a valid sub-controller ID")]
    fn broadcast_is_no_sub_controller() {
        sc_id(0xFFF);
    }
}
