//! Test support shared by the integration tests and the fuzz target: a minimal
//! `embedded_can::Frame`, standing in for socketcan's and embassy's frame types.
#![allow(dead_code)]

use embedded_can::{Frame, Id};

/// A classic CAN frame: an ID, the remote flag and up to 8 data bytes.
#[derive(Clone, Debug, PartialEq)]
pub struct TestFrame {
    id: Id,
    remote: bool,
    dlc: usize,
    data: [u8; 8],
}

impl Frame for TestFrame {
    fn new(id: impl Into<Id>, data: &[u8]) -> Option<Self> {
        if data.len() > 8 {
            return None;
        }
        let mut d = [0; 8];
        d[..data.len()].copy_from_slice(data);
        Some(TestFrame {
            id: id.into(),
            remote: false,
            dlc: data.len(),
            data: d,
        })
    }

    fn new_remote(id: impl Into<Id>, dlc: usize) -> Option<Self> {
        (dlc <= 8).then(|| TestFrame {
            id: id.into(),
            remote: true,
            dlc,
            data: [0; 8],
        })
    }

    fn is_extended(&self) -> bool {
        matches!(self.id, Id::Extended(_))
    }

    fn is_remote_frame(&self) -> bool {
        self.remote
    }

    fn id(&self) -> Id {
        self.id
    }

    fn dlc(&self) -> usize {
        self.dlc
    }

    fn data(&self) -> &[u8] {
        if self.remote {
            &[]
        } else {
            &self.data[..self.dlc]
        }
    }
}
