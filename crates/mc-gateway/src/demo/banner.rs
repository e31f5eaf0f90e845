//! The copy-paste instructions printed when the demo starts, written for the island actually loaded:
//! every element it names exists, and the docking it suggests can happen (a free mobile element on a
//! free port of a static element).

use std::fmt::Write as _;
use std::path::Path;

use ihex_proto::NodeId;
use sim_node::IslandDesc;

use crate::topic::Topics;

/// What the banner suggests docking: a mobile element, and where.
struct DockExample {
    mobile: NodeId,
    static_id: NodeId,
    port: u8,
    /// The mobile element is docked there at start: undock first, then dock it back.
    undock_first: bool,
}

/// The ports of `static_id` no mobile element is docked on at start.
fn free_ports(desc: &IslandDesc, static_id: NodeId, ports: u8) -> impl Iterator<Item = u8> + '_ {
    (0..ports).filter(move |&p| {
        !desc.mobiles.iter().any(|m| {
            m.dock
                .is_some_and(|(s, sp)| s == static_id && sp.get() == p)
        })
    })
}

fn dock_example(desc: &IslandDesc) -> Option<DockExample> {
    let configured = |m: &&sim_node::desc::MobileDesc| m.configured;
    if let Some(m) = desc
        .mobiles
        .iter()
        .filter(configured)
        .find(|m| m.dock.is_none())
    {
        // The last static element with a node ID and a free port: the first one usually has the
        // docked example, and one without an ID is silent on the bus (its docking reaches no one).
        let (static_id, port) = desc
            .statics
            .iter()
            .rev()
            .filter(|s| s.configured)
            .find_map(|s| {
                let port = free_ports(desc, s.id, s.ports).next()?;
                Some((s.id, port))
            })?;
        return Some(DockExample {
            mobile: m.id,
            static_id,
            port,
            undock_first: false,
        });
    }
    let m = desc
        .mobiles
        .iter()
        .filter(configured)
        .find(|m| m.dock.is_some())?;
    let (static_id, port) = m.dock?;
    Some(DockExample {
        mobile: m.id,
        static_id,
        port: port.get(),
        undock_first: true,
    })
}

/// What the banner describes.
pub struct Banner<'a> {
    /// The gateway's topics.
    pub topics: &'a Topics,
    /// The embedded broker's address.
    pub host: &'a str,
    /// The embedded broker's port.
    pub port: u16,
    /// The simulated island.
    pub desc: &'a IslandDesc,
    /// The island file it was loaded from (`None`: the built-in island).
    pub file: Option<&'a Path>,
    /// The island view's address, when it runs.
    pub view_url: Option<&'a str>,
    /// The SiLA server's address (`grpcs://…`, or `grpc://…` in plaintext), when it runs.
    pub sila_url: Option<&'a str>,
    /// The JSON log file, when there is one.
    pub log: Option<&'a Path>,
}

/// The banner for what `b` describes.
pub fn banner(b: &Banner<'_>) -> String {
    let Banner {
        topics,
        host,
        port,
        desc,
        file,
        view_url,
        sila_url,
        log,
    } = *b;
    let b = format!("-h {host} -p {port}");
    let (events, cmds, sim) = (&topics.events, &topics.commands, &topics.sim);
    let states = format!("{}/+/state", topics.node_state_root);
    let statics: Vec<NodeId> = desc
        .statics
        .iter()
        .filter(|s| s.configured)
        .map(|s| s.id)
        .collect();
    let list = |ids: &[String]| {
        if ids.is_empty() {
            "none".to_owned()
        } else {
            ids.join(", ")
        }
    };
    let static_names: Vec<String> = statics.iter().map(ToString::to_string).collect();
    let mobile_names: Vec<String> = desc
        .mobiles
        .iter()
        .filter(|m| m.configured)
        .map(|m| match m.dock {
            Some((s, p)) => format!("{} (docked on {s} port {p})", m.id),
            None => format!("{} (free)", m.id),
        })
        .collect();
    let unconfigured = desc.statics.iter().filter(|s| !s.configured).count()
        + desc.mobiles.iter().filter(|m| !m.configured).count();
    let source = match file {
        Some(f) => format!("from {}", f.display()),
        None => "built in".to_owned(),
    };

    let mut t = String::new();
    // Writing to a String cannot fail.
    let _ = writeln!(t);
    let _ = writeln!(
        t,
        "iHEX gateway demo: embedded MQTT broker on {host}:{port}, simulated island ({source}):"
    );
    let _ = writeln!(
        t,
        "  static {}; mobile {}",
        list(&static_names),
        list(&mobile_names)
    );
    if unconfigured > 0 {
        let _ = writeln!(
            t,
            "  and {unconfigured} board(s) without a node ID yet (docs/sim-node.md, ihex-provision)"
        );
    }
    let _ = writeln!(t);
    let docked: Vec<String> = desc
        .mobiles
        .iter()
        .filter(|m| m.configured)
        .filter_map(|m| m.dock.map(|(s, p)| format!("{} on {s} port {p}", m.id)))
        .collect();
    let _ = writeln!(
        t,
        "The island booted (and {}) before anyone could subscribe: those events are gone, but the",
        if docked.is_empty() {
            "its elements came online".to_owned()
        } else {
            format!("docked {}", docked.join(", "))
        }
    );
    let _ = writeln!(t, "retained state topics below show it.");
    let _ = writeln!(t);
    if let Some(url) = view_url {
        let _ = writeln!(t, "See the island live in a browser: {url}");
    }
    if let Some(url) = sila_url {
        let _ = writeln!(
            t,
            "Lab orchestrators reach it as a SiLA 2 server at {url} (found over mDNS; docs/sila.md)"
        );
    }
    let _ = writeln!(t, "Watch every event:");
    let _ = writeln!(t, "  mosquitto_sub {b} -t '{events}' -v");
    let _ = writeln!(
        t,
        "Watch the retained node states and the gateway's availability:"
    );
    let _ = writeln!(
        t,
        "  mosquitto_sub {b} -t '{states}' -t '{}' -v",
        topics.availability
    );
    if let Some(first) = statics.first() {
        let _ = writeln!(t, "Turn node {first}'s LEDs red:");
        let _ = writeln!(
            t,
            "  mosquitto_pub {b} -q 1 -t '{cmds}' -m '{{\"cmd\":\"led\",\"node\":\"{first}\",\"color\":\"red\"}}'"
        );
    }
    let _ = writeln!(t, "List the nodes:");
    let _ = writeln!(
        t,
        "  mosquitto_pub {b} -q 1 -t '{cmds}' -m '{{\"cmd\":\"list\"}}'"
    );
    if let Some(d) = dock_example(desc) {
        let dock = format!(
            "  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"dock\",\"mobile\":\"{}\",\"static\":\"{}\",\"port\":{}}}'",
            d.mobile, d.static_id, d.port
        );
        let undock = format!(
            "  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"undock\",\"mobile\":\"{}\"}}'",
            d.mobile
        );
        if d.undock_first {
            let _ = writeln!(
                t,
                "Undock mobile {} (publishes connection_removed), then dock it back on {} port {} (new_connection):",
                d.mobile, d.static_id, d.port
            );
            let _ = writeln!(t, "{undock}\n{dock}");
        } else {
            let _ = writeln!(
                t,
                "Dock mobile {} on port {} of {} (publishes new_connection), then undock it (connection_removed):",
                d.mobile, d.port, d.static_id
            );
            let _ = writeln!(t, "{dock}\n{undock}");
        }
    }
    if let Some(last) = statics.last() {
        let _ = writeln!(
            t,
            "Take {last} off the bus (node_lost after a few health checks) and back (node_online):"
        );
        for name in ["off_bus", "on_bus"] {
            let _ = writeln!(
                t,
                "  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"{name}\",\"node\":\"{last}\"}}'"
            );
        }
    }
    // The island prefix of the topics (the firmware upload topic always has one name), for
    // ihex-provision's --island.
    let island = topics
        .fw_upload
        .strip_suffix(ihex_gateway_core::topic::FW_UPLOAD)
        .and_then(|p| p.strip_suffix('/'))
        .map_or_else(String::new, |i| format!(" --island {i}"));
    let _ = writeln!(
        t,
        "Update every element's firmware with a demo image (docs/firmware-update.md):\n  \
         ihex-provision fw demo-image --version 0.2.0 && \
         ihex-provision fw update sim-fw-0.2.0.img --broker {host}:{port}{island}"
    );
    let _ = writeln!(
        t,
        "Mistakes on '{sim}' are answered on '{events}' (sim_rejected, sim_result)."
    );
    match log {
        Some(log) => {
            let _ = writeln!(
                t,
                "The JSON log: {} (this gateway's lines have \"pid\":{}).",
                log.display(),
                std::process::id()
            );
        }
        None => {
            let _ = writeln!(
                t,
                "No JSON log file (--log-dir -): the log is on stderr only."
            );
        }
    }
    let _ = write!(
        t,
        "Ctrl-C stops the gateway. Commands: docs/mqtt-api.md; options: mc-gateway --help, docs/gateway.md."
    );
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_banner_uses_the_configured_topics() {
        let topics = Topics::new(Some("lab"), "CommandsTopic", "EventsTopic", "a", "n");
        let desc = IslandDesc::parse(super::super::BUILTIN_ISLAND).unwrap();
        let plain = Banner {
            topics: &topics,
            host: "127.0.0.1",
            port: 1884,
            desc: &desc,
            file: None,
            view_url: None,
            sila_url: None,
            log: None,
        };
        let text = banner(&plain);
        assert!(!text.contains("browser"), "{text}");
        assert!(!text.contains("SiLA"), "{text}");
        assert!(text.contains("No JSON log file"), "{text}");
        assert!(
            text.contains("ihex-provision fw demo-image --version 0.2.0 && ihex-provision fw update sim-fw-0.2.0.img --broker 127.0.0.1:1884 --island lab"),
            "{text}"
        );
        let text = banner(&Banner {
            view_url: Some("http://127.0.0.1:8080/"),
            sila_url: Some("grpcs://127.0.0.1:50052"),
            log: Some(Path::new("/var/log/ihex/mc-gateway.2026-11-25.jsonl")),
            ..plain
        });
        assert!(
            text.contains(
                "Lab orchestrators reach it as a SiLA 2 server at grpcs://127.0.0.1:50052 (found \
                 over mDNS; docs/sila.md)\n"
            ),
            "{text}"
        );
        assert!(
            text.contains(&format!(
                "The JSON log: /var/log/ihex/mc-gateway.2026-11-25.jsonl (this gateway's lines have \"pid\":{}).",
                std::process::id()
            )),
            "{text}"
        );
        assert!(
            text.contains("See the island live in a browser: http://127.0.0.1:8080/\n"),
            "{text}"
        );
        assert!(text.contains("mosquitto_pub -h 127.0.0.1 -p 1884 -q 1 -t 'lab/CommandsTopic'"));
        assert!(text.contains("mosquitto_sub -h 127.0.0.1 -p 1884 -t 'lab/EventsTopic' -v"));
        assert!(text.contains("-t 'lab/ihex/sim'"));
        assert!(text.contains("docked 2 on 111 port 3"), "{text}");
    }

    /// Every `ihex/sim` command the banner prints works on the island it was printed for, and the
    /// LED command names one of its elements: for the built-in island and every example island.
    #[tokio::test]
    async fn the_banner_commands_work_on_every_example_island() {
        use sim_node::{bus::MemBus, link::Link, Island};
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../examples/islands");
        let mut islands: Vec<(Option<std::path::PathBuf>, IslandDesc)> = vec![(
            None,
            IslandDesc::parse(super::super::BUILTIN_ISLAND).unwrap(),
        )];
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "toml") {
                let desc = IslandDesc::load(&path).unwrap();
                islands.push((Some(path), desc));
            }
        }
        assert!(
            islands.len() >= 3,
            "the example islands were not found in {dir:?}"
        );
        let topics = Topics::seed();
        for (file, desc) in islands {
            let text = banner(&Banner {
                topics: &topics,
                host: "127.0.0.1",
                port: 1883,
                desc: &desc,
                file: file.as_deref(),
                view_url: None,
                sila_url: None,
                log: None,
            });
            let island = Island::start(&desc, Link::Mem(MemBus::new())).unwrap();
            let payload = |line: &str| {
                line.split(" -m '")
                    .nth(1)
                    .and_then(|s| s.strip_suffix('\''))
                    .unwrap_or_else(|| panic!("no payload in {line}"))
                    .to_owned()
            };
            let mut sims = 0;
            for line in text.lines().filter(|l| l.contains("-t 'ihex/sim' -m")) {
                let answer = super::super::sim::handle(&island, payload(line).as_bytes()).await;
                let ihex_gateway_core::event::Event::SimResult(r) = answer else {
                    panic!("{file:?}: {line}: {answer:?}");
                };
                assert_eq!(
                    r.result,
                    ihex_gateway_core::event::Outcome::Ok,
                    "{file:?}: {line}: {r:?}"
                );
                // A docking only reaches the gateway (new_connection) through a static element that
                // has a node ID: one without is silent on the bus.
                let v: serde_json::Value = serde_json::from_str(&payload(line)).unwrap();
                if let Some(s) = v["static"].as_str() {
                    let s: NodeId = s.parse().unwrap();
                    assert!(
                        desc.statics.iter().any(|st| st.id == s && st.configured),
                        "{file:?}: {line} docks onto a board without a node ID"
                    );
                }
                sims += 1;
            }
            assert!(
                sims >= 4,
                "{file:?}: only {sims} simulation commands in\n{text}"
            );
            for line in text.lines().filter(|l| l.contains("\"cmd\":\"led\"")) {
                let v: serde_json::Value = serde_json::from_str(&payload(line)).unwrap();
                let node: NodeId = v["node"].as_str().unwrap().parse().unwrap();
                assert!(
                    desc.statics.iter().any(|s| s.id == node && s.configured),
                    "{file:?}: {line}"
                );
            }
            assert!(text.contains("retained state topics"), "{text}");
            island.shutdown().await;
        }
    }
}
