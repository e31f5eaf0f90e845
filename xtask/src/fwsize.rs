//! Flash and static RAM use of the firmware ELFs, from their section headers, against the budget.
//!
//! Flash = text + rodata + data (initialised data is stored in flash and copied at boot);
//! static RAM = data + bss. Non-allocated sections (debug info, defmt strings) cost nothing.
//! The bootloader must fit its 24 KiB partition; an application (the firmware, the loopback
//! self-test) has a 96 KiB goal inside its 128 KiB slot (`ihex_image::board::F303RE`), so that a
//! release can grow without a layout change (which needs a probe on every board).

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use object::{Object, ObjectKind, ObjectSection, SectionFlags, SectionKind};

/// Flash budget of an application image, in bytes.
pub const APP_FLASH_BUDGET: u64 = 96 * 1024;
/// Flash budget of the bootloader: its partition.
pub const BOOTLOADER_FLASH_BUDGET: u64 = 24 * 1024;
/// Static RAM budget of every image, in bytes.
pub const RAM_BUDGET: u64 = 16 * 1024;
/// The bootloader's binary name (everything else in the folder is an application).
pub const BOOTLOADER: &str = "ihex-sc-bootloader";

/// (flash, static RAM) budget of the binary called `name`.
pub fn budget(name: &str) -> (u64, u64) {
    if name == BOOTLOADER {
        (BOOTLOADER_FLASH_BUDGET, RAM_BUDGET)
    } else {
        (APP_FLASH_BUDGET, RAM_BUDGET)
    }
}

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

/// The application every update image is made from.
pub const APP: &str = "ihex-sc-fw";

/// Packs the release application in `dir` into an update image signed with the committed test key
/// (`ihex-sc-fw.img` next to it) and checks it as a node would: proves on the real ELF that the
/// packer finds its identity record and that it is linked at the slot's load address.
pub fn pack_check(dir: &Path) -> Result<()> {
    use ihex_image::{board::F303RE, pack_elf, verify_image, Board, PackOverrides, Policy};
    let elf_path = dir.join(APP);
    let elf = fs::read(&elf_path).with_context(|| format!("reading {}", elf_path.display()))?;
    let key = ihex_image::SigningKey::test_key();
    let image = pack_elf(&elf, PackOverrides::default(), &key)
        .with_context(|| format!("packing {}", elf_path.display()))?;
    let info = ihex_image::elf::fw_info(&elf)?.context("no IHEX_FW_INFO in the firmware")?;
    let policy = Policy::new(Board::NUCLEO_F303RE, &F303RE, info.protocol.0, info.version);
    let header = verify_image(&image, &key.public(), &policy).context("the packed image")?;
    let out = dir.join(format!("{APP}.img"));
    fs::write(&out, &image).with_context(|| format!("writing {}", out.display()))?;
    println!(
        "{APP}.img: version {}, {} bytes, sha512 {}..., test-key signed, verifies",
        header.version,
        image.len(),
        &header.payload_hash.to_string()[..16]
    );
    Ok(())
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
        let (flash_budget, ram_budget) = budget(&name);
        println!(
            "{:<20} {:>8} {:>8} {:>6} {:>6}  {:>7}/{} ({:>5.1} %)  {:>7}/{} ({:>5.1} %)",
            name,
            s.text,
            s.rodata,
            s.data,
            s.bss,
            s.flash(),
            flash_budget,
            pct(s.flash(), flash_budget),
            s.ram(),
            ram_budget,
            pct(s.ram(), ram_budget)
        );
        if s.flash() > flash_budget {
            over.push(format!(
                "{name}: flash {} B > {} B",
                s.flash(),
                flash_budget
            ));
        }
        if s.ram() > ram_budget {
            over.push(format!(
                "{name}: static RAM {} B > {} B",
                s.ram(),
                ram_budget
            ));
        }
    }
    if !over.is_empty() {
        bail!("firmware over budget: {}", over.join("; "));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const PROGBITS: u32 = 1;
    const STRTAB: u32 = 3;
    const NOBITS: u32 = 8;

    /// A minimal little-endian ELF32 ARM file with the given `(name, type, flags, size)` sections.
    fn elf(e_type: u16, sections: &[(&str, u32, u32, u32)]) -> Vec<u8> {
        let mut names = vec![0u8];
        let mut name_off = Vec::new();
        for (n, ..) in sections {
            name_off.push(names.len() as u32);
            names.extend_from_slice(n.as_bytes());
            names.push(0);
        }
        let shstrtab_name = names.len() as u32;
        names.extend_from_slice(b".shstrtab\0");
        // Contents follow the 52-byte header; NOBITS sections take no file space.
        let mut body = Vec::new();
        let mut offsets = Vec::new();
        for (_, ty, _, size) in sections {
            offsets.push(52 + body.len() as u32);
            if *ty != NOBITS {
                body.resize(body.len() + *size as usize, 0);
            }
        }
        let names_off = 52 + body.len() as u32;
        body.extend_from_slice(&names);
        while body.len() % 4 != 0 {
            body.push(0);
        }
        let shoff = 52 + body.len() as u32;
        let shnum = sections.len() as u16 + 2;
        let mut f = vec![0x7f, b'E', b'L', b'F', 1, 1, 1];
        f.resize(16, 0);
        for v in [e_type, 40] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        for v in [1u32, 0x0800_0000, 0, shoff, 0] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        for v in [52u16, 32, 0, 40, shnum, shnum - 1] {
            f.extend_from_slice(&v.to_le_bytes());
        }
        f.extend_from_slice(&body);
        let mut sh = |words: [u32; 10]| {
            words
                .iter()
                .for_each(|w| f.extend_from_slice(&w.to_le_bytes()))
        };
        sh([0; 10]);
        for (i, (_, ty, flags, size)) in sections.iter().enumerate() {
            sh([name_off[i], *ty, *flags, 0, offsets[i], *size, 0, 0, 4, 0]);
        }
        sh([
            shstrtab_name,
            STRTAB,
            0,
            0,
            names_off,
            names.len() as u32,
            0,
            0,
            1,
            0,
        ]);
        f
    }

    fn firmware(text: u32, bss: u32) -> Vec<u8> {
        let ax = (SHF_ALLOC | SHF_EXECINSTR) as u32;
        let wa = (SHF_ALLOC | SHF_WRITE) as u32;
        elf(
            2,
            &[
                (".vector_table", PROGBITS, SHF_ALLOC as u32, 404),
                (".text", PROGBITS, ax, text),
                (".rodata", PROGBITS, SHF_ALLOC as u32, 100),
                (".data", PROGBITS, wa, 24),
                (".bss", NOBITS, wa, bss),
                (".uninit", NOBITS, wa, 1024),
                (".defmt", PROGBITS, 0, 77),
                (".debug_info", PROGBITS, 0, 999),
            ],
        )
    }

    #[test]
    fn sections_are_summed_by_flags() {
        let s = sizes(&firmware(1000, 300)).unwrap().expect("an executable");
        assert_eq!(
            s,
            Sizes {
                text: 1000,
                rodata: 504,
                data: 24,
                bss: 1324
            }
        );
        assert_eq!(s.flash(), 1528);
        assert_eq!(s.ram(), 1348);
    }

    #[test]
    fn relocatable_objects_are_not_firmware() {
        assert_eq!(sizes(&elf(1, &[(".text", PROGBITS, 6, 10)])).unwrap(), None);
    }

    #[test]
    fn report_fails_over_budget_and_on_an_empty_folder() {
        let dir = std::env::temp_dir().join(format!("xtask-fwsize-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        assert!(report(&dir)
            .unwrap_err()
            .to_string()
            .contains("no firmware ELF"));
        fs::write(dir.join("fits"), firmware(30_000, 4_000)).unwrap();
        fs::write(dir.join("fits.d"), "not an ELF").unwrap();
        report(&dir).unwrap();
        fs::write(dir.join("too-big"), firmware(100_000, 4_000)).unwrap();
        let err = report(&dir).unwrap_err().to_string();
        assert!(
            err.contains("too-big: flash") && !err.contains("fits:"),
            "{err}"
        );
        fs::write(dir.join("too-big"), firmware(30_000, 16_000)).unwrap();
        assert!(report(&dir)
            .unwrap_err()
            .to_string()
            .contains("too-big: static RAM"));
        fs::remove_file(dir.join("too-big")).unwrap();
        // The bootloader has its partition's budget: what fits an application does not fit it.
        fs::write(dir.join(BOOTLOADER), firmware(30_000, 1_000)).unwrap();
        let err = report(&dir).unwrap_err().to_string();
        assert!(err.contains("ihex-sc-bootloader: flash"), "{err}");
        fs::write(dir.join(BOOTLOADER), firmware(20_000, 1_000)).unwrap();
        report(&dir).unwrap();
        fs::remove_dir_all(&dir).unwrap();
    }
}
