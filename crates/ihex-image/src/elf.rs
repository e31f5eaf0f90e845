//! A firmware ELF as the flat binary a slot holds (`std`): its loadable segments placed at their
//! load (physical) addresses — initialised data sits in flash after the code — from the slot's load
//! address on, gaps filled with `0xFF` like erased flash. Also reads the firmware's [`FwInfo`].

use object::read::elf::{ElfFile32, FileHeader, ProgramHeader};
use object::{Endianness, Object, ObjectSection, ObjectSymbol, SymbolSection};

use crate::header::FwInfo;

const PT_LOAD: u32 = 1;

/// Why an ELF cannot become a slot's payload.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ElfError {
    /// Not a 32-bit ELF file.
    #[error("not a 32-bit ELF file: {0}")]
    Parse(String),
    /// No loadable segment with content.
    #[error("no loadable segment with content")]
    Empty,
    /// The first byte is not at the load address: the ELF is linked for another slot (or no slot).
    #[error("linked at {lowest:#010x}, the slot runs code at {base:#010x} (build the firmware for this layout)")]
    NotAtBase {
        /// The lowest load address in the file.
        lowest: u32,
        /// The slot's load address.
        base: u32,
    },
    /// A segment lies (partly) outside the slot.
    #[error(
        "segment at {addr:#010x} ({len} bytes) lies outside the slot {base:#010x}..{end:#010x}"
    )]
    OutOfSlot {
        /// Segment load address.
        addr: u32,
        /// Segment bytes.
        len: u32,
        /// Slot load address.
        base: u32,
        /// One past the slot's last byte.
        end: u32,
    },
    /// Two segments claim the same bytes.
    #[error("segments overlap at {0:#010x}")]
    Overlap(u32),
}

/// The payload of a slot, as flattened from an ELF.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Flat {
    /// Address of the first byte.
    pub base: u32,
    /// The bytes.
    pub bytes: Vec<u8>,
}

fn parse(elf: &[u8]) -> Result<ElfFile32<'_, Endianness>, ElfError> {
    ElfFile32::<Endianness>::parse(elf).map_err(|e| ElfError::Parse(e.to_string()))
}

/// The firmware's identity record ([`FwInfo`], symbol `IHEX_FW_INFO`), `None` if the ELF has none
/// (or a malformed one).
pub fn fw_info(elf: &[u8]) -> Result<Option<FwInfo>, ElfError> {
    let file = parse(elf)?;
    let Some(sym) = file.symbols().find(|s| s.name() == Ok(FwInfo::SYMBOL)) else {
        return Ok(None);
    };
    let SymbolSection::Section(index) = sym.section() else {
        return Ok(None);
    };
    let bytes = file
        .section_by_index(index)
        .and_then(|sec| sec.data_range(sym.address(), FwInfo::LEN as u64))
        .map_err(|e| ElfError::Parse(e.to_string()))?;
    Ok(bytes.and_then(FwInfo::parse))
}

/// Flattens `elf` into a payload starting at `base` of at most `max_len` bytes.
pub fn flatten(elf: &[u8], base: u32, max_len: u32) -> Result<Flat, ElfError> {
    let file = parse(elf)?;
    let endian = file.endian();
    let headers = file
        .elf_header()
        .program_headers(endian, elf)
        .map_err(|e| ElfError::Parse(e.to_string()))?;
    let end = base.saturating_add(max_len);
    let mut segments = Vec::new();
    for ph in headers {
        if ph.p_type(endian) != PT_LOAD || ph.p_filesz(endian) == 0 {
            continue;
        }
        let addr = ph.p_paddr(endian);
        let data = ph
            .data(endian, elf)
            .map_err(|()| ElfError::Parse(format!("segment at {addr:#010x} is truncated")))?;
        let len = data.len() as u32;
        if addr < base || addr.checked_add(len).is_none_or(|e| e > end) {
            return Err(ElfError::OutOfSlot {
                addr,
                len,
                base,
                end,
            });
        }
        segments.push((addr, data));
    }
    segments.sort_by_key(|(a, _)| *a);
    let lowest = segments.first().ok_or(ElfError::Empty)?.0;
    if lowest != base {
        return Err(ElfError::NotAtBase { lowest, base });
    }
    let mut bytes: Vec<u8> = Vec::new();
    for (addr, data) in &segments {
        let off = (addr - base) as usize;
        if off < bytes.len() {
            return Err(ElfError::Overlap(*addr));
        }
        bytes.resize(off, 0xFF);
        bytes.extend_from_slice(data);
    }
    Ok(Flat { base, bytes })
}
