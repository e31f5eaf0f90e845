//! The seeded plan of a fault run: the faults, their order and durations, and the random commands
//! and island activity around them. The same seed gives the same plan (not the same kernel
//! scheduling: what the system makes of the plan may differ from run to run).
//!
//! Commands are built so the checker can tell their frames apart: every LED command has its own
//! colour and every buzzer command its own tone; power and identify commands repeat by nature.

use std::time::Duration;

use super::trace::{Fault, IslandAction};

/// Environment variable fixing the seed (decimal `u64`); unset = a fresh one, printed.
pub const SEED_ENV: &str = "IHEX_FAULT_SEED";

/// Environment variable asking for a soak: random faults for this many minutes instead of the
/// bounded set (every kind of fault once).
pub const MINUTES_ENV: &str = "IHEX_FAULT_MINUTES";

/// The seed from [`SEED_ENV`], or a fresh random one.
pub fn seed_from_env() -> u64 {
    std::env::var(SEED_ENV)
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or_else(|| fastrand::u64(..))
}

/// The soak length from [`MINUTES_ENV`], if set to a positive number.
pub fn soak_from_env() -> Option<Duration> {
    let m: f64 = std::env::var(MINUTES_ENV).ok()?.trim().parse().ok()?;
    (m.is_finite() && m > 0.0).then(|| Duration::from_secs_f64(m * 60.0))
}

/// The run's clock settings, in real milliseconds (already scaled for the machine).
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    /// The gateway's health period.
    pub health_period_ms: u64,
    /// Missed health checks before a node is lost.
    pub lost_after: u32,
    /// The gateway's command timeout.
    pub command_timeout_ms: u64,
    /// The gateway's docking handshake timeout.
    pub dock_timeout_ms: u64,
    /// MQTT keep-alive of the gateway, seconds (the broker notices a silent client after 1.5×).
    pub keep_alive_s: u64,
    /// How long the gateway waits for a PUBACK or PINGRESP before it gives the link up: scaled
    /// like everything else, so a delayed link (a round trip of two proxy delays) is never taken
    /// for dead.
    pub broker_ack_timeout_ms: u64,
    /// What the machine may add to any expectation.
    pub slack_ms: u64,
    /// The machine's slowness factor (`IHEX_TEST_TIME_SCALE`): durations of activity scale by it.
    pub scale: f64,
}

impl Timing {
    /// Settings for this machine: a fast health period so faults are noticed quickly, stretched by
    /// `IHEX_TEST_TIME_SCALE` like every deadline of the tests.
    pub fn for_this_machine() -> Timing {
        let ms = |v: u64| crate::time::scaled(Duration::from_millis(v)).as_millis() as u64;
        Timing {
            health_period_ms: ms(300),
            lost_after: 3,
            command_timeout_ms: ms(1000),
            dock_timeout_ms: ms(3000),
            keep_alive_s: 5,
            broker_ack_timeout_ms: ms(5000),
            slack_ms: ms(1000),
            scale: ms(1000) as f64 / 1000.0,
        }
    }

    /// `ms` of activity, scaled.
    pub fn ms(&self, ms: u64) -> u64 {
        (ms as f64 * self.scale) as u64
    }
}

/// A command to send.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Command {
    /// What the core's parser reads (no `request_id`, no `ttl_ms`).
    pub action: String,
    /// Its `request_id`, if any.
    pub request_id: Option<String>,
    /// Its `ttl_ms`, if any.
    pub ttl_ms: Option<u64>,
}

impl Command {
    /// The payload as published.
    pub fn payload(&self) -> String {
        let mut p = self
            .action
            .strip_suffix('}')
            .unwrap_or(&self.action)
            .to_string();
        if let Some(r) = &self.request_id {
            p.push_str(&format!(",\"request_id\":\"{r}\""));
        }
        if let Some(t) = self.ttl_ms {
            p.push_str(&format!(",\"ttl_ms\":{t}"));
        }
        p.push('}');
        p
    }
}

/// The nodes commands go to, and what the island looks like for docking.
#[derive(Clone, Debug)]
pub struct Island {
    /// Static elements (hex ids).
    pub statics: Vec<String>,
    /// Mobile elements: (hex id, its own port).
    pub mobiles: Vec<(String, u8)>,
    /// Ports a mobile element may dock on: (static element, port).
    pub dock_ports: Vec<(String, u8)>,
}

/// The seeded random source of a run.
pub struct Plan {
    /// The seed.
    pub seed: u64,
    rng: fastrand::Rng,
    commands: u32,
}

impl Plan {
    /// A plan from `seed`.
    pub fn new(seed: u64) -> Plan {
        Plan {
            seed,
            rng: fastrand::Rng::with_seed(seed),
            commands: 0,
        }
    }

    /// Every kind of fault once, in a seeded order, with seeded durations.
    pub fn every_fault_once(&mut self, t: &Timing, island: &Island) -> Vec<Fault> {
        let mut kinds: Vec<u8> = (0..9).collect();
        self.rng.shuffle(&mut kinds);
        kinds
            .into_iter()
            .map(|k| self.fault(k, t, island))
            .collect()
    }

    /// One random fault.
    pub fn any_fault(&mut self, t: &Timing, island: &Island) -> Fault {
        let k = self.rng.u8(0..9);
        self.fault(k, t, island)
    }

    fn fault(&mut self, kind: u8, t: &Timing, island: &Island) -> Fault {
        let hp = t.health_period_ms;
        // Zombie connections: short enough that neither end's keep-alive notices, or long enough
        // that the broker does (after 1.5 keep-alives of silence; the gateway after a keep-alive plus
        // its acknowledgement bound, or when the proxy passes again and delivers the broker's close).
        let ka = t.keep_alive_s * 1000;
        match kind {
            0 => Fault::BrokerKill {
                down_ms: self.rng.u64(t.ms(200)..=t.ms(2000)),
            },
            1 => Fault::GatewayKill {
                down_ms: self.rng.u64(t.ms(200)..=t.ms(2000)),
            },
            2 => Fault::ProxyCut {
                ms: self.rng.u64(t.ms(200)..=t.ms(2000)),
            },
            3 => Fault::ProxyDelay {
                delay_ms: self.rng.u64(t.ms(50)..=t.ms(500)),
                ms: self.rng.u64(t.ms(1000)..=t.ms(3000)),
            },
            4 => Fault::ProxyHalfOpen {
                ms: self.rng.u64(ka / 10..=ka * 4 / 10),
                noticed: false,
            },
            5 => Fault::ProxyHalfOpen {
                ms: self.rng.u64(ka * 5 / 2..=ka * 3),
                noticed: true,
            },
            6 => Fault::CanDown {
                ms: self.rng.u64(hp..=5 * hp),
            },
            7 => Fault::NodeReset {
                node: self.pick(&island.statics),
            },
            _ => Fault::OffBus {
                node: self.pick(&island.statics),
                ms: self.rng.u64(hp..=(u64::from(t.lost_after) + 2) * hp),
            },
        }
    }

    fn pick(&mut self, from: &[String]) -> String {
        from.get(self.rng.usize(..from.len().max(1)))
            .cloned()
            .unwrap_or_default()
    }

    /// Milliseconds to wait before the next command (scaled).
    pub fn pause_ms(&mut self, t: &Timing) -> u64 {
        t.ms(self.rng.u64(50..=300))
    }

    /// A random command: LED (most), buzzer, power, identify; to one node or `all`; with a
    /// `request_id` most of the time; sometimes with a `ttl_ms`.
    pub fn command(&mut self, island: &Island, t: &Timing) -> Command {
        self.commands += 1;
        let n = self.commands;
        let mut nodes: Vec<String> = island.statics.clone();
        nodes.extend(island.mobiles.iter().map(|(m, _)| m.clone()));
        let roll = self.rng.u8(0..100);
        let node = if self.rng.u8(0..10) == 0 {
            "all".to_string()
        } else {
            self.pick(&nodes)
        };
        let action = match roll {
            // A colour of its own: the frame tells which command it belongs to.
            0..=59 => {
                let c = unique_color(n);
                if self.rng.bool() {
                    format!(
                        r#"{{"cmd":"led","node":"{node}","color":[{},{},{}]}}"#,
                        c[0], c[1], c[2]
                    )
                } else {
                    format!(
                        r#"{{"cmd":"led","node":"{node}","color":[{},{},{}],"blink":{{"period_ms":{},"duty":{}}}}}"#,
                        c[0],
                        c[1],
                        c[2],
                        self.rng.u16(1..=255) * 10,
                        self.rng.u8(1..=99)
                    )
                }
            }
            60..=79 => {
                let freq = 20 + (n * 7919) % 19_980;
                if self.rng.u8(0..3) == 0 {
                    format!(r#"{{"cmd":"buzzer","node":"{node}","mode":"off"}}"#)
                } else if self.rng.bool() {
                    format!(r#"{{"cmd":"buzzer","node":"{node}","mode":"on","freq_hz":{freq}}}"#)
                } else {
                    format!(
                        r#"{{"cmd":"buzzer","node":"{node}","mode":"pattern","freq_hz":{freq},"on_ms":{},"off_ms":{},"count":0}}"#,
                        self.rng.u16(1..=50) * 10,
                        self.rng.u16(1..=50) * 10
                    )
                }
            }
            // Mostly on: a relay left off keeps its mobile elements dark for the rest of the run.
            80..=89 => {
                let on = self.rng.u8(0..4) != 0;
                format!(r#"{{"cmd":"power","node":"{node}","on":{on}}}"#)
            }
            _ => {
                let seconds = self.rng.u8(0..=1);
                format!(r#"{{"cmd":"identify","node":"{node}","seconds":{seconds}}}"#)
            }
        };
        let request_id = (self.rng.u8(0..4) != 0).then(|| format!("c{n}"));
        let ttl_ms = (request_id.is_some() && self.rng.u8(0..4) == 0)
            .then(|| self.rng.u64(t.ms(100)..=t.ms(2000)));
        Command {
            action,
            request_id,
            ttl_ms,
        }
    }

    /// A command to publish retained (always with a `request_id`, an LED colour of its own).
    pub fn retained_command(&mut self, island: &Island) -> Command {
        self.commands += 1;
        let n = self.commands;
        let c = unique_color(n);
        let node = self.pick(&island.statics);
        Command {
            action: format!(
                r#"{{"cmd":"led","node":"{node}","color":[{},{},{}]}}"#,
                c[0], c[1], c[2]
            ),
            request_id: Some(format!("retained{n}")),
            ttl_ms: None,
        }
    }

    /// Some island activity, now and then: undock a docked mobile element, or dock a free one on
    /// a free port. `docked` is where each mobile element is (same order as `island.mobiles`).
    pub fn island_action(
        &mut self,
        island: &Island,
        docked: &[Option<(String, u8)>],
    ) -> Option<IslandAction> {
        if self.rng.u8(0..8) != 0 {
            return None;
        }
        let i = self.rng.usize(..island.mobiles.len().max(1));
        let (mobile, _) = island.mobiles.get(i)?;
        match docked.get(i)? {
            Some(_) => Some(IslandAction::Undock {
                mobile: mobile.clone(),
            }),
            None => {
                let free: Vec<&(String, u8)> = island
                    .dock_ports
                    .iter()
                    .filter(|p| !docked.iter().flatten().any(|d| d == *p))
                    .collect();
                let (at, port) = free.get(self.rng.usize(..free.len().max(1)))?;
                Some(IslandAction::Dock {
                    mobile: mobile.clone(),
                    at: at.clone(),
                    port: *port,
                })
            }
        }
    }
}

/// A colour no other command number gives (the 24-bit number `n` spread over the cube; 0 and
/// white avoided so no command looks like "off" or the identify flash).
pub fn unique_color(n: u32) -> [u8; 3] {
    // 0x9E3779 is odd, so multiplying by it is a bijection modulo 2^24.
    let v = (n.wrapping_mul(0x9E_3779).wrapping_add(0x12_3456)) & 0xFF_FFFF;
    let v = if v == 0 || v == 0xFF_FFFF {
        0x01_0203
    } else {
        v
    };
    [(v >> 16) as u8, (v >> 8) as u8, v as u8]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn island() -> Island {
        Island {
            statics: vec!["111".into(), "112".into()],
            mobiles: vec![("2".into(), 0), ("3".into(), 1)],
            dock_ports: vec![("111".into(), 3), ("112".into(), 2)],
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_plan() {
        let t = Timing::for_this_machine();
        let run = |seed| {
            let mut p = Plan::new(seed);
            let faults = p.every_fault_once(&t, &island());
            let cmds: Vec<String> = (0..50)
                .map(|_| p.command(&island(), &t).payload())
                .collect();
            (faults, cmds)
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7), run(8));
    }

    #[test]
    fn the_bounded_plan_has_every_kind_of_fault() {
        let t = Timing::for_this_machine();
        let faults = Plan::new(1).every_fault_once(&t, &island());
        let names: std::collections::BTreeSet<&str> = faults.iter().map(Fault::name).collect();
        assert_eq!(names.len(), 8, "{faults:?}");
        assert!(faults
            .iter()
            .any(|f| matches!(f, Fault::ProxyHalfOpen { noticed: true, .. })));
        assert!(faults
            .iter()
            .any(|f| matches!(f, Fault::ProxyHalfOpen { noticed: false, .. })));
    }

    #[test]
    fn commands_parse_and_led_colours_never_repeat() {
        let t = Timing::for_this_machine();
        let mut p = Plan::new(3);
        let mut colours = std::collections::BTreeSet::new();
        for n in 1..=100_000 {
            assert!(colours.insert(unique_color(n)), "colour of {n} repeats");
        }
        for _ in 0..500 {
            let c = p.command(&island(), &t);
            let parsed = ihex_gateway_core::command::parse(c.action.as_bytes(), 4096);
            assert!(parsed.is_ok(), "{} does not parse: {parsed:?}", c.action);
            let full: serde_json::Value = serde_json::from_str(&c.payload()).unwrap();
            assert_eq!(full["request_id"].as_str(), c.request_id.as_deref());
        }
    }

    #[test]
    fn island_actions_dock_on_free_ports_only() {
        let mut p = Plan::new(5);
        let isl = island();
        let mut docked: Vec<Option<(String, u8)>> = vec![Some(("111".into(), 3)), None];
        for _ in 0..2000 {
            match p.island_action(&isl, &docked) {
                Some(IslandAction::Dock { mobile, at, port }) => {
                    let i = isl.mobiles.iter().position(|(m, _)| *m == mobile).unwrap();
                    assert!(docked[i].is_none());
                    assert!(!docked.iter().flatten().any(|d| *d == (at.clone(), port)));
                    docked[i] = Some((at, port));
                }
                Some(IslandAction::Undock { mobile }) => {
                    let i = isl.mobiles.iter().position(|(m, _)| *m == mobile).unwrap();
                    assert!(docked[i].take().is_some());
                }
                None => {}
            }
        }
    }
}
