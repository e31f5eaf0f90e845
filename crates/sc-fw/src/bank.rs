//! bxCAN filter banks from the protocol's register values, in the shape embassy's filter API takes.
//!
//! `ihex_proto::filter::to_bxcan` gives the exact `FxR1`/`FxR2` values a bank must hold. embassy-stm32
//! does not take raw register values: it builds them from an identifier and a mask (`Mask32`) or from
//! identifiers (`ListEntry32`). [`plan`] decomposes our values into those constructor arguments and
//! [`registers`] mirrors what embassy writes for them (`can/bxcan/filter.rs` of embassy-stm32 0.6), so
//! the round trip is checked on the host; on the board `crate::can::verify_filters` also reads the bank
//! registers back. Pure code, no HAL.

use ihex_proto::filter::{BxcanBank, BXCAN_IDE, BXCAN_RTR};

/// How to build one bank with embassy's constructors.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BankPlan {
    /// `Mask32::frames_with_ext_id(id, mask)`, then `data_frames_only()` (`rtr == Some(false)`) or
    /// `remote_frames_only()` (`Some(true)`).
    ExtMask {
        /// 29-bit identifier.
        id: u32,
        /// 29-bit mask.
        mask: u32,
        /// Required RTR value, `None` = either.
        rtr: Option<bool>,
    },
    /// `Mask32::frames_with_std_id(id, mask)`, RTR as for `ExtMask`.
    StdMask {
        /// 11-bit identifier.
        id: u16,
        /// 11-bit mask.
        mask: u16,
        /// Required RTR value, `None` = either.
        rtr: Option<bool>,
    },
    /// `[ListEntry32; 2]`, each `data_frames_with_id` or `remote_frames_with_id`.
    List([ListPlan; 2]),
}

/// One identifier of a list bank.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ListPlan {
    /// Extended (29-bit) or standard (11-bit) identifier.
    pub extended: bool,
    /// The identifier.
    pub id: u32,
    /// Remote frame.
    pub remote: bool,
}

/// A register value embassy's constructors cannot produce.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BankError {
    /// The mask does not compare the IDE bit (embassy always does).
    IdeNotMasked,
    /// Bits outside the identifier field are set (for a standard filter: EXID bits).
    StrayBits,
}

const EXT_SHIFT: u32 = 3;
const STD_SHIFT: u32 = 21;

fn rtr_of(id: u32, mask: u32) -> Option<bool> {
    (mask & BXCAN_RTR != 0).then_some(id & BXCAN_RTR != 0)
}

/// Decomposes one bank's register values into embassy constructor arguments.
pub fn plan(bank: &BxcanBank) -> Result<BankPlan, BankError> {
    match *bank {
        BxcanBank::Mask32 { id, mask } => {
            if mask & BXCAN_IDE == 0 {
                return Err(BankError::IdeNotMasked);
            }
            let rtr = rtr_of(id, mask);
            if (id | mask) & 1 != 0 {
                return Err(BankError::StrayBits);
            }
            if id & BXCAN_IDE != 0 {
                Ok(BankPlan::ExtMask {
                    id: id >> EXT_SHIFT,
                    mask: mask >> EXT_SHIFT,
                    rtr,
                })
            } else {
                let exid_bits = ((1u32 << STD_SHIFT) - 1) & !0b111;
                if (id | mask) & exid_bits != 0 {
                    return Err(BankError::StrayBits);
                }
                Ok(BankPlan::StdMask {
                    id: (id >> STD_SHIFT) as u16,
                    mask: (mask >> STD_SHIFT) as u16,
                    rtr,
                })
            }
        }
        BxcanBank::List32 { ids } => {
            let entry = |v: u32| -> Result<ListPlan, BankError> {
                if v & 1 != 0 {
                    return Err(BankError::StrayBits);
                }
                let remote = v & BXCAN_RTR != 0;
                if v & BXCAN_IDE != 0 {
                    Ok(ListPlan {
                        extended: true,
                        id: v >> EXT_SHIFT,
                        remote,
                    })
                } else if v & (((1u32 << STD_SHIFT) - 1) & !0b111) != 0 {
                    Err(BankError::StrayBits)
                } else {
                    Ok(ListPlan {
                        extended: false,
                        id: v >> STD_SHIFT,
                        remote,
                    })
                }
            };
            Ok(BankPlan::List([entry(ids[0])?, entry(ids[1])?]))
        }
    }
}

/// The `FxR1`/`FxR2` values embassy-stm32 0.6 writes for a plan (mirrors its `filter.rs`).
pub fn registers(plan: &BankPlan) -> (u32, u32) {
    let apply_rtr = |(mut id, mut mask): (u32, u32), rtr: Option<bool>| {
        match rtr {
            Some(false) => {
                id &= !BXCAN_RTR;
                mask |= BXCAN_RTR;
            }
            Some(true) => {
                id |= BXCAN_RTR;
                mask |= BXCAN_RTR;
            }
            None => {}
        }
        (id, mask)
    };
    match *plan {
        BankPlan::ExtMask { id, mask, rtr } => apply_rtr(
            (id << EXT_SHIFT | BXCAN_IDE, mask << EXT_SHIFT | BXCAN_IDE),
            rtr,
        ),
        BankPlan::StdMask { id, mask, rtr } => apply_rtr(
            (
                (id as u32) << STD_SHIFT,
                (mask as u32) << STD_SHIFT | BXCAN_IDE,
            ),
            rtr,
        ),
        BankPlan::List(entries) => {
            let reg = |e: ListPlan| {
                let base = if e.extended {
                    e.id << EXT_SHIFT | BXCAN_IDE
                } else {
                    e.id << STD_SHIFT
                };
                base | if e.remote { BXCAN_RTR } else { 0 }
            };
            (reg(entries[0]), reg(entries[1]))
        }
    }
}

/// The register pair a protocol bank stands for.
pub fn bank_registers(bank: &BxcanBank) -> (u32, u32) {
    match *bank {
        BxcanBank::Mask32 { id, mask } => (id, mask),
        BxcanBank::List32 { ids } => (ids[0], ids[1]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::filter::{sc_filters, to_bxcan, Filter, EFF, RTR, WORD_MASK};
    use ihex_proto::{Header, Kind, NodeId};

    fn round_trips(bank: &BxcanBank) {
        let p = plan(bank).expect("plannable");
        assert_eq!(
            registers(&p),
            bank_registers(bank),
            "bank {bank:?} plan {p:?}"
        );
    }

    #[test]
    fn sc_banks_round_trip_through_embassy_constructors_for_every_id() {
        for raw in 0x001..=0xFFD {
            let id = NodeId::new_sc(raw).unwrap();
            let banks = to_bxcan(&sc_filters(Some(id))).unwrap();
            assert_eq!(banks.len(), 2);
            for b in &banks {
                round_trips(b);
                assert!(matches!(
                    plan(b).unwrap(),
                    BankPlan::ExtMask {
                        rtr: Some(false),
                        ..
                    }
                ));
            }
        }
        let unconfigured = to_bxcan(&sc_filters(None)).unwrap();
        assert_eq!(unconfigured.len(), 1);
        round_trips(&unconfigured[0]);
    }

    #[test]
    fn planned_sc_banks_accept_exactly_own_and_broadcast_frames() {
        let own = NodeId::new_sc(0x111).unwrap();
        let banks = to_bxcan(&sc_filters(Some(own))).unwrap();
        let accepted = |dest: NodeId, remote: bool| {
            let h = Header {
                kind: Kind::LedSet,
                dest,
                src: NodeId::GATEWAY,
            };
            let rixr = (h.to_raw() << 3) | BXCAN_IDE | if remote { BXCAN_RTR } else { 0 };
            banks.iter().any(|b| {
                let (id, mask) = registers(&plan(b).unwrap());
                (rixr & mask) == (id & mask)
            })
        };
        assert!(accepted(own, false));
        assert!(accepted(NodeId::BROADCAST, false));
        assert!(!accepted(NodeId::new_sc(0x112).unwrap(), false));
        assert!(!accepted(NodeId::GATEWAY, false));
        assert!(!accepted(own, true), "remote frames must be filtered out");
    }

    #[test]
    fn list_and_standard_banks_round_trip() {
        let filters = [
            Filter::accept_id(EFF | 0x1234_5678),
            Filter::accept_id(EFF | RTR | 0x0ABC_DEF0),
            Filter::accept(0x123, WORD_MASK & !0xF),
            Filter::accept(RTR | 0x7FF, EFF | RTR | 0x7FF),
        ];
        for b in &to_bxcan(&filters).unwrap() {
            round_trips(b);
        }
    }

    #[test]
    fn values_embassy_cannot_express_are_refused() {
        assert_eq!(
            plan(&BxcanBank::Mask32 { id: 0, mask: 0 }),
            Err(BankError::IdeNotMasked)
        );
        assert_eq!(
            plan(&BxcanBank::Mask32 {
                id: 1 << 5,
                mask: BXCAN_IDE
            }),
            Err(BankError::StrayBits)
        );
        assert_eq!(
            plan(&BxcanBank::List32 { ids: [1, 0] }),
            Err(BankError::StrayBits)
        );
    }
}
