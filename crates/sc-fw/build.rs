//! Build script: linker set-up, and the pin map check + code generation.
//!
//! `hw/pinmap.toml` is the single source of the SC's pin assignment. This script
//!
//! 1. checks every entry against the chip's alternate-function table (stm32-metapac metadata, the data
//!    embassy-stm32 itself is generated from): the pin exists on the STM32F303RE, the peripheral has
//!    that signal on that pin, with that AF number;
//! 2. checks the map against what this firmware drives (`EXPECTED` below): every signal present, with
//!    the peripheral and channel the tasks are written for, no pin and no EXTI line used twice;
//! 3. generates `board.rs` (included by `src/board.rs`): the `take_board!` macro moving exactly those
//!    pins out of `Peripherals`, the EXTI interrupt bindings, and the pulls/active levels.
//!
//! Any disagreement fails the build with a message naming the pin map entry.
//!
//! It also writes the linker's `memory.x` from the flash layout (`ihex_image::board::F303RE`, the
//! one place the partitions are written; checked against the chip's metadata here): the
//! application runs in the active slot after the image header block, so FLASH starts at
//! `F303RE.app_start()`. And it embeds the public key images must be signed with
//! (`IHEX_FW_PUBKEY`, a key file; the committed test key, with a warning, when unset).

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::{env, fs};

use ihex_image::board::F303RE;
use serde::Deserialize;
use stm32_metapac::metadata::METADATA;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PinMap {
    board: BoardInfo,
    signal: Vec<Signal>,
}

#[derive(Deserialize)]
struct BoardInfo {
    chip: String,
    config_page_addr: u32,
    config_page_size: u32,
    apb1_hz: u32,
    sysclk_hz: u32,
    hse_hz: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Signal {
    name: String,
    pin: String,
    peripheral: String,
    function: Option<String>,
    af: Option<u8>,
    exti: Option<u8>,
    direction: String,
    pull: String,
    active: String,
    #[allow(dead_code)]
    reset_state: String,
    #[allow(dead_code)]
    nucleo: String,
    #[allow(dead_code)]
    notes: String,
}

/// What the firmware's tasks are written for: (name, peripheral, function, direction, needs EXTI).
const EXPECTED: &[(&str, &str, Option<&str>, &str, bool)] = &[
    ("can_rx", "CAN", Some("RX"), "in", false),
    ("can_tx", "CAN", Some("TX"), "out", false),
    ("uart_tx", "USART2", Some("TX"), "out", false),
    ("uart_rx", "USART2", Some("RX"), "in", false),
    ("led_r", "TIM1", Some("CH1"), "out", false),
    ("led_g", "TIM1", Some("CH2"), "out", false),
    ("led_b", "TIM1", Some("CH3"), "out", false),
    ("led_blink", "TIM3", Some("CH1"), "out", false),
    ("buzzer", "TIM15", Some("CH2"), "out", false),
    ("relay", "GPIO", None, "out", false),
    ("loop0", "GPIO", None, "in", true),
    ("loop1", "GPIO", None, "in", true),
    ("loop2", "GPIO", None, "in", true),
    ("loop3", "GPIO", None, "in", true),
    ("loop4", "GPIO", None, "in", true),
    ("loop5", "GPIO", None, "in", true),
    ("role", "GPIO", None, "in", false),
    ("status_led", "GPIO", None, "out", false),
];

fn main() {
    let manifest = PathBuf::from(env::var("CARGO_MANIFEST_DIR").unwrap());
    let out = PathBuf::from(env::var("OUT_DIR").unwrap());
    // IHEX_PINMAP points the check at another file (used by check-pinmap.sh's negative cases).
    println!("cargo:rerun-if-env-changed=IHEX_PINMAP");
    let pinmap_path = env::var_os("IHEX_PINMAP")
        .map(PathBuf::from)
        .unwrap_or_else(|| manifest.join("../../hw/pinmap.toml"));
    println!("cargo:rerun-if-changed={}", pinmap_path.display());
    println!("cargo:rerun-if-changed=build.rs");

    let text = fs::read_to_string(&pinmap_path)
        .unwrap_or_else(|e| fail(&format!("cannot read {}: {e}", pinmap_path.display())));
    let map: PinMap = toml::from_str(&text)
        .unwrap_or_else(|e| fail(&format!("hw/pinmap.toml does not parse: {e}")));

    let errors = check(&map);
    if !errors.is_empty() {
        let mut msg = String::from("hw/pinmap.toml disagrees with the chip or with sc-fw:\n");
        for e in &errors {
            let _ = writeln!(msg, "  - {e}");
        }
        fail(&msg);
    }

    fs::write(out.join("memory.x"), memory_x()).unwrap();
    fs::write(out.join("board.rs"), generate(&map)).unwrap();
    fs::write(out.join("pubkey.rs"), public_key(&manifest)).unwrap();
    println!("cargo:rerun-if-changed=../ihex-image/src/board.rs");

    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=--nmagic");
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
}

fn fail(msg: &str) -> ! {
    // A panic message is what cargo shows for a failing build script.
    panic!("\n\n{msg}\n");
}

fn check(map: &PinMap) -> Vec<String> {
    let mut errors = Vec::new();
    if !METADATA.name.eq_ignore_ascii_case(&map.board.chip) {
        errors.push(format!(
            "board.chip is {} but sc-fw is built for {}",
            map.board.chip, METADATA.name
        ));
    }
    if let Err(e) = F303RE.check() {
        errors.push(format!(
            "ihex_image::board::F303RE is not a valid layout: {e}"
        ));
    }
    let (flash, sram) = (region("BANK_1"), region("SRAM"));
    if (
        F303RE.flash.start,
        F303RE.flash.len,
        F303RE.ram.start,
        F303RE.ram.len,
    ) != (flash.address, flash.size, sram.address, sram.size)
    {
        errors.push("ihex_image::board::F303RE's flash or RAM differ from the chip's".into());
    }
    if flash
        .settings
        .as_ref()
        .map(|s| (s.erase_size, s.write_size))
        != Some((F303RE.page, F303RE.write_unit))
    {
        errors.push("ihex_image::board::F303RE's page or write unit differ from the chip's".into());
    }
    if (map.board.config_page_addr, map.board.config_page_size)
        != (F303RE.config.start, F303RE.config.len)
    {
        errors.push(format!(
            "board.config_page_addr/size must be the layout's config page, {:#010x} / {}",
            F303RE.config.start, F303RE.config.len
        ));
    }
    if (map.board.hse_hz, map.board.sysclk_hz, map.board.apb1_hz)
        != (8_000_000, 72_000_000, 36_000_000)
    {
        errors.push(
            "clock tree must be HSE 8 MHz -> SYSCLK 72 MHz -> APB1 36 MHz (src/main.rs sets it)"
                .into(),
        );
    }

    let chip_pins: BTreeSet<&str> = METADATA.pins.iter().map(|p| p.name).collect();
    let mut pins_used: BTreeMap<&str, &str> = BTreeMap::new();
    let mut exti_used: BTreeMap<u8, &str> = BTreeMap::new();
    let mut names: BTreeSet<&str> = BTreeSet::new();

    for s in &map.signal {
        let n = s.name.as_str();
        if !names.insert(n) {
            errors.push(format!("signal `{n}` is listed twice"));
        }
        if !chip_pins.contains(s.pin.as_str()) {
            errors.push(format!(
                "`{n}`: pin {} does not exist on {}",
                s.pin, METADATA.name
            ));
            continue;
        }
        if let Some(other) = pins_used.insert(&s.pin, n) {
            errors.push(format!("`{n}`: pin {} is already used by `{other}`", s.pin));
        }
        if !matches!(s.direction.as_str(), "in" | "out") {
            errors.push(format!("`{n}`: direction must be \"in\" or \"out\""));
        }
        if !matches!(s.pull.as_str(), "up" | "down" | "none") {
            errors.push(format!("`{n}`: pull must be \"up\", \"down\" or \"none\""));
        }
        if !matches!(s.active.as_str(), "high" | "low") {
            errors.push(format!("`{n}`: active must be \"high\" or \"low\""));
        }
        if let Some(line) = s.exti {
            if pin_number(&s.pin) != Some(line) {
                errors.push(format!(
                    "`{n}`: the EXTI line of {} is {}, not {line}",
                    s.pin,
                    pin_number(&s.pin).map_or("-".to_string(), |l| l.to_string())
                ));
            }
            if let Some(other) = exti_used.insert(line, n) {
                errors.push(format!(
                    "`{n}`: EXTI line {line} is already used by `{other}` (lines must be distinct)"
                ));
            }
        }
        match (s.peripheral.as_str(), &s.function, s.af) {
            ("GPIO", None, None) => {}
            ("GPIO", _, _) => errors.push(format!("`{n}`: a GPIO signal has no function/af")),
            (periph, Some(func), Some(af)) => check_af(&mut errors, n, &s.pin, periph, func, af),
            (_, _, _) => errors.push(format!(
                "`{n}`: a peripheral signal needs both `function` and `af`"
            )),
        }
    }

    for &(name, periph, func, dir, exti) in EXPECTED {
        let Some(s) = map.signal.iter().find(|s| s.name == name) else {
            let what = func.map_or(periph.to_string(), |f| format!("{periph}_{f}"));
            errors.push(format!(
                "signal `{name}` ({what}) is missing; sc-fw needs it"
            ));
            continue;
        };
        if s.peripheral != periph || s.function.as_deref() != func {
            errors.push(format!(
                "`{name}` is {} {} but sc-fw drives it as {periph} {}",
                s.peripheral,
                s.function.as_deref().unwrap_or(""),
                func.unwrap_or("")
            ));
        }
        if s.direction != dir {
            errors.push(format!(
                "`{name}`: direction {} but sc-fw uses it as {dir}",
                s.direction
            ));
        }
        if s.exti.is_some() != exti {
            errors.push(format!(
                "`{name}`: sc-fw {} an EXTI line",
                if exti { "needs" } else { "does not use" }
            ));
        }
    }
    // The bootloader drives the relay without the generated board module (bootloader/src/main.rs
    // `RELAY_PIN`): PB5, on = high.
    if let Some(s) = map.signal.iter().find(|s| s.name == "relay") {
        if (s.pin.as_str(), s.active.as_str()) != ("PB5", "high") {
            errors.push(format!(
                "`relay` is {} active {}, but the bootloader keeps it on as PB5 active high \
                 (bootloader/src/main.rs RELAY_PIN)",
                s.pin, s.active
            ));
        }
    }
    for s in &map.signal {
        if !EXPECTED.iter().any(|e| e.0 == s.name) {
            errors.push(format!(
                "signal `{}` is not used by sc-fw (remove it or add it to build.rs EXPECTED)",
                s.name
            ));
        }
    }
    errors
}

fn check_af(errors: &mut Vec<String>, name: &str, pin: &str, periph: &str, func: &str, af: u8) {
    let Some(p) = METADATA.peripherals.iter().find(|p| p.name == periph) else {
        errors.push(format!(
            "`{name}`: {} has no peripheral {periph}",
            METADATA.name
        ));
        return;
    };
    let here = p.pins.iter().find(|pp| pp.pin == pin && pp.signal == func);
    match here {
        Some(pp) if pp.af == Some(af) => {}
        Some(pp) => errors.push(format!(
            "`{name}`: {periph}_{func} on {pin} is AF{}, not AF{af}",
            pp.af.map_or("-".to_string(), |a| a.to_string())
        )),
        None => {
            let alts: Vec<String> = p
                .pins
                .iter()
                .filter(|pp| pp.signal == func)
                .map(|pp| format!("{} (AF{})", pp.pin, pp.af.unwrap_or(0)))
                .collect();
            errors.push(format!(
                "`{name}`: {pin} cannot be {periph}_{func}; it is available on {}",
                if alts.is_empty() {
                    "no pin".to_string()
                } else {
                    alts.join(", ")
                }
            ));
        }
    }
}

/// `PC5` → 5.
fn pin_number(pin: &str) -> Option<u8> {
    pin.get(2..)?.parse().ok()
}

/// A memory region of the chip's metadata.
fn region(name: &str) -> &'static stm32_metapac::metadata::MemoryRegion {
    METADATA
        .memory
        .iter()
        .flat_map(|bank| bank.iter())
        .find(|r| r.name == name)
        .unwrap_or_else(|| fail(&format!("the chip metadata has no {name} region")))
}

fn memory_x() -> String {
    let l = F303RE;
    format!(
        "/* Generated by sc-fw/build.rs from ihex_image::board::F303RE. The application runs in the\n   \
         active slot ({:#010x}..{:#010x}) after the {}-byte image header block; the bootloader,\n   \
         its state, the DFU slot and the configuration page ({:#010x}) lie outside FLASH.\n   \
         CCM RAM is not used. KEPT (the top of SRAM, at the same address as in the bootloader's\n   \
         memory.x) is outside RAM, so no start-up clears it. */\n\
         MEMORY\n{{\n  FLASH : ORIGIN = {:#010x}, LENGTH = {}\n  RAM : ORIGIN = {:#010x}, LENGTH = {}\n  \
         KEPT : ORIGIN = {:#010x}, LENGTH = {}\n}}\n",
        l.active.start,
        l.active.end(),
        ihex_image::HEADER_BLOCK,
        l.config.start,
        l.app_start(),
        l.active.end() - l.app_start(),
        l.program_ram().start,
        l.program_ram().len,
        l.kept_ram().start,
        l.kept_ram().len,
    )
}

/// `FW_PUBLIC_KEY`: the key of `IHEX_FW_PUBKEY`, or the committed test key (with a warning).
fn public_key(manifest: &std::path::Path) -> String {
    println!("cargo:rerun-if-env-changed=IHEX_FW_PUBKEY");
    let (path, is_test) = match env::var_os("IHEX_FW_PUBKEY") {
        Some(p) => (PathBuf::from(p), false),
        None => (
            manifest.join("../ihex-image/test-key/ihex-test-key.pub"),
            true,
        ),
    };
    println!("cargo:rerun-if-changed={}", path.display());
    let text = fs::read_to_string(&path).unwrap_or_else(|e| {
        fail(&format!(
            "IHEX_FW_PUBKEY: cannot read {}: {e}",
            path.display()
        ))
    });
    let key = ihex_image::PublicKey::from_text(&text)
        .unwrap_or_else(|e| fail(&format!("IHEX_FW_PUBKEY: {}: {e}", path.display())));
    if is_test || key == ihex_image::test_key::PUBLIC {
        println!(
            "cargo:warning=firmware trusts the committed TEST key ({}): anybody can sign images for it. \
             Set IHEX_FW_PUBKEY=<your lab's .pub> for a real island (docs/firmware-update.md).",
            key.id()
        );
    }
    format!(
        "/// The public key update images must be signed with (key ID {}).\n\
         pub const FW_PUBLIC_KEY: [u8; 32] = {:?};\n",
        key.id(),
        key.to_bytes()
    )
}
fn exti_irq(line: u8) -> &'static str {
    let exti = METADATA
        .peripherals
        .iter()
        .find(|p| p.name == "EXTI")
        .expect("EXTI in metadata");
    let sig = format!("EXTI{line}");
    exti.interrupts
        .iter()
        .find(|i| i.signal == sig)
        .map(|i| i.interrupt)
        // Like embassy-stm32's build script: the metadata omits EXTI2 on chips that share its vector
        // with the touch controller.
        .or_else(|| {
            (line == 2)
                .then(|| {
                    METADATA
                        .interrupts
                        .iter()
                        .find(|i| i.name == "EXTI2_TSC")
                        .map(|i| i.name)
                })
                .flatten()
        })
        .unwrap_or_else(|| fail(&format!("no interrupt for EXTI line {line}")))
}

fn generate(map: &PinMap) -> String {
    let mut fields = String::new();
    let mut inits = String::new();
    let mut consts = String::new();
    let mut irqs: BTreeSet<&str> = BTreeSet::new();
    for s in &map.signal {
        let n = &s.name;
        let what = match &s.function {
            Some(f) => format!("{} {f} (AF{})", s.peripheral, s.af.unwrap_or(0)),
            None => "GPIO".to_string(),
        };
        let _ = writeln!(
            fields,
            "    /// `{n}`: {} as {what}, {}.",
            s.pin, s.direction
        );
        let _ = writeln!(
            fields,
            "    pub {n}: Peri<'static, peripherals::{}>,",
            s.pin
        );
        let _ = writeln!(inits, "            {n}: $p.{},", s.pin);
        if let Some(line) = s.exti {
            let _ = writeln!(fields, "    /// EXTI channel of `{n}`.");
            let _ = writeln!(
                fields,
                "    pub {n}_exti: Peri<'static, peripherals::EXTI{line}>,"
            );
            let _ = writeln!(inits, "            {n}_exti: $p.EXTI{line},");
            irqs.insert(exti_irq(line));
        }
        let upper = n.to_uppercase();
        let pull = match s.pull.as_str() {
            "up" => "Up",
            "down" => "Down",
            _ => "None",
        };
        let _ = writeln!(consts, "/// Internal pull of `{n}` ({}).", s.pin);
        let _ = writeln!(consts, "pub const {upper}_PULL: Pull = Pull::{pull};");
        let _ = writeln!(consts, "/// True when `{n}` is asserted low.");
        let _ = writeln!(
            consts,
            "pub const {upper}_ACTIVE_LOW: bool = {};",
            s.active == "low"
        );
    }
    let mut binds = String::new();
    for irq in &irqs {
        let _ = writeln!(
            binds,
            "        {irq} => exti::InterruptHandler<interrupt::typelevel::{irq}>;"
        );
    }
    format!(
        "// Generated by sc-fw/build.rs from hw/pinmap.toml. Do not edit.\n\
         use embassy_stm32::gpio::Pull;\n\
         use embassy_stm32::{{bind_interrupts, exti, interrupt, peripherals, Peri}};\n\n\
         /// Every pin (and EXTI channel) of the pin map, moved out of `Peripherals`.\n\
         pub struct Board {{\n{fields}}}\n\n\
         /// Moves the pin map's pins out of a `Peripherals` value (the other fields stay usable).\n\
         #[macro_export]\n\
         macro_rules! take_board {{\n    ($p:ident) => {{\n        $crate::board::Board {{\n{inits}        }}\n    }};\n}}\n\n\
         bind_interrupts!(\n    /// EXTI interrupt bindings for the signal-loop lines of the pin map.\n    pub struct ExtiIrqs {{\n{binds}    }}\n);\n\n\
         {consts}\n\
         /// Address of the flash page holding the configuration record.\n\
         pub const CONFIG_PAGE_ADDR: u32 = {:#010x};\n\
         /// Size of that page.\n\
         pub const CONFIG_PAGE_SIZE: u32 = {};\n\
         /// APB1 clock (bxCAN kernel clock).\n\
         pub const APB1_HZ: u32 = {};\n",
        map.board.config_page_addr, map.board.config_page_size, map.board.apb1_hz
    )
}
