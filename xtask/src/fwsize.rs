//! Flash and static RAM use of the firmware ELFs, from their section headers, against the budget.
//!
//! Flash = text + rodata + data (initialised data is stored in flash and copied at boot);
//! static RAM = data + bss. Non-allocated sections (debug info, defmt strings) cost nothing.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use object::{Object, ObjectKind, ObjectSection, SectionFlags, SectionKind};

/// Flash budget of one firmware image, in bytes.
pub const FLASH_BUDGET: u64 = 64 * 1024;
/// Static RAM budget of one firmware image, in bytes.
pub const RAM_BUDGET: u64 = 16 * 1024;

const SHF_WRITE: u64 = 0x1;
const SHF_ALLOC: u64 = 0x2;
const SHF_EXECINSTR: u64 = 0x4;

/// Section totals of one ELF, in bytes.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Sizes {
    /// Executable code.
    pub text: u64,
    /// Read-only data (vector table, constants).
    pub rodata: u64,
    /// Initialised writable data.
    pub data: u64,
    /// Zero-initialised or uninitialised writable data.
    pub bss: u64,
}

impl Sizes {
    /// Bytes stored in flash.
    pub fn flash(&self) -> u64 {
        self.text + self.rodata + self.data
    }

    /// Bytes of RAM reserved before the stack.
    pub fn ram(&self) -> u64 {
        self.data + self.bss
    }
}

/// Totals of an ELF's allocated sections; `None` when the file is not an executable ELF.
pub fn sizes(bytes: &[u8]) -> Result<Option<Sizes>> {
    let file = object::File::parse(bytes).context("parsing ELF")?;
    if file.kind() != ObjectKind::Executable {
        return Ok(None);
    }
    let mut s = Sizes::default();
    for sec in file.sections() {
        let SectionFlags::Elf { sh_flags } = sec.flags() else {
            continue;
        };
        if sh_flags & SHF_ALLOC == 0 {
            continue;
        }
        let size = sec.size();
        let nobits = matches!(
            sec.kind(),
            SectionKind::UninitializedData | SectionKind::UninitializedTls | SectionKind::Common
        );
        match (
            sh_flags & SHF_EXECINSTR != 0,
            sh_flags & SHF_WRITE != 0,
            nobits,
        ) {
            (true, _, _) => s.text += size,
            (false, true, true) => s.bss += size,
            (false, true, false) => s.data += size,
            (false, false, _) => s.rodata += size,
        }
    }
    Ok(Some(s))
}

/// The firmware ELFs (executables) in `dir`, sorted by name.
pub fn binaries(dir: &Path) -> Result<Vec<(PathBuf, Sizes)>> {
    let mut out = Vec::new();
    let entries = fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))?;
    for entry in entries {
        let path = entry?.path();
        if !path.is_file() {
            continue;
        }
        let bytes = fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        if !bytes.starts_with(b"\x7fELF") {
            continue;
        }
        if let Some(s) = sizes(&bytes).with_context(|| format!("in {}", path.display()))? {
            out.push((path, s));
        }
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(out)
}

fn pct(used: u64, budget: u64) -> f64 {
    used as f64 * 100.0 / budget as f64
}

/// Prints the table for the release firmware and fails when an image is over budget.
pub fn report(dir: &Path) -> Result<()> {
    let bins = binaries(dir)?;
    if bins.is_empty() {
        bail!(
            "no firmware ELF in {} (build it first: cd crates/sc-fw && cargo build --release)",
            dir.display()
        );
    }
    println!(
        "{:<20} {:>8} {:>8} {:>6} {:>6}  {:>22}  {:>22}",
        "binary", "text", "rodata", "data", "bss", "flash", "static RAM"
    );
    let mut over = Vec::new();
    for (path, s) in &bins {
        let name = path.file_name().unwrap_or_default().to_string_lossy();
        println!(
            "{:<20} {:>8} {:>8} {:>6} {:>6}  {:>7}/{} ({:>5.1} %)  {:>7}/{} ({:>5.1} %)",
            name,
            s.text,
            s.rodata,
            s.data,
            s.bss,
            s.flash(),
            FLASH_BUDGET,
            pct(s.flash(), FLASH_BUDGET),
            s.ram(),
            RAM_BUDGET,
            pct(s.ram(), RAM_BUDGET)
        );
        if s.flash() > FLASH_BUDGET {
            over.push(format!(
                "{name}: flash {} B > {} B",
                s.flash(),
                FLASH_BUDGET
            ));
        }
        if s.ram() > RAM_BUDGET {
            over.push(format!(
                "{name}: static RAM {} B > {} B",
                s.ram(),
                RAM_BUDGET
            ));
        }
    }
    if !over.is_empty() {
        bail!("firmware over budget: {}", over.join("; "));
    }
    Ok(())
}
