//! Boards an image can be built for, and each board's flash layout — the one place the partition
//! addresses are written: the firmware's and the bootloader's linker scripts are generated from
//! [`Layout`], the node checks an image's load address and size against it, the packer links
//! against it, the simulator lays out its in-memory flash with it.
//!
//! The STM32F303RE (512 KiB, 2 KiB pages, 8-byte write unit as embassy-stm32 programs it):
//!
//! | region       | start        | size    | what |
//! |--------------|--------------|--------:|------|
//! | `bootloader` | `0x0800_0000`|  24 KiB | embassy-boot bootloader (reset vector) |
//! | `state`      | `0x0800_6000`|   4 KiB | embassy-boot state: swap magic and progress |
//! | `active`     | `0x0800_7000`| 128 KiB | running image: header block, then the app at `0x0800_7200` |
//! | `dfu`        | `0x0802_7000`| 130 KiB | incoming image (one page more than `active`, for the swap) |
//! | free         | `0x0804_7800`| 224 KiB | unused: room to grow the slots (a layout change needs a probe) |
//! | `config`     | `0x0807_F800`|   2 KiB | node configuration record (node ID), outside every partition |
//!
//! RAM: the 64 KiB SRAM at `0x2000_0000` (the 16 KiB CCM RAM is not used).

use core::fmt;
use core::str::FromStr;

use crate::header::{HEADER_BLOCK, SIGNED_LEN};

/// A board an image is built for (header field `board`). Unknown values are kept as they are.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Board(pub u16);

impl Board {
    /// The sub-controller: NUCLEO-F303RE (STM32F303RETx) with an MCP2551 transceiver.
    pub const NUCLEO_F303RE: Board = Board(0x0001);
    /// A simulated sub-controller (`sim-node`); its layout mirrors the F303RE's.
    pub const SIM: Board = Board(0x0100);
    /// Every board this version knows, with its name.
    pub const KNOWN: &'static [(Board, &'static str)] =
        &[(Board::NUCLEO_F303RE, "nucleo-f303re"), (Board::SIM, "sim")];

    /// The board's name (`nucleo-f303re`, `sim`), `None` if unknown.
    pub fn name(self) -> Option<&'static str> {
        Board::KNOWN
            .iter()
            .find(|(b, _)| *b == self)
            .map(|(_, n)| *n)
    }

    /// The board's flash layout, `None` if unknown.
    pub const fn layout(self) -> Option<&'static Layout> {
        match self {
            Board::NUCLEO_F303RE | Board::SIM => Some(&F303RE),
            _ => None,
        }
    }
}

impl fmt::Display for Board {
    /// The name, or `0x` and four hex digits for a board this version does not know.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(n) => f.write_str(n),
            None => write!(f, "{:#06x}", self.0),
        }
    }
}

/// Why a text is not a [`Board`].
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct BoardParseError;

impl fmt::Display for BoardParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("expected a board name (nucleo-f303re, sim) or a number like 0x0001")
    }
}

impl core::error::Error for BoardParseError {}

impl FromStr for Board {
    type Err = BoardParseError;

    /// A known name, or a number (`0x` hex or decimal).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if let Some((b, _)) = Board::KNOWN.iter().find(|(_, n)| n.eq_ignore_ascii_case(s)) {
            return Ok(*b);
        }
        let n = match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
            Some(h) => u16::from_str_radix(h, 16),
            None => s.parse(),
        };
        n.map(Board).map_err(|_| BoardParseError)
    }
}

/// A range of flash addresses.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Region {
    /// First address.
    pub start: u32,
    /// Length in bytes.
    pub len: u32,
}

impl Region {
    /// One past the last address.
    pub const fn end(&self) -> u32 {
        self.start + self.len
    }

    /// True if the two regions share an address.
    pub const fn overlaps(&self, other: &Region) -> bool {
        self.start < other.end() && other.start < self.end()
    }

    /// True if `other` lies inside this region.
    pub const fn contains(&self, other: &Region) -> bool {
        other.start >= self.start && other.end() <= self.end()
    }
}

/// A board's flash: geometry and partitions (see the module docs for the F303RE).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Layout {
    /// The whole flash.
    pub flash: Region,
    /// Erase unit.
    pub page: u32,
    /// Program unit (embassy's `NorFlash::WRITE_SIZE`).
    pub write_unit: u32,
    /// The bootloader (starts at the reset vector).
    pub bootloader: Region,
    /// The bootloader's state partition.
    pub state: Region,
    /// The running image.
    pub active: Region,
    /// The incoming image.
    pub dfu: Region,
    /// The node configuration record.
    pub config: Region,
    /// The RAM the firmware and the bootloader use (each on its own: only one runs at a time).
    pub ram: Region,
}

const KIB: u32 = 1024;

/// Bytes at the top of RAM kept across a system reset ([`Layout::kept_ram`]).
pub const KEPT_RAM_LEN: u32 = 64;

/// The STM32F303RE layout (module docs).
pub const F303RE: Layout = Layout {
    flash: Region {
        start: 0x0800_0000,
        len: 512 * KIB,
    },
    page: 2 * KIB,
    write_unit: 8,
    bootloader: Region {
        start: 0x0800_0000,
        len: 24 * KIB,
    },
    state: Region {
        start: 0x0800_6000,
        len: 4 * KIB,
    },
    active: Region {
        start: 0x0800_7000,
        len: 128 * KIB,
    },
    dfu: Region {
        start: 0x0802_7000,
        len: 130 * KIB,
    },
    config: Region {
        start: 0x0807_F800,
        len: 2 * KIB,
    },
    // SRAM; the 16 KiB CCM RAM is not used.
    ram: Region {
        start: 0x2000_0000,
        len: 64 * KIB,
    },
};

impl Layout {
    /// Where the payload (the application's vector table) runs: the active slot + [`HEADER_BLOCK`].
    pub const fn app_start(&self) -> u32 {
        self.active.start + HEADER_BLOCK as u32
    }

    /// The top [`KEPT_RAM_LEN`] bytes of RAM, outside both programs' `.data`/`.bss`/stack, so neither
    /// start-up clears them: the application leaves a block there before a reset it asks for and
    /// the bootloader and the next application read it (SRAM keeps its content through a system
    /// reset, not through a power cut). Both linker scripts place it at this same address.
    pub const fn kept_ram(&self) -> Region {
        Region {
            start: self.ram.end() - KEPT_RAM_LEN,
            len: KEPT_RAM_LEN,
        }
    }

    /// The RAM each program links into: [`Layout::ram`] without [`Layout::kept_ram`].
    pub const fn program_ram(&self) -> Region {
        Region {
            start: self.ram.start,
            len: self.ram.len - KEPT_RAM_LEN,
        }
    }

    /// The largest image (header block + payload) a slot takes.
    pub const fn max_image_len(&self) -> u32 {
        self.active.len
    }

    /// The largest payload.
    pub const fn max_payload_len(&self) -> u32 {
        self.active.len - HEADER_BLOCK as u32
    }

    /// Checks what the bootloader and the update logic rely on: page alignment, every region
    /// inside the flash and apart from the others, the bootloader at the reset vector, DFU at
    /// least one page larger than ACTIVE, a state partition large enough for embassy-boot's
    /// progress index (`(2 + 4 × active pages) × write unit`), a header block that holds the
    /// signed header and keeps the write unit.
    pub const fn check(&self) -> Result<(), &'static str> {
        let parts = [
            self.bootloader,
            self.state,
            self.active,
            self.dfu,
            self.config,
        ];
        let mut i = 0;
        while i < parts.len() {
            let r = parts[i];
            if r.len == 0 || !r.start.is_multiple_of(self.page) || !r.len.is_multiple_of(self.page)
            {
                return Err("every region must be a non-empty whole number of pages, page-aligned");
            }
            if !self.flash.contains(&r) {
                return Err("every region must lie inside the flash");
            }
            let mut j = i + 1;
            while j < parts.len() {
                if r.overlaps(&parts[j]) {
                    return Err("regions overlap");
                }
                j += 1;
            }
            i += 1;
        }
        if self.bootloader.start != self.flash.start {
            return Err("the bootloader must start at the reset vector (flash start)");
        }
        if self.dfu.len < self.active.len + self.page {
            return Err("DFU must be at least one page larger than ACTIVE");
        }
        if (2 + 4 * (self.active.len / self.page)) * self.write_unit > self.state.len {
            return Err("the state partition is too small for the swap progress index");
        }
        if !(HEADER_BLOCK as u32).is_multiple_of(self.write_unit) || HEADER_BLOCK < SIGNED_LEN {
            return Err("the header block must hold the signed header and keep the write unit");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kept_ram_is_the_top_of_sram_outside_program_ram() {
        let (kept, prog) = (F303RE.kept_ram(), F303RE.program_ram());
        assert_eq!((kept.start, kept.len), (0x2000_FFC0, 64));
        assert!(F303RE.ram.contains(&kept) && F303RE.ram.contains(&prog));
        assert!(!kept.overlaps(&prog));
        assert_eq!(prog.end(), kept.start);
    }

    #[test]
    fn the_f303re_layout_holds() {
        assert_eq!(F303RE.check(), Ok(()));
        assert_eq!(F303RE.app_start(), 0x0800_7200);
        // The config page is the chip's last page, where the firmware has always kept it.
        assert_eq!(F303RE.config.end(), F303RE.flash.end());
    }

    #[test]
    fn broken_layouts_are_caught() {
        let mut l = F303RE;
        l.dfu.len = l.active.len;
        assert!(l.check().is_err());
        let mut l = F303RE;
        l.state.len = 2 * KIB;
        assert!(l.check().unwrap_err().contains("state"));
        let mut l = F303RE;
        l.config.start = l.dfu.start;
        assert!(l.check().unwrap_err().contains("overlap"));
        let mut l = F303RE;
        l.active.start += 512;
        assert!(l.check().is_err());
    }

    #[test]
    fn board_names_and_numbers() {
        assert_eq!("nucleo-f303re".parse(), Ok(Board::NUCLEO_F303RE));
        assert_eq!("SIM".parse(), Ok(Board::SIM));
        assert_eq!("0x0007".parse(), Ok(Board(7)));
        assert_eq!("300".parse(), Ok(Board(300)));
        assert!("nucleo".parse::<Board>().is_err());
        assert_eq!(Board(0x0042).to_string(), "0x0042");
        assert_eq!(Board::NUCLEO_F303RE.to_string(), "nucleo-f303re");
    }
}
