//! The hardware notes must not disagree with the machine-readable pin map (`hw/pinmap.toml`, owned by
//! the firmware): every signal appears in the pin table of `hw/boards.md` with the same pin, the table
//! names no signal the map lacks, and the bill of materials is well-formed CSV.

use std::{collections::BTreeMap, fs, path::PathBuf};

fn hw(file: &str) -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../hw")
        .join(file);
    fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `name -> pin` from the pin map's `[[signal]]` tables.
fn pinmap() -> BTreeMap<String, String> {
    let map: toml::Table = hw("pinmap.toml").parse().expect("hw/pinmap.toml is TOML");
    let signals = map["signal"].as_array().expect("[[signal]] tables");
    signals
        .iter()
        .map(|s| {
            let name = s["name"].as_str().expect("signal name").to_owned();
            let pin = s["pin"].as_str().expect("signal pin").to_owned();
            (name, pin)
        })
        .collect()
}

/// `signal -> pin` from the rows of the boards.md table whose header starts `| signal | pin |`.
fn boards_table() -> BTreeMap<String, String> {
    let text = hw("boards.md");
    let mut rows = BTreeMap::new();
    let mut in_table = false;
    for line in text.lines() {
        let cells: Vec<&str> = line
            .trim()
            .trim_matches('|')
            .split('|')
            .map(str::trim)
            .collect();
        if line.starts_with("| signal | pin |") {
            in_table = true;
            continue;
        }
        if !in_table || cells.first().is_some_and(|c| c.starts_with("---")) {
            continue;
        }
        if !line.starts_with('|') {
            break;
        }
        let dup = rows.insert(cells[0].to_owned(), cells[1].to_owned());
        assert!(dup.is_none(), "boards.md lists {} twice", cells[0]);
    }
    rows
}

#[test]
fn boards_md_pin_table_matches_pinmap() {
    let map = pinmap();
    let table = boards_table();
    assert!(map.len() >= 10, "pin map looks empty: {map:?}");
    for (name, pin) in &map {
        match table.get(name) {
            Some(p) => assert_eq!(
                p, pin,
                "hw/boards.md says {name} is on {p}, hw/pinmap.toml says {pin}"
            ),
            None => panic!("hw/boards.md has no row for signal {name} ({pin})"),
        }
    }
    for name in table.keys() {
        assert!(
            map.contains_key(name),
            "hw/boards.md lists {name}, which hw/pinmap.toml does not have"
        );
    }
}

#[test]
fn every_mcu_pin_named_in_the_connector_tables_is_the_pinmap_pin() {
    // Connector tables name MCU pins like "PA8" next to the net; each must be a pin the map uses.
    let pins: Vec<String> = pinmap().into_values().collect();
    let text = hw("boards.md");
    for word in text.split(|c: char| !c.is_ascii_alphanumeric()) {
        let is_pin = word.len() >= 3
            && word.starts_with('P')
            && word.as_bytes()[1].is_ascii_uppercase()
            && word.as_bytes()[1] <= b'F'
            && word[2..].chars().all(|c| c.is_ascii_digit());
        if is_pin {
            assert!(
                pins.iter().any(|p| p == word),
                "hw/boards.md mentions {word}, not in hw/pinmap.toml"
            );
        }
    }
}

#[test]
fn bom_csv_is_well_formed() {
    let text = hw("bom.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(
        header,
        [
            "assembly",
            "ref",
            "qty_per_assembly",
            "part",
            "value_or_type",
            "example_part",
            "notes"
        ]
    );
    let mut n = 0;
    for (i, line) in lines.enumerate() {
        let cells: Vec<&str> = line.split(',').collect();
        assert_eq!(cells.len(), header.len(), "bom.csv line {}: {line}", i + 2);
        let qty: u32 = cells[2]
            .parse()
            .unwrap_or_else(|_| panic!("bom.csv line {}: quantity {:?}", i + 2, cells[2]));
        assert!(qty > 0);
        n += 1;
    }
    // Every assembly named in the docs has parts.
    for a in ["SC", "Main", "IO", "Dock-female", "Dock-male", "LED", "MC"] {
        assert!(
            text.lines().any(|l| l.starts_with(&format!("{a},"))),
            "bom.csv has no {a} parts"
        );
    }
    assert!(n > 20);
}
