//! The DBC file against the codec: the committed `docs/ihex.dbc` is what the generator writes, a
//! Rust DBC parser (can-dbc) reads back exactly the schema, and cantools decodes every golden
//! vector and a few hundred generated frames to the codec's field values and encodes those values
//! back to bytes the codec decodes to the same packet.
//!
//! The cantools test needs Python with cantools: `cargo xtask test` (host stage) installs it in
//! `target/venv` and runs it with `--ignored`, setting `IHEX_CANTOOLS_PYTHON` (that Python),
//! `IHEX_GOLDEN_VECTORS` (the vectors `golden.rs` wrote in the same run) and
//! `IHEX_CANTOOLS_REPORT` (a file the test writes when it has passed, which xtask checks).

use std::collections::{BTreeMap, BTreeSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use can_dbc::{ByteOrder, Dbc, MessageId, MultiplexIndicator, NumericValue, ValueType};
use ihex_proto::dbc::{self, Layout, FRAME_ID_MASK};
use ihex_proto::schema::{self, Direction, MessageSchema, Mux};
use ihex_proto::test_util::id as node;
use ihex_proto::{Header, Kind, NodeId, Packet};
use proptest::strategy::{Strategy, ValueTree};
use proptest::test_runner::TestRunner;
use serde_json::{json, Value};

mod signals;
mod strategy;

fn manifest_dir() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn committed_path() -> PathBuf {
    manifest_dir().join("../../docs/ihex.dbc")
}

fn generate(layout: Layout<'_>) -> String {
    let mut text = String::new();
    dbc::write(&mut text, layout).unwrap();
    text
}

#[test]
fn committed_dbc_is_what_the_generator_writes() {
    let committed = std::fs::read_to_string(committed_path()).unwrap();
    assert!(
        committed == generate(Layout::ByKind),
        "docs/ihex.dbc differs from what ihex-proto's schema generates: run `cargo xtask dbc` \
         and commit the result"
    );
}

/// Checks one parsed message against its schema.
fn check_message(dbc: &Dbc, m: &can_dbc::Message, schema: &MessageSchema, tx: &str, rx: &[&str]) {
    let what = &m.name;
    assert_eq!(m.size, u64::from(schema.data_len()), "{what}");
    assert_eq!(m.transmitter.as_deref(), Some(tx), "{what}");
    let names: Vec<&str> = m.signals.iter().map(|s| s.name.as_str()).collect();
    let want: Vec<&str> = schema.signals.iter().map(|s| s.name).collect();
    assert_eq!(names, want, "{what}");
    for (got, s) in m.signals.iter().zip(schema.signals) {
        let what = format!("{what}.{}", s.name);
        assert_eq!(got.start_bit, u64::from(s.start), "{what}");
        assert_eq!(got.size, u64::from(s.bits), "{what}");
        assert_eq!(got.byte_order, ByteOrder::LittleEndian, "{what}");
        assert_eq!(got.value_type, ValueType::Unsigned, "{what}");
        assert_eq!(got.factor, f64::from(s.factor), "{what}");
        assert_eq!(got.offset, f64::from(s.offset), "{what}");
        assert_eq!(
            got.min,
            NumericValue::Uint(s.physical(s.min) as u64),
            "{what}"
        );
        assert_eq!(
            got.max,
            NumericValue::Uint(s.physical(s.max) as u64),
            "{what}"
        );
        assert_eq!(got.unit, s.unit, "{what}");
        assert_eq!(got.receivers, rx, "{what}");
        let (indicator, extended) = match s.mux {
            Mux::Always => (MultiplexIndicator::Plain, None),
            Mux::Selector => (MultiplexIndicator::Multiplexor, None),
            Mux::When(v) => (
                MultiplexIndicator::MultiplexedSignal(u64::from(v[0])),
                (v.len() > 1).then_some(v),
            ),
        };
        assert_eq!(got.multiplexer_indicator, indicator, "{what}");
        let mapped: Vec<u64> = dbc
            .extended_multiplex
            .iter()
            .filter(|x| x.message_id == m.id && x.signal_name == s.name)
            .flat_map(|x| {
                let selector = schema.selector().map(|s| s.name);
                assert_eq!(Some(x.multiplexor_signal_name.as_str()), selector, "{what}");
                x.mappings.iter().flat_map(|r| r.min_value..=r.max_value)
            })
            .collect();
        let want: Vec<u64> = extended
            .unwrap_or(&[])
            .iter()
            .map(|v| u64::from(*v))
            .collect();
        assert_eq!(mapped, want, "{what}: SG_MUL_VAL_");
        let values: Vec<(i64, &str)> = dbc
            .value_descriptions_for_signal(m.id, s.name)
            .unwrap_or_default()
            .iter()
            .map(|v| (v.id, v.description.as_str()))
            .collect();
        let want: Vec<(i64, &str)> = s.values.iter().map(|(v, l)| (i64::from(*v), *l)).collect();
        assert_eq!(values, want, "{what}");
        assert!(dbc.signal_comment(m.id, s.name).is_some(), "{what}");
    }
    assert!(dbc.message_comment(m.id).is_some(), "{what}");
}

#[test]
fn can_dbc_reads_back_the_schema() {
    let text = std::fs::read_to_string(committed_path()).unwrap();
    let dbc = Dbc::try_from(text.as_str()).unwrap();
    let nodes: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    assert_eq!(nodes, [dbc::GATEWAY, dbc::SC]);
    assert_eq!(dbc.messages.len(), Kind::ALL.len());
    for (m, schema) in dbc.messages.iter().zip(schema::all()) {
        // Bit 31 in the file (extended), the kind alone in the identifier.
        assert_eq!(
            m.id,
            MessageId::Extended(u32::from(schema.kind as u8) << 24)
        );
        assert_eq!(m.id.raw() & FRAME_ID_MASK, (schema.kind as u32) << 24);
        assert_eq!(m.name, schema.name());
        let (tx, rx) = match schema.direction() {
            Direction::Command => (dbc::GATEWAY, dbc::SC),
            Direction::Report => (dbc::SC, dbc::GATEWAY),
        };
        check_message(&dbc, m, &schema, tx, &[rx]);
    }
}

#[test]
fn can_dbc_reads_an_island_file_with_every_allowed_address_pair() {
    let nodes = [node(0x002), node(0x111)];
    let text = generate(Layout::Island(&nodes));
    let dbc = Dbc::try_from(text.as_str()).unwrap();
    let names: Vec<&str> = dbc.nodes.iter().map(|n| n.0.as_str()).collect();
    assert_eq!(names, ["Gateway", "SC_2", "SC_111", "SC_unconfigured"]);
    let all_sc = ["SC_2", "SC_111", "SC_unconfigured"];
    let mut seen = BTreeSet::new();
    for m in &dbc.messages {
        let MessageId::Extended(raw) = m.id else {
            panic!("{}: not extended", m.name)
        };
        let h = Header::from_raw(raw).unwrap();
        assert_eq!(h.check_addresses(), Ok(()), "{}", m.name);
        let schema = schema::of(h.kind);
        let (sc, tx, rx): (String, String, Vec<String>) = match schema.direction() {
            Direction::Command if h.dest == NodeId::BROADCAST => (
                "all".into(),
                "Gateway".into(),
                all_sc.iter().map(|s| s.to_string()).collect(),
            ),
            Direction::Command => (
                h.dest.to_string(),
                "Gateway".into(),
                vec![format!("SC_{}", h.dest)],
            ),
            Direction::Report if h.src == NodeId::UNCONFIGURED => (
                "unconfigured".into(),
                "SC_unconfigured".into(),
                vec!["Gateway".into()],
            ),
            Direction::Report => (
                h.src.to_string(),
                format!("SC_{}", h.src),
                vec!["Gateway".into()],
            ),
        };
        let rx: Vec<&str> = rx.iter().map(String::as_str).collect();
        assert_eq!(m.name, format!("{}_{sc}", schema.name()));
        check_message(&dbc, m, &schema, &tx, &rx);
        seen.insert(raw);
    }
    // Exactly the pairs the address rules allow among gateway, the nodes, 0xFFE and broadcast.
    let addresses = [
        NodeId::GATEWAY,
        node(0x002),
        node(0x111),
        NodeId::UNCONFIGURED,
        NodeId::BROADCAST,
    ];
    let mut allowed = BTreeSet::new();
    for kind in Kind::ALL {
        for dest in addresses {
            for src in addresses {
                let h = Header { kind, dest, src };
                if h.check_addresses().is_ok() {
                    allowed.insert(h.to_raw());
                }
            }
        }
    }
    assert_eq!(seen, allowed);
    assert_eq!(dbc.messages.len(), allowed.len(), "a message twice");
}

/// Multiplexing on a small example: `M`, `m<n>` and `SG_MUL_VAL_` ranges (`StateReport`, checked
/// above, has them too).
#[test]
fn can_dbc_reads_multiplexed_signals() {
    let example = signals::mux_example();
    let mut text = String::new();
    dbc::write_messages(&mut text, Layout::ByKind, &[example]).unwrap();
    assert!(text.contains(" SG_ part M : 0|8@1+"), "{text}");
    assert!(text.contains(" SG_ c m1 : 8|16@1+"), "{text}");
    assert!(
        text.contains("SG_MUL_VAL_ 2164260864 c part 1-3;"),
        "{text}"
    );
    let dbc = Dbc::try_from(text.as_str()).unwrap();
    assert_eq!(dbc.messages.len(), 1);
    check_message(&dbc, &dbc.messages[0], &example, dbc::SC, &[dbc::GATEWAY]);

    // The state reports of the committed file: the dock parts as one range, the part numbers this
    // version does not know (around 0x00-0x02, 0x10-0x17, 0x20-0x24 and 0xFF) as three.
    let committed = std::fs::read_to_string(committed_path()).unwrap();
    for line in [
        " SG_ part M : 0|8@1+ (1,0) [0|255] \"\" Gateway\n",
        " SG_ dock_partner m16 : 16|16@1+ (1,0) [1|4095] \"\" Gateway\n",
        "SG_MUL_VAL_ 2449473536 dock_partner part 16-23;\n",
        "SG_MUL_VAL_ 2449473536 data_1 part 3-15, 24-31, 37-254;\n",
    ] {
        assert!(committed.contains(line), "{line}");
    }
}

#[test]
fn an_island_lists_distinct_sub_controllers() {
    let mut out = String::new();
    for (nodes, err) in [
        (
            vec![node(0x111), NodeId::GATEWAY],
            dbc::Error::NotASubController(NodeId::GATEWAY),
        ),
        (
            vec![NodeId::BROADCAST],
            dbc::Error::NotASubController(NodeId::BROADCAST),
        ),
        (
            vec![node(0x2), node(0x111), node(0x2)],
            dbc::Error::Duplicate(node(0x2)),
        ),
    ] {
        assert_eq!(dbc::write(&mut out, Layout::Island(&nodes)), Err(err));
        assert!(out.is_empty(), "nothing written before the check");
    }
}

// ---------------------------------------------------------------------------------------------
// cantools

fn required_env(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| {
        panic!(
            "{name} is not set: this test runs through `cargo xtask test --stage host`, which \
             installs cantools in target/venv and sets IHEX_CANTOOLS_PYTHON and IHEX_GOLDEN_VECTORS"
        )
    })
}

fn hex(data: &[u8]) -> String {
    data.iter().map(|b| format!("{b:02X}")).collect()
}

fn unhex(s: &str) -> Vec<u8> {
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

/// The golden vectors `golden.rs` recorded: every one must be a valid packet.
fn golden_vectors(path: &str) -> Vec<Packet> {
    let text = std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("IHEX_GOLDEN_VECTORS={path}: {e} (run the golden tests first)"));
    let lines: BTreeSet<&str> = text.lines().collect();
    lines
        .into_iter()
        .map(|line| {
            let (id, data) = line.split_once('#').unwrap();
            Packet::decode(u32::from_str_radix(id, 16).unwrap(), &unhex(data))
                .unwrap_or_else(|e| panic!("golden vector {line}: {e}"))
        })
        .collect()
}

/// The sub-controller a frame is to or from.
fn sc_of(p: &Packet) -> NodeId {
    if p.msg.kind().is_command() {
        p.dest
    } else {
        p.src
    }
}

/// How cantools names a node in an island message name.
fn island_suffix(n: NodeId) -> String {
    match n {
        NodeId::BROADCAST => "all".into(),
        NodeId::UNCONFIGURED => "unconfigured".into(),
        n => n.to_string(),
    }
}

/// cantools' one-line form of a decoded message, as `cantools decode --single-line` prints it
/// (the signals of a multiplexed message in schema order: the selector is first).
fn cantools_line(p: &Packet) -> String {
    let expected = signals::expected(&p.msg);
    let schema = schema::of(p.msg.kind());
    let data = p.msg.encode();
    let fields: Vec<String> = schema
        .signals_in(&data)
        .map(|s| {
            let e = expected.iter().find(|e| e.name == s.name).unwrap();
            match (&e.label, s.unit) {
                (Some(label), _) => format!("{}: {label}", s.name),
                (None, "") => format!("{}: {}", s.name, e.physical),
                (None, unit) => format!("{}: {} {unit}", s.name, e.physical),
            }
        })
        .collect();
    format!("{}({})", schema.name(), fields.join(", "))
}

#[test]
#[ignore = "needs cantools: `cargo xtask test --stage host` runs it"]
fn cantools_decodes_and_encodes_like_the_codec() {
    let python = required_env("IHEX_CANTOOLS_PYTHON");
    let golden = golden_vectors(&required_env("IHEX_GOLDEN_VECTORS"));
    let kinds: BTreeSet<u8> = golden.iter().map(|p| p.msg.kind() as u8).collect();
    assert_eq!(kinds.len(), Kind::ALL.len(), "golden vectors of every kind");

    // A few hundred property-generated packets, the same ones every run.
    let mut runner = TestRunner::deterministic();
    let strategy = strategy::packet();
    let generated: Vec<Packet> = (0..400)
        .map(|_| strategy.new_tree(&mut runner).unwrap().current())
        .collect();

    // The golden vectors also go through an island file with exact IDs for their nodes.
    let island_nodes: BTreeSet<NodeId> = golden.iter().map(sc_of).filter(|n| n.is_sc()).collect();
    let island_nodes: Vec<NodeId> = island_nodes.into_iter().collect();
    let island_path = Path::new(env!("CARGO_TARGET_TMPDIR")).join("island.dbc");
    std::fs::write(&island_path, generate(Layout::Island(&island_nodes))).unwrap();

    let packets: Vec<(Packet, bool)> = golden
        .iter()
        .map(|p| (*p, true))
        .chain(generated.iter().map(|p| (*p, false)))
        .collect();
    let frames: Vec<Value> = packets
        .iter()
        .map(|(p, island)| {
            let (id, data) = p.encode();
            let values: BTreeMap<&str, i64> = signals::expected(&p.msg)
                .iter()
                .map(|e| (e.name, e.physical))
                .collect();
            json!({"id": id, "data": hex(&data), "values": values, "island": island})
        })
        .collect();
    let request = json!({
        "dbc": committed_path(),
        "mask": FRAME_ID_MASK,
        "island_dbc": island_path,
        "frames": frames,
    });
    let script = manifest_dir().join("tests/dbc/cantools_roundtrip.py");
    let out = run_python(&python, &[script.to_str().unwrap()], &request.to_string());
    let reply: Value = serde_json::from_str(&out).unwrap();
    println!(
        "cantools {} decoded {} golden and {} generated frames",
        reply["cantools"],
        golden.len(),
        generated.len()
    );
    let results = reply["results"].as_array().unwrap();
    assert_eq!(results.len(), packets.len());

    for ((p, island), r) in packets.iter().zip(results) {
        let kind = p.msg.kind();
        let ctx = format!("{p:?} ({:08X}#{})", p.encode().0, hex(&p.encode().1));
        assert_eq!(r["name"], kind.name(), "{ctx}");
        let decoded = r["decoded"].as_object().unwrap();
        let expected = signals::expected(&p.msg);
        assert_eq!(decoded.len(), expected.len(), "{ctx}: {decoded:?}");
        for e in &expected {
            let got = &decoded[e.name];
            assert_eq!(got["value"].as_i64(), Some(e.physical), "{ctx}: {}", e.name);
            assert_eq!(
                got["label"].as_str(),
                e.label.as_deref(),
                "{ctx}: {}",
                e.name
            );
        }
        // What cantools encodes from the field values decodes to the same packet.
        let encoded = unhex(r["encoded"].as_str().unwrap());
        assert_eq!(
            Packet::decode(p.encode().0, &encoded),
            Ok(*p),
            "{ctx}: cantools encoded {encoded:02X?}"
        );
        if *island {
            let name = format!("{}_{}", kind.name(), island_suffix(sc_of(p)));
            assert_eq!(r["island_name"], name.as_str(), "{ctx}");
            assert_eq!(r["island_decoded"], r["decoded"], "{ctx}");
        }
    }

    // Multiplexing on the small example (a range that ends the selector's values) reads the same
    // in cantools.
    let mux_path = Path::new(env!("CARGO_TARGET_TMPDIR")).join("mux-example.dbc");
    let mut text = String::new();
    dbc::write_messages(&mut text, Layout::ByKind, &[signals::mux_example()]).unwrap();
    std::fs::write(&mux_path, text).unwrap();
    let script = "import cantools, json, sys\n\
                  m = cantools.database.load_file(sys.argv[1]).messages[0]\n\
                  out = []\n\
                  for d in json.load(sys.stdin):\n\
                  \x20   v = m.decode(bytes.fromhex(d), decode_choices=False)\n\
                  \x20   out.append([v, m.encode(v).hex().upper()])\n\
                  print(json.dumps(out))\n";
    let frames = ["00AA01020304", "0233120FEEDD", "0100000000FF"];
    let out = run_python(
        &python,
        &["-c", script, mux_path.to_str().unwrap()],
        &json!(frames).to_string(),
    );
    let got: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(
        got,
        json!([
            [{"part": 0, "a": 0xAA, "b": 0x0403_0201}, frames[0]],
            [{"part": 2, "c": 0x1233, "d": 0xDD_EE0F}, frames[1]],
            [{"part": 1, "c": 0, "d": 0xFF_0000}, frames[2]],
        ])
    );

    // The documented one-liner: candump -L lines into `cantools decode --frame-id-mask`.
    let log: String = golden
        .iter()
        .map(|p| {
            let (id, data) = p.encode();
            format!("(1700000000.000000) can0 {id:08X}#{}\n", hex(&data))
        })
        .collect();
    let mask = format!("{FRAME_ID_MASK:#010x}");
    let dbc_path = committed_path();
    let out = run_python(
        &python,
        &[
            "-m",
            "cantools",
            "decode",
            "--single-line",
            "--frame-id-mask",
            &mask,
            dbc_path.to_str().unwrap(),
        ],
        &log,
    );
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), golden.len(), "{out}");
    for (line, p) in lines.iter().zip(&golden) {
        let want = cantools_line(p);
        assert!(
            line.ends_with(&format!(" :: {want}")),
            "{line}\nwant {want}"
        );
    }

    // Tells `cargo xtask test` that the round trip ran (a test filter cannot skip it unseen).
    if let Ok(path) = std::env::var("IHEX_CANTOOLS_REPORT") {
        let report = format!(
            "cantools {} decoded and re-encoded {} golden vectors and {} generated frames\n",
            reply["cantools"].as_str().unwrap_or("?"),
            golden.len(),
            generated.len()
        );
        std::fs::write(path, report).unwrap();
    }
}

fn run_python(python: &str, args: &[&str], stdin: &str) -> String {
    let mut child = Command::new(python)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {python}: {e}"));
    let mut input = child.stdin.take().unwrap();
    let stdin = stdin.to_string();
    // Written from a thread: the reply can be larger than the pipe buffer.
    let writer = std::thread::spawn(move || input.write_all(stdin.as_bytes()));
    let out = child.wait_with_output().unwrap();
    writer.join().unwrap().unwrap();
    assert!(
        out.status.success(),
        "{python} {args:?} failed: {}",
        out.status
    );
    String::from_utf8(out.stdout).unwrap()
}
