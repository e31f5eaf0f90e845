//! The `sim-node` console: control commands typed on stdin, and one readable line per change.

use std::fmt::Write as _;

use ihex_proto::NodeId;
use ihex_sc_core::{Actuators, BuzzerOutput};

use crate::{desc::parse_node_id, island::NodeView, IslandError, IslandEvent, IslandHandle};

/// Help text for the console commands.
pub const HELP: &str = "\
commands (node ids in hex, as in the island file):
  dock MOBILE STATIC PORT   dock a mobile element on a static element's port
  undock MOBILE             pull a mobile element off its dock
  cycle NODE                power-cycle an element (a fresh boot)
  off NODE | on NODE        take an element off the bus / put it back
  uart NODE BYTE...         write bytes (hex) to its configuration UART, print the reply
                            e.g. `uart 111 b0 00` (query), `uart 111 a1 23` (set id 123)
  show                      every element's state
  sleep MS                  pause reading commands (for scripts piped into stdin)
  help                      this text
  quit                      stop the island and exit";

/// One console command.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Command {
    /// `dock MOBILE STATIC PORT`.
    Dock {
        /// Mobile element.
        mobile: NodeId,
        /// Static element.
        static_id: NodeId,
        /// Port of the static element.
        port: u8,
    },
    /// `undock MOBILE`.
    Undock(NodeId),
    /// `cycle NODE`.
    Cycle(NodeId),
    /// `on NODE` / `off NODE`.
    Bus(NodeId, bool),
    /// `uart NODE BYTE...`.
    Uart(NodeId, Vec<u8>),
    /// `show`.
    Show,
    /// `sleep MS`: wait before the next command (scripts).
    Sleep(u64),
    /// `help`.
    Help,
    /// `quit` / `exit`.
    Quit,
}

/// Parses one console line; `Ok(None)` for a blank line or a `#` comment.
pub fn parse(line: &str) -> Result<Option<Command>, String> {
    let words: Vec<&str> = line
        .split('#')
        .next()
        .unwrap_or("")
        .split_whitespace()
        .collect();
    let Some((&verb, args)) = words.split_first() else {
        return Ok(None);
    };
    let node = |i: usize| -> Result<NodeId, String> {
        let w = args
            .get(i)
            .ok_or_else(|| format!("`{verb}` needs more arguments (try `help`)"))?;
        parse_node_id(w)
    };
    let arity = |n: usize| {
        if args.len() == n {
            Ok(())
        } else {
            Err(format!(
                "`{verb}` takes {n} argument(s), got {} (try `help`)",
                args.len()
            ))
        }
    };
    let cmd = match verb.to_ascii_lowercase().as_str() {
        "dock" => {
            arity(3)?;
            let port = args[2]
                .parse::<u8>()
                .map_err(|_| format!("port {:?} is not a number", args[2]))?;
            Command::Dock {
                mobile: node(0)?,
                static_id: node(1)?,
                port,
            }
        }
        "undock" => arity(1).and_then(|_| node(0)).map(Command::Undock)?,
        "cycle" => arity(1).and_then(|_| node(0)).map(Command::Cycle)?,
        "off" => arity(1)
            .and_then(|_| node(0))
            .map(|n| Command::Bus(n, false))?,
        "on" => arity(1)
            .and_then(|_| node(0))
            .map(|n| Command::Bus(n, true))?,
        "uart" => {
            if args.len() < 2 {
                return Err("`uart` needs a node and at least one byte (try `help`)".into());
            }
            let bytes = args[1..]
                .iter()
                .map(|b| {
                    u8::from_str_radix(b.trim_start_matches("0x"), 16)
                        .map_err(|_| format!("{b:?} is not a hex byte"))
                })
                .collect::<Result<Vec<u8>, String>>()?;
            Command::Uart(node(0)?, bytes)
        }
        "show" => arity(0).map(|_| Command::Show)?,
        "sleep" => {
            arity(1)?;
            let ms = args[0]
                .parse::<u64>()
                .map_err(|_| format!("{:?} is not milliseconds", args[0]))?;
            Command::Sleep(ms)
        }
        "help" | "?" => Command::Help,
        "quit" | "exit" => Command::Quit,
        other => return Err(format!("unknown command `{other}` (try `help`)")),
    };
    Ok(Some(cmd))
}

/// Carries out a command on the island; returns the lines to print. `Quit` does nothing here (the
/// caller stops reading).
pub async fn execute(island: &IslandHandle, cmd: Command) -> Result<Vec<String>, IslandError> {
    let none = |r: Result<(), IslandError>| r.map(|_| Vec::new());
    match cmd {
        Command::Dock {
            mobile,
            static_id,
            port,
        } => none(island.dock(mobile, static_id, port).await),
        Command::Undock(m) => none(island.undock(m).await),
        Command::Cycle(n) => none(island.power_cycle(n).await),
        Command::Bus(n, on) => none(island.set_on_bus(n, on).await),
        Command::Uart(n, bytes) => {
            let reply = island.uart(n, &bytes).await?;
            let hex: Vec<String> = reply.iter().map(|b| format!("{b:02x}")).collect();
            let hex = if hex.is_empty() {
                "(none)".to_string()
            } else {
                hex.join(" ")
            };
            Ok(vec![format!("{:>3}  uart reply: {hex}", name(n))])
        }
        Command::Show => Ok(island.snapshot().await?.iter().map(view_line).collect()),
        Command::Sleep(ms) => {
            tokio::time::sleep(std::time::Duration::from_millis(ms)).await;
            Ok(Vec::new())
        }
        Command::Help => Ok(HELP.lines().map(String::from).collect()),
        Command::Quit => Ok(Vec::new()),
    }
}

/// Actuators as a person reads them: `LED #ff0000 blink 500ms/50%  buzzer off  relay ON`.
pub fn describe(a: &Actuators) -> String {
    let mut s = String::new();
    let d = a.led.duty;
    if (d.r, d.g, d.b) == (0, 0, 0) {
        s.push_str("LED off");
    } else {
        let _ = write!(s, "LED #{:02x}{:02x}{:02x}", d.r, d.g, d.b);
        match a.led.blink {
            Some((period, pct)) => {
                let _ = write!(s, " blink {period}ms/{pct}%");
            }
            None => s.push_str(" steady"),
        }
    }
    match a.buzzer {
        BuzzerOutput::Off => s.push_str("  buzzer off"),
        BuzzerOutput::Tone { freq_hz } => {
            let _ = write!(s, "  buzzer {freq_hz}Hz");
        }
        BuzzerOutput::Pattern {
            freq_hz,
            on_ms,
            off_ms,
            count,
        } => {
            let _ = write!(s, "  buzzer {freq_hz}Hz {on_ms}/{off_ms}ms ");
            if count == 0 {
                s.push_str("forever");
            } else {
                let _ = write!(s, "x{count}");
            }
        }
    }
    s.push_str(if a.relay { "  relay ON" } else { "  relay off" });
    s
}

/// One line for an island event.
pub fn event_line(e: &IslandEvent) -> String {
    match *e {
        IslandEvent::Actuators { node, actuators } => {
            format!("{:>3}  {}", name(node), describe(&actuators))
        }
        IslandEvent::Power { node, on } => {
            format!(
                "{:>3}  power {}",
                name(node),
                if on { "ON (boot)" } else { "off" }
            )
        }
        IslandEvent::Bus { node, on } => {
            format!(
                "{:>3}  {} the bus",
                name(node),
                if on { "back on" } else { "off" }
            )
        }
        IslandEvent::Docked {
            mobile,
            static_id,
            port,
        } => {
            format!("{:>3}  docked on {static_id} port {port}", name(mobile))
        }
        IslandEvent::Undocked {
            mobile,
            static_id,
            port,
        } => {
            format!("{:>3}  undocked from {static_id} port {port}", name(mobile))
        }
        IslandEvent::IdStored { node, id } => {
            format!("{:>3}  stored node id {id}", name(node))
        }
    }
}

/// A node ID as text (`NodeId`'s `Display` ignores widths).
fn name(id: NodeId) -> String {
    id.to_string()
}

/// One line of `show` for an element.
pub fn view_line(v: &NodeView) -> String {
    let role = match v.role {
        ihex_proto::BootRole::Static => "static",
        ihex_proto::BootRole::Mobile => "mobile",
    };
    let id = v.node_id.map_or("unset".to_string(), |i| i.to_string());
    let mut s = format!(
        "{:>3}  {role} id={id} fw={}",
        name(v.name),
        v.firmware.version
    );
    if !v.powered {
        s.push_str("  unpowered");
    } else {
        let _ = write!(s, "  {}", describe(&v.actuators));
    }
    if !v.on_bus {
        s.push_str("  OFF-BUS");
    }
    if v.loops != 0 {
        let _ = write!(s, "  loops={:08b}", v.loops);
    }
    if let Some((st, p)) = v.docked {
        let _ = write!(s, "  docked on {st} port {p}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::sc_id as id;
    use ihex_proto::Rgb;
    use ihex_sc_core::LedOutput;

    #[test]
    fn parses_every_command() {
        assert_eq!(
            parse("dock 2 111 3").unwrap(),
            Some(Command::Dock {
                mobile: id(2),
                static_id: id(0x111),
                port: 3
            })
        );
        assert_eq!(parse("  undock 2 ").unwrap(), Some(Command::Undock(id(2))));
        assert_eq!(parse("cycle 111").unwrap(), Some(Command::Cycle(id(0x111))));
        assert_eq!(
            parse("off 111").unwrap(),
            Some(Command::Bus(id(0x111), false))
        );
        assert_eq!(
            parse("ON 111").unwrap(),
            Some(Command::Bus(id(0x111), true))
        );
        assert_eq!(
            parse("uart 111 a1 0x23").unwrap(),
            Some(Command::Uart(id(0x111), vec![0xa1, 0x23]))
        );
        assert_eq!(parse("show").unwrap(), Some(Command::Show));
        assert_eq!(parse("sleep 250").unwrap(), Some(Command::Sleep(250)));
        assert_eq!(parse("help").unwrap(), Some(Command::Help));
        assert_eq!(parse("quit").unwrap(), Some(Command::Quit));
        assert_eq!(parse("").unwrap(), None);
        assert_eq!(parse("# a comment").unwrap(), None);
    }

    #[test]
    fn bad_lines_say_what_is_wrong() {
        for (line, needle) in [
            ("dock 2 111", "takes 3"),
            ("dock 2 111 x", "not a number"),
            ("undock zz", "1 to 3 hex digits"),
            ("cycle fff", "outside"),
            ("uart 111", "at least one byte"),
            ("uart 111 1ff", "not a hex byte"),
            ("fly 111", "unknown command"),
            ("show 1", "takes 0"),
            ("sleep soon", "not milliseconds"),
        ] {
            let err = parse(line).unwrap_err();
            assert!(err.contains(needle), "{line:?}: {err}");
        }
    }

    #[test]
    fn describes_actuators_readably() {
        let a = Actuators {
            led: LedOutput {
                duty: Rgb::new(255, 0, 0),
                blink: Some((500, 50)),
            },
            buzzer: BuzzerOutput::Off,
            relay: true,
        };
        assert_eq!(
            describe(&a),
            "LED #ff0000 blink 500ms/50%  buzzer off  relay ON"
        );
        let b = Actuators {
            led: LedOutput::default(),
            buzzer: BuzzerOutput::Pattern {
                freq_hz: 2000,
                on_ms: 100,
                off_ms: 400,
                count: 3,
            },
            relay: false,
        };
        assert_eq!(
            describe(&b),
            "LED off  buzzer 2000Hz 100/400ms x3  relay off"
        );
        let e = IslandEvent::Actuators {
            node: id(0x111),
            actuators: a,
        };
        assert_eq!(
            event_line(&e),
            "111  LED #ff0000 blink 500ms/50%  buzzer off  relay ON"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_script_drives_an_island() {
        use crate::{bus::MemBus, Island, IslandDesc, Link};
        let desc = IslandDesc::parse(
            "[[static]]\nid = \"111\"\nports = 4\nfirmware = \"1.4.0\"\n\
             [[static]]\nid = \"120\"\nunconfigured = true\nfirmware = \"2.0.1-rc.1\"\n\
             [[mobile]]\nid = \"2\"\n",
        )
        .unwrap();
        let island = Island::start(&desc, Link::Mem(MemBus::new())).unwrap();
        let mut out = Vec::new();
        for line in [
            "dock 2 111 3",
            "sleep 100",
            "off 111",
            "uart 120 a1 23",
            "uart 120 b0 00",
            "show",
        ] {
            let cmd = parse(line).unwrap().unwrap();
            out.extend(execute(&island, cmd).await.unwrap());
        }
        assert_eq!(
            out,
            [
                "120  uart reply: 51 23".to_string(),
                "120  uart reply: 51 23".to_string(),
                "111  static id=111 fw=1.4.0  LED off  buzzer off  relay off  OFF-BUS  loops=00001000"
                    .to_string(),
                "120  static id=123 fw=2.0.1  LED off  buzzer off  relay off".to_string(),
                format!(
                    "  2  mobile id=2 fw={}  unpowered  loops=00000001  docked on 111 port 3",
                    crate::desc::DEFAULT_FIRMWARE
                ),
            ]
        );
        let err = execute(&island, parse("undock 111").unwrap().unwrap())
            .await
            .unwrap_err();
        assert_eq!(err.to_string(), "\"111\" is not a mobile element");
        island.shutdown().await;
    }
}
