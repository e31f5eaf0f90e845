//! Flattening a firmware ELF into a slot payload, on hand-made ELF files.

use ihex_image::elf::{flatten, fw_info, ElfError};
use ihex_image::{
    board::F303RE, pack_elf, verify_image, Board, FirmwareVersion, FwInfo, PackOverrides, Policy,
    SigningKey, ToolError,
};

const PT_LOAD: u32 = 1;
const BASE: u32 = F303RE.app_start();

struct Seg {
    vaddr: u32,
    paddr: u32,
    data: Vec<u8>,
    memsz: u32,
}

/// A little-endian ELF32 ARM executable with these segments and, optionally, the symbol
/// `IHEX_FW_INFO` at `sym`.
fn elf(segs: &[Seg], sym: Option<u32>) -> Vec<u8> {
    let phoff = 52u32;
    let mut data_off = phoff + 32 * segs.len() as u32;
    let mut body = Vec::new();
    let mut phs = Vec::new();
    for s in segs {
        phs.push([
            PT_LOAD,
            data_off,
            s.vaddr,
            s.paddr,
            s.data.len() as u32,
            s.memsz,
            5,
            4,
        ]);
        body.extend_from_slice(&s.data);
        data_off += s.data.len() as u32;
    }
    // .strtab, .symtab, .shstrtab
    let strtab = b"\0IHEX_FW_INFO\0".to_vec();
    let mut symtab = vec![0u8; 16];
    if let Some(a) = sym {
        for w in [1u32, a, 12] {
            symtab.extend_from_slice(&w.to_le_bytes());
        }
        symtab.extend_from_slice(&[1, 0]); // STB_LOCAL STT_OBJECT, other
        symtab.extend_from_slice(&4u16.to_le_bytes()); // shndx: .text
    }
    let shstr = b"\0.strtab\0.symtab\0.shstrtab\0.text\0".to_vec();
    let strtab_off = data_off;
    let symtab_off = strtab_off + strtab.len() as u32;
    let shstr_off = symtab_off + symtab.len() as u32;
    body.extend_from_slice(&strtab);
    body.extend_from_slice(&symtab);
    body.extend_from_slice(&shstr);
    while body.len() % 4 != 0 {
        body.push(0);
    }
    let shoff = data_off + (strtab.len() + symtab.len() + shstr.len()) as u32;
    let shoff = (shoff + 3) & !3;
    let mut f = vec![0x7f, b'E', b'L', b'F', 1, 1, 1];
    f.resize(16, 0);
    for v in [2u16, 40] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    for v in [1u32, BASE, phoff, shoff, 0x0500_0400] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    for v in [52u16, 32, segs.len() as u16, 40, 5, 3] {
        f.extend_from_slice(&v.to_le_bytes());
    }
    for ph in phs {
        for w in ph {
            f.extend_from_slice(&w.to_le_bytes());
        }
    }
    f.extend_from_slice(&body);
    f.resize(shoff as usize, 0);
    let sh = |f: &mut Vec<u8>, w: [u32; 10]| {
        w.iter().for_each(|x| f.extend_from_slice(&x.to_le_bytes()))
    };
    sh(&mut f, [0; 10]);
    sh(
        &mut f,
        [1, 3, 0, 0, strtab_off, strtab.len() as u32, 0, 0, 1, 0],
    );
    sh(
        &mut f,
        [9, 2, 0, 0, symtab_off, symtab.len() as u32, 1, 1, 4, 16],
    );
    sh(
        &mut f,
        [17, 3, 0, 0, shstr_off, shstr.len() as u32, 0, 0, 1, 0],
    );
    // .text: the first segment's bytes, where the symbol lives.
    let (addr, len) = segs
        .first()
        .map_or((0, 0), |s| (s.vaddr, s.data.len() as u32));
    sh(
        &mut f,
        [
            27,
            1,
            6,
            addr,
            phoff + 32 * segs.len() as u32,
            len,
            0,
            0,
            4,
            0,
        ],
    );
    f
}

fn info() -> FwInfo {
    FwInfo {
        board: Board::NUCLEO_F303RE,
        protocol: (1, 0),
        version: FirmwareVersion::new(0, 3, 1),
    }
}

#[test]
fn code_then_data_at_their_load_addresses() {
    let mut text = vec![0xAB; 0x100];
    text[0x40..0x4C].copy_from_slice(&info().encode());
    let segs = [
        Seg {
            vaddr: BASE,
            paddr: BASE,
            data: text,
            memsz: 0x100,
        },
        // .data: runs in RAM, stored in flash after a gap.
        Seg {
            vaddr: 0x2000_0000,
            paddr: BASE + 0x108,
            data: vec![0xCD; 8],
            memsz: 8,
        },
        // .bss: no file content, left out.
        Seg {
            vaddr: 0x2000_0008,
            paddr: 0x2000_0008,
            data: vec![],
            memsz: 64,
        },
    ];
    let file = elf(&segs, Some(BASE + 0x40));
    let flat = flatten(&file, BASE, 4096).unwrap();
    assert_eq!(flat.bytes.len(), 0x110);
    assert_eq!(flat.bytes[..0x40], [0xAB; 0x40]);
    assert_eq!(
        flat.bytes[0x100..0x108],
        [0xFF; 8],
        "gaps read as erased flash"
    );
    assert_eq!(flat.bytes[0x108..], [0xCD; 8]);
    assert_eq!(fw_info(&file), Ok(Some(info())));

    // Packed: the header takes board, protocol and version from the record.
    let key = SigningKey::test_key();
    let img = pack_elf(&file, PackOverrides::default(), &key).unwrap();
    let policy = Policy::new(
        Board::NUCLEO_F303RE,
        &F303RE,
        1,
        FirmwareVersion::new(0, 1, 0),
    );
    let h = verify_image(&img, &key.public(), &policy).unwrap();
    assert_eq!(
        (h.version, h.protocol, h.payload_len),
        (FirmwareVersion::new(0, 3, 1), (1, 0), 0x110)
    );
    assert_eq!(&img[512..], &flat.bytes[..]);
    // Overrides that agree are fine; one that contradicts the record is refused.
    let same = PackOverrides {
        version: Some(FirmwareVersion::new(0, 3, 1)),
        ..Default::default()
    };
    assert_eq!(pack_elf(&file, same, &key).unwrap(), img);
    let other = PackOverrides {
        version: Some(FirmwareVersion::new(0, 4, 0)),
        ..Default::default()
    };
    assert!(matches!(
        pack_elf(&file, other, &key),
        Err(ToolError::InfoMismatch {
            field: "version",
            ..
        })
    ));
}

#[test]
fn without_a_record_the_fields_must_be_given() {
    let segs = [Seg {
        vaddr: BASE,
        paddr: BASE,
        data: vec![1; 64],
        memsz: 64,
    }];
    let file = elf(&segs, None);
    assert_eq!(fw_info(&file), Ok(None));
    let key = SigningKey::test_key();
    assert!(matches!(
        pack_elf(&file, PackOverrides::default(), &key),
        Err(ToolError::InfoMissing("board"))
    ));
    let given = PackOverrides {
        board: Some(Board::NUCLEO_F303RE),
        protocol: Some((1, 0)),
        version: Some(FirmwareVersion::new(2, 0, 0)),
    };
    let img = pack_elf(&file, given, &key).unwrap();
    assert_eq!(img.len(), 512 + 64);
}

#[test]
fn misplaced_segments_are_refused() {
    let seg = |paddr: u32, len: usize| Seg {
        vaddr: paddr,
        paddr,
        data: vec![1; len],
        memsz: len as u32,
    };
    assert_eq!(
        flatten(&elf(&[seg(0x0800_0000, 16)], None), BASE, 4096),
        Err(ElfError::OutOfSlot {
            addr: 0x0800_0000,
            len: 16,
            base: BASE,
            end: BASE + 4096
        })
    );
    assert!(matches!(
        flatten(
            &elf(&[seg(BASE, 16), seg(BASE + 4090, 16)], None),
            BASE,
            4096
        ),
        Err(ElfError::OutOfSlot { .. })
    ));
    assert_eq!(
        flatten(&elf(&[seg(BASE + 0x200, 16)], None), BASE, 4096),
        Err(ElfError::NotAtBase {
            lowest: BASE + 0x200,
            base: BASE
        })
    );
    assert_eq!(
        flatten(&elf(&[seg(BASE, 16), seg(BASE + 8, 16)], None), BASE, 4096),
        Err(ElfError::Overlap(BASE + 8))
    );
    assert_eq!(flatten(&elf(&[], None), BASE, 4096), Err(ElfError::Empty));
    assert!(matches!(
        flatten(b"not an elf", BASE, 4096),
        Err(ElfError::Parse(_))
    ));
    assert_eq!(
        flatten(&elf(&[seg(BASE, 16)], None), BASE, 4096)
            .unwrap()
            .bytes,
        vec![1; 16]
    );
}
