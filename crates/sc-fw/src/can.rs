//! bxCAN set-up from the protocol crate: bit timing, acceptance filters (with register read-back),
//! frame conversion and the error counters.

use core::num::{NonZeroU16, NonZeroU8};

use defmt::{error, info};
use embassy_stm32::can::filter::{BankConfig, ListEntry32, Mask32, MasterFilters};
use embassy_stm32::can::util::NominalBitTiming;
use embassy_stm32::can::{ExtendedId, Fifo, Frame, StandardId};
use embassy_stm32::pac::CAN;
use embedded_can::Frame as _;
use ihex_proto::filter::{sc_filters, to_bxcan, BxcanBank, FilterError, BXCAN_BANKS};
use ihex_proto::timing::{BitTiming, TimingError};
use ihex_proto::{NodeId, BITRATE};

use crate::bank::{self, BankError, BankPlan};
use crate::board::APB1_HZ;
use crate::event::{CanStatus, RxFrame};

/// The timing fields of `CAN_BTR` (BRP, TS1, TS2, SJW).
const BTR_TIMING_MASK: u32 = 0x037F_03FF;

/// The island's bit timing for this board's APB1 clock. embassy's own `set_bitrate` would choose
/// prescaler 6 and 1+10+1 quanta (91.7 % sample point) at 36 MHz; the protocol's table is prescaler 9,
/// 1+6+1 (87.5 %), which is what every node on the bus must use, so the timing is set explicitly.
pub const fn bit_timing() -> Result<BitTiming, TimingError> {
    BitTiming::compute(APB1_HZ, BITRATE)
}

/// The protocol timing as embassy's timing struct; `None` when a field is out of embassy's range.
pub fn nominal(t: &BitTiming) -> Option<NominalBitTiming> {
    Some(NominalBitTiming {
        prescaler: NonZeroU16::new(t.prescaler)?,
        seg1: NonZeroU8::new(t.bs1)?,
        seg2: NonZeroU8::new(t.bs2)?,
        sync_jump_width: NonZeroU8::new(t.sjw)?,
    })
}

/// True when the controller's `CAN_BTR` holds exactly the timing of `t`.
pub fn verify_bit_timing(t: &BitTiming) -> bool {
    let btr = CAN.btr().read().0 & BTR_TIMING_MASK;
    if btr != t.btr() {
        error!(
            "CAN_BTR timing {=u32:#010x}, expected {=u32:#010x}",
            btr,
            t.btr()
        );
        return false;
    }
    true
}

/// Why filters could not be installed.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub enum FilterSetupError {
    /// The protocol filters have no bxCAN form.
    Protocol(FilterError),
    /// embassy's constructors cannot express a bank.
    Bank(BankError),
    /// A constructor argument was out of range.
    Id,
}

fn bank_config(p: &BankPlan) -> Result<BankConfig, FilterSetupError> {
    let rtr = |m: &mut Mask32, rtr: Option<bool>| match rtr {
        Some(false) => {
            m.data_frames_only();
        }
        Some(true) => {
            m.remote_frames_only();
        }
        None => {}
    };
    Ok(match *p {
        BankPlan::ExtMask { id, mask, rtr: r } => {
            let mut m = Mask32::frames_with_ext_id(
                ExtendedId::new(id).ok_or(FilterSetupError::Id)?,
                ExtendedId::new(mask).ok_or(FilterSetupError::Id)?,
            );
            rtr(&mut m, r);
            m.into()
        }
        BankPlan::StdMask { id, mask, rtr: r } => {
            let mut m = Mask32::frames_with_std_id(
                StandardId::new(id).ok_or(FilterSetupError::Id)?,
                StandardId::new(mask).ok_or(FilterSetupError::Id)?,
            );
            rtr(&mut m, r);
            m.into()
        }
        BankPlan::List(entries) => {
            let mut out = [ListEntry32::data_frames_with_id(StandardId::ZERO); 2];
            for (o, e) in out.iter_mut().zip(entries) {
                let id: embedded_can::Id = if e.extended {
                    ExtendedId::new(e.id).ok_or(FilterSetupError::Id)?.into()
                } else {
                    StandardId::new(e.id as u16)
                        .ok_or(FilterSetupError::Id)?
                        .into()
                };
                *o = if e.remote {
                    ListEntry32::remote_frames_with_id(id)
                } else {
                    ListEntry32::data_frames_with_id(id)
                };
            }
            out.into()
        }
    })
}

/// The protocol's bxCAN banks for a node (`None` = unconfigured).
pub fn banks_for(
    own: Option<NodeId>,
) -> Result<heapless::Vec<BxcanBank, BXCAN_BANKS>, FilterSetupError> {
    to_bxcan(&sc_filters(own)).map_err(FilterSetupError::Protocol)
}

/// Installs `banks` (all into FIFO 0), disabling every other bank. Returns the number installed.
pub fn apply_filters(
    filters: &mut MasterFilters<'_>,
    banks: &[BxcanBank],
) -> Result<usize, FilterSetupError> {
    // Build every config first so a bad bank leaves the previous filters untouched.
    let mut configs: heapless::Vec<BankConfig, BXCAN_BANKS> = heapless::Vec::new();
    for b in banks {
        let plan = bank::plan(b).map_err(FilterSetupError::Bank)?;
        let _ = configs.push(bank_config(&plan)?);
    }
    filters.clear();
    for (i, c) in configs.into_iter().enumerate() {
        filters.enable_bank(i as u8, Fifo::Fifo0, c);
    }
    Ok(banks.len())
}

/// Reads the filter bank registers back and compares them with the protocol's values: proves that
/// the embassy constructors produced the register layout `ihex_proto::filter` specifies.
pub fn verify_filters(banks: &[BxcanBank]) -> bool {
    let mut ok = true;
    for (i, b) in banks.iter().enumerate() {
        let fb = CAN.fb(i);
        let got = (fb.fr1().read().0, fb.fr2().read().0);
        let want = bank::bank_registers(b);
        if got != want {
            error!("filter bank {}: FR1/FR2 {=u32:#010x}/{=u32:#010x}, expected {=u32:#010x}/{=u32:#010x}", i, got.0, got.1, want.0, want.1);
            ok = false;
        }
    }
    let active = CAN.fa1r().read().0 & ((1 << BXCAN_BANKS) - 1);
    if active != (1u32 << banks.len()) - 1 {
        error!(
            "filter banks active {=u32:#b}, expected the first {}",
            active,
            banks.len()
        );
        ok = false;
    }
    if ok {
        info!("CAN filters verified: {} bank(s)", banks.len());
    }
    ok
}

/// A received frame in the core's terms.
pub fn rx_frame(f: &Frame) -> RxFrame {
    let (raw_id, extended) = match f.id() {
        embedded_can::Id::Standard(s) => (s.as_raw() as u32, false),
        embedded_can::Id::Extended(e) => (e.as_raw(), true),
    };
    let d = f.data();
    let mut data = [0u8; 8];
    let len = d.len().min(8);
    data[..len].copy_from_slice(&d[..len]);
    RxFrame {
        raw_id,
        extended,
        remote: f.is_remote_frame(),
        len: len as u8,
        data,
    }
}

/// The controller's error counters and bus-off flag.
pub fn status() -> CanStatus {
    let esr = CAN.esr().read();
    CanStatus {
        tec: esr.tec(),
        rec: esr.rec(),
        bus_off: esr.boff(),
    }
}
