//! Acceptance filters with the seed's semantics (Rule 2.1), and their translation to SocketCAN kernel
//! filters and bxCAN filter banks.
//!
//! A filter compares a 32-bit *match word* built from a frame:
//!
//! | bits  | 31       | 30  | 29  | 28 – 0                      |
//! |-------|----------|-----|-----|-----------------------------|
//! | field | (unused) | RTR | EFF | identifier (11 or 29 bits)  |
//!
//! A frame matches a filter when `(word & mask) == (id & mask)`: every bit set in the mask must match,
//! the others are don't-care. An *ID filter* is a mask filter whose mask covers every bit
//! ([`WORD_MASK`]). Each filter either accepts or rejects; a set of filters lets a frame through when
//! it matches at least one accept filter (or there are none) and no reject filter.
//!
//! The seed's worked example: mask `0x20000111`, ID `0xA0000431` — `0x21353011` passes, `0x21353110`
//! fails on bits 0 and 8 (bit 31 of the filter ID lies outside every mask and so never matters).

use embedded_can::{Frame, Id};

use crate::{Header, NodeId};

/// Extended-frame bit of a match word.
pub const EFF: u32 = 1 << 29;
/// Remote-frame bit of a match word.
pub const RTR: u32 = 1 << 30;
/// Identifier bits of a match word.
pub const ID_MASK: u32 = 0x1FFF_FFFF;
/// Every bit a filter can compare.
pub const WORD_MASK: u32 = ID_MASK | EFF | RTR;

/// SocketCAN `CAN_EFF_FLAG`.
pub const CAN_EFF_FLAG: u32 = 0x8000_0000;
/// SocketCAN `CAN_RTR_FLAG`.
pub const CAN_RTR_FLAG: u32 = 0x4000_0000;
/// SocketCAN `CAN_INV_FILTER`, set in a filter's `can_id` to invert it.
pub const CAN_INV_FILTER: u32 = 0x2000_0000;
/// SocketCAN `CAN_ERR_FLAG`: the same bit as [`CAN_INV_FILTER`], but in a filter's `can_mask` it
/// turns the filter into an error-frame filter.
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// SocketCAN `CAN_SFF_MASK`: the bits of a standard identifier.
pub const CAN_SFF_MASK: u32 = 0x7FF;

/// Number of filter banks of the STM32F303's bxCAN.
pub const BXCAN_BANKS: usize = 14;

/// Largest number of kernel filters [`to_kernel`] produces.
pub const MAX_KERNEL_FILTERS: usize = 32;

/// What a matching frame does.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub enum Action {
    /// Let matching frames through.
    Accept,
    /// Drop matching frames.
    Reject,
}

/// One accept or reject filter over a match word.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct Filter {
    /// Accept or reject.
    pub action: Action,
    /// Match word to compare against (bits outside `mask` are ignored).
    pub id: u32,
    /// Bits that must match.
    pub mask: u32,
}

/// Why filters cannot be translated for a target.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FilterError {
    /// bxCAN banks can only accept.
    RejectUnsupported,
    /// A bxCAN filter must fix the EFF bit: standard and extended IDs sit in different register bits.
    EffNotFixed,
    /// A standard-ID filter compares identifier bits above bit 10 against ones, so it matches nothing.
    NeverMatches,
    /// More filters than the target has room for.
    TooMany,
}

impl core::fmt::Display for FilterError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            FilterError::RejectUnsupported => {
                "bxCAN filter banks cannot reject; apply reject filters in software"
            }
            FilterError::EffNotFixed => "bxCAN filters must include the EFF bit in the mask",
            FilterError::NeverMatches => {
                "standard-ID filter compares bits above bit 10 against ones"
            }
            FilterError::TooMany => "more filters than the target has room for",
        })
    }
}

impl core::error::Error for FilterError {}

/// The match word of an identifier and remote flag.
pub fn word(id: Id, remote: bool) -> u32 {
    let (raw, eff) = match id {
        Id::Standard(s) => (s.as_raw() as u32, 0),
        Id::Extended(e) => (e.as_raw(), EFF),
    };
    raw | eff | if remote { RTR } else { 0 }
}

/// The match word of a frame.
pub fn word_of<F: Frame>(frame: &F) -> u32 {
    word(frame.id(), frame.is_remote_frame())
}

impl Filter {
    /// Accepts frames whose match word has the bits of `mask` equal to those of `id`.
    pub const fn accept(id: u32, mask: u32) -> Self {
        Filter {
            action: Action::Accept,
            id,
            mask,
        }
    }

    /// Rejects frames whose match word has the bits of `mask` equal to those of `id`.
    pub const fn reject(id: u32, mask: u32) -> Self {
        Filter {
            action: Action::Reject,
            id,
            mask,
        }
    }

    /// Accepts exactly one match word (an ID filter).
    pub const fn accept_id(word: u32) -> Self {
        Self::accept(word, WORD_MASK)
    }

    /// Rejects exactly one match word (an ID filter).
    pub const fn reject_id(word: u32) -> Self {
        Self::reject(word, WORD_MASK)
    }

    /// True for an ID filter (every comparable bit must match).
    pub const fn is_id_filter(&self) -> bool {
        self.mask & WORD_MASK == WORD_MASK
    }

    /// True for a standard-frame filter (EFF compared and clear) that compares identifier bits above
    /// bit 10 against ones: no frame can match it.
    pub const fn never_matches(&self) -> bool {
        self.mask & EFF != 0 && self.id & EFF == 0 && (self.id & self.mask & ID_MASK & !0x7FF) != 0
    }

    /// True when the word's masked bits equal the filter's (whatever the action).
    pub const fn matches(&self, word: u32) -> bool {
        let m = self.mask & WORD_MASK;
        (word & m) == (self.id & m)
    }

    /// Accepts extended data frames whose destination field is `dest`, from any source and of any kind.
    pub const fn to_node(dest: NodeId) -> Self {
        let shift = Header::DEST_SHIFT;
        Self::accept(
            EFF | ((dest.get() as u32) << shift),
            EFF | RTR | (Header::NODE_MASK << shift),
        )
    }
}

impl Filter {
    /// Accepts extended data frames whose source field is `src`, to any destination and of any
    /// kind (with `CAN_RAW_RECV_OWN_MSGS`, the gateway hears its own frames back this way: the
    /// echo that confirms they were sent).
    pub const fn from_node(src: NodeId) -> Self {
        let shift = Header::SRC_SHIFT;
        Self::accept(
            EFF | ((src.get() as u32) << shift),
            EFF | RTR | (Header::NODE_MASK << shift),
        )
    }
}

/// The seed's rule for a set: through when it matches some accept filter (or there is none) and no
/// reject filter.
pub fn accepts(filters: &[Filter], word: u32) -> bool {
    let mut any_accept = false;
    let mut accepted = false;
    for f in filters {
        match f.action {
            Action::Reject if f.matches(word) => return false,
            Action::Reject => {}
            Action::Accept => {
                any_accept = true;
                accepted |= f.matches(word);
            }
        }
    }
    accepted || !any_accept
}

/// The filters of a sub-controller: frames addressed to it and broadcasts. An unconfigured node (`None`)
/// listens to broadcasts only (that is where node-ID assignment arrives). Two bxCAN banks at most.
pub fn sc_filters(own: Option<NodeId>) -> heapless::Vec<Filter, 2> {
    let mut v = heapless::Vec::new();
    let _ = v.push(Filter::to_node(NodeId::BROADCAST));
    if let Some(id) = own {
        let _ = v.push(Filter::to_node(id));
    }
    v
}

/// The gateway's filters: extended data frames addressed to it.
pub fn gateway_filters() -> [Filter; 1] {
    [Filter::to_node(NodeId::GATEWAY)]
}

/// One raw SocketCAN `struct can_filter` (`can_id` carries [`CAN_INV_FILTER`] when inverted).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct KernelFilter {
    /// `can_id` field.
    pub can_id: u32,
    /// `can_mask` field.
    pub can_mask: u32,
}

impl KernelFilter {
    /// True when the filter is inverted (a reject filter).
    pub const fn inverted(&self) -> bool {
        self.can_id & CAN_INV_FILTER != 0
    }

    /// The kernel's own matching rule for a data or remote frame's raw `can_id` (flags included), for
    /// tests and for software fall-back, as `can_rcv_list_find` and `can_rcv_filter` in Linux's
    /// `net/can/af_can.c` apply it: `((can_id ^ filter.can_id) & can_mask) == 0`, negated when inverted,
    /// where a filter whose mask has `CAN_EFF_FLAG` but whose `can_id` does not ("standard frames only")
    /// compares only the 11 standard bits and the flags, and a filter whose mask has `CAN_ERR_FLAG`
    /// only ever sees error frames.
    pub const fn kernel_matches(&self, frame_can_id: u32) -> bool {
        let mut mask = self.can_mask;
        if mask & CAN_ERR_FLAG != 0 {
            return false;
        }
        if mask & CAN_EFF_FLAG != 0 && self.can_id & CAN_EFF_FLAG == 0 {
            mask &= CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
        }
        let hit = ((frame_can_id ^ (self.can_id & !CAN_INV_FILTER)) & mask) == 0;
        hit != self.inverted()
    }
}

/// How to install a filter set on a SocketCAN socket.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct KernelPlan {
    /// `CAN_RAW_FILTER` entries. Empty means "receive nothing" (every accept filter of the set can
    /// never match): install it as an empty list, which the kernel takes as exactly that.
    pub filters: heapless::Vec<KernelFilter, MAX_KERNEL_FILTERS>,
    /// Set `CAN_RAW_JOIN_FILTERS` (a frame must match every entry instead of any).
    pub join: bool,
    /// The kernel cannot express the set exactly (several accepts *and* rejects): it lets through a
    /// superset and the caller must apply [`accepts`] in software as well.
    pub software_check: bool,
}

/// A match word in SocketCAN's `can_id` layout (flags in bits 31 and 30).
pub const fn kernel_bits(word: u32) -> u32 {
    (word & ID_MASK)
        | if word & EFF != 0 { CAN_EFF_FLAG } else { 0 }
        | if word & RTR != 0 { CAN_RTR_FLAG } else { 0 }
}

fn kernel_filter(f: &Filter, invert: bool) -> KernelFilter {
    let can_id = kernel_bits(f.id & f.mask) | if invert { CAN_INV_FILTER } else { 0 };
    KernelFilter {
        can_id,
        can_mask: kernel_bits(f.mask),
    }
}

/// Translates a filter set to kernel filters with exactly [`accepts`]'s semantics where the kernel can
/// express it: accepts alone are OR-ed, rejects become inverted filters joined with AND, one accept and
/// rejects are joined; several accepts with rejects install the accepts and ask for a software check.
///
/// Standard-frame filters that compare identifier bits above bit 10 against ones can never match
/// ([`accepts`]), but the kernel would ignore those bits and match: they are left out (a set whose
/// accept filters are all such gives an empty, receive-nothing plan).
pub fn to_kernel(filters: &[Filter]) -> Result<KernelPlan, FilterError> {
    let any_accept = filters.iter().any(|f| f.action == Action::Accept);
    let live = || filters.iter().filter(|f| !f.never_matches());
    let accepts_n = live().filter(|f| f.action == Action::Accept).count();
    let rejects_n = live().count() - accepts_n;
    let mut plan = KernelPlan {
        filters: heapless::Vec::new(),
        join: false,
        software_check: false,
    };
    let mut push = |k: KernelFilter| plan.filters.push(k).map_err(|_| FilterError::TooMany);
    if any_accept && accepts_n == 0 {
        // Accept filters exist but none can match: nothing passes, which is an empty kernel list.
    } else if accepts_n + rejects_n == 0 {
        // Zero kernel filters would receive nothing; an all-don't-care filter receives everything.
        push(KernelFilter {
            can_id: 0,
            can_mask: 0,
        })?;
    } else if rejects_n == 0 || accepts_n <= 1 {
        for f in live() {
            push(kernel_filter(f, f.action == Action::Reject))?;
        }
        plan.join = rejects_n > 0;
    } else {
        for f in live().filter(|f| f.action == Action::Accept) {
            push(kernel_filter(f, false))?;
        }
        plan.software_check = true;
    }
    Ok(plan)
}

/// One bxCAN 32-bit filter bank, as the values of its two `FxRy` registers.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BxcanBank {
    /// Identifier/mask mode.
    Mask32 {
        /// `FxR1`: identifier in `RIxR` layout.
        id: u32,
        /// `FxR2`: mask in `RIxR` layout.
        mask: u32,
    },
    /// Identifier-list mode: two exact identifiers.
    List32 {
        /// `FxR1`, `FxR2`.
        ids: [u32; 2],
    },
}

/// bxCAN `RIxR` IDE bit.
pub const BXCAN_IDE: u32 = 1 << 2;
/// bxCAN `RIxR` RTR bit.
pub const BXCAN_RTR: u32 = 1 << 1;

/// A match word in bxCAN's `RIxR` register layout (STID in 31:21 or EXID in 31:3, IDE, RTR).
pub const fn bxcan_bits(word: u32) -> u32 {
    let rtr = if word & RTR != 0 { BXCAN_RTR } else { 0 };
    if word & EFF != 0 {
        ((word & ID_MASK) << 3) | BXCAN_IDE | rtr
    } else {
        ((word & 0x7FF) << 21) | rtr
    }
}

impl BxcanBank {
    /// The hardware's rule for a received frame's `RIxR` value (bit 0, TXRQ, is ignored).
    pub const fn matches(&self, rixr: u32) -> bool {
        let r = rixr & !1;
        match *self {
            BxcanBank::Mask32 { id, mask } => (r & mask) == (id & mask),
            BxcanBank::List32 { ids } => r == ids[0] || r == ids[1],
        }
    }
}

fn bxcan_mask_bits(f: &Filter) -> Result<(u32, u32), FilterError> {
    if f.mask & EFF == 0 {
        return Err(FilterError::EffNotFixed);
    }
    if f.never_matches() {
        return Err(FilterError::NeverMatches);
    }
    // The IDE bit is always compared (the EFF bit is in the mask). The mask must be laid out like
    // the identifier it applies to: EXID bits for an extended filter, only the 11 STID bits for a
    // standard one (a standard frame has no EXID bits to compare).
    let id = bxcan_bits(f.id & f.mask);
    let mask_word = if f.id & EFF != 0 {
        f.mask
    } else {
        f.mask & !EFF
    };
    let mask = bxcan_bits(mask_word) | BXCAN_IDE;
    Ok((id, mask))
}

/// Translates accept filters into bxCAN banks: ID filters two to a list bank, mask filters one per mask
/// bank; an empty set becomes one bank that passes everything, as [`accepts`] does. Reject filters,
/// filters that leave EFF open, and more than [`BXCAN_BANKS`] banks are errors.
pub fn to_bxcan(filters: &[Filter]) -> Result<heapless::Vec<BxcanBank, BXCAN_BANKS>, FilterError> {
    let mut banks: heapless::Vec<BxcanBank, BXCAN_BANKS> = heapless::Vec::new();
    if filters.is_empty() {
        // No filter means "everything passes" ([`accepts`]), but bxCAN with no active bank
        // receives nothing: install one bank that compares no bit.
        let _ = banks.push(BxcanBank::Mask32 { id: 0, mask: 0 });
        return Ok(banks);
    }
    let mut pending_id: Option<u32> = None;
    for f in filters {
        if f.action == Action::Reject {
            return Err(FilterError::RejectUnsupported);
        }
        let (id, mask) = bxcan_mask_bits(f)?;
        if f.is_id_filter() {
            match pending_id.take() {
                Some(first) => banks
                    .push(BxcanBank::List32 { ids: [first, id] })
                    .map_err(|_| FilterError::TooMany)?,
                None => pending_id = Some(id),
            }
        } else {
            banks
                .push(BxcanBank::Mask32 { id, mask })
                .map_err(|_| FilterError::TooMany)?;
        }
    }
    if let Some(id) = pending_id {
        banks
            .push(BxcanBank::List32 { ids: [id, id] })
            .map_err(|_| FilterError::TooMany)?;
    }
    Ok(banks)
}
