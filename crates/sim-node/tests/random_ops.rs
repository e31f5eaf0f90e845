//! Random sequences of island operations and gateway commands (seeded, reproducible) never panic
//! and never break the physical rules: a mobile element has power only while it is docked on a
//! powered static element whose relay is on, and loop levels match the docks.

use std::time::Duration;

use ihex_proto::test_util::sc_id as id;
use ihex_proto::{
    filter::gateway_filters, BootRole, LedCommand, Message, NodeId, Packet, Port, Rgb,
};
use sim_node::{bus::MemBus, Island, IslandDesc, IslandHandle, Link};

const ISLAND: &str = r#"
[[static]]
id = "111"
ports = 6
[[static]]
id = "112"
ports = 2
[[static]]
id = "120"
unconfigured = true
[[mobile]]
id = "2"
port = 1
[[mobile]]
id = "3"
[[mobile]]
id = "4"
port = 5
dock = { static = "111", port = 0 }
"#;

/// xorshift64*: small, seeded, good enough to pick operations.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Checks the rules; returns how many mobile elements have power (so the run proves it got there).
async fn check_invariants(island: &IslandHandle, step: usize, seed: u64) -> usize {
    let snap = island.snapshot().await.unwrap();
    let at = |n: NodeId| snap.iter().find(|v| v.name == n).unwrap();
    for v in snap.iter().filter(|v| v.role == BootRole::Mobile) {
        let ctx = format!("seed {seed} step {step}: {v:?}");
        if v.powered {
            let (s, _) = v
                .docked
                .unwrap_or_else(|| panic!("powered but undocked; {ctx}"));
            let st = at(s);
            assert!(
                st.powered && st.actuators.relay,
                "powered without a relay; {ctx} on {st:?}"
            );
        }
        let own = v.docked.map_or(0, |_| 0xFF);
        assert_eq!(
            v.loops & own,
            v.loops,
            "own loop closed while undocked; {ctx}"
        );
    }
    for s in snap.iter().filter(|v| v.role == BootRole::Static) {
        let docked: u8 = snap
            .iter()
            .filter_map(|m| m.docked.filter(|d| d.0 == s.name).map(|d| d.1.mask()))
            .fold(0, |a, b| a | b);
        assert_eq!(s.loops, docked, "seed {seed} step {step}: loops of {s:?}");
    }
    snap.iter()
        .filter(|v| v.role == BootRole::Mobile && v.powered)
        .count()
}

async fn run(seed: u64, steps: usize) {
    let desc = IslandDesc::parse(ISLAND).unwrap();
    let bus = MemBus::new();
    let gw = bus.endpoint();
    gw.set_filters(&gateway_filters());
    let island = Island::start(&desc, Link::Mem(bus.clone())).unwrap();
    let statics = [id(0x111), id(0x112), id(0x120)];
    let mobiles = [id(2), id(3), id(4)];
    let all = [statics, mobiles].concat();
    let mut rng = Rng(seed | 1);
    let mut powered_steps = 0;
    for step in 0..steps {
        let pick = |rng: &mut Rng, set: &[NodeId]| set[rng.below(set.len() as u64) as usize];
        let seq = rng.below(256) as u8;
        // Dock and power commands mostly go where they can work (static elements).
        let target = |rng: &mut Rng| {
            if rng.below(4) == 0 {
                pick(rng, &all)
            } else {
                pick(rng, &statics)
            }
        };
        let port = Port::new(rng.below(8) as u8).unwrap();
        // Refusals (wrong element, taken port, no power) are fine: only panics and broken rules fail.
        match rng.below(11) {
            0 | 1 => {
                let (m, s) = (pick(&mut rng, &mobiles), pick(&mut rng, &all));
                let _ = island.dock(m, s, rng.below(8) as u8).await;
            }
            2 => {
                let _ = island.undock(pick(&mut rng, &all)).await;
            }
            3 => {
                let _ = island.power_cycle(pick(&mut rng, &all)).await;
            }
            4 => {
                let _ = island
                    .set_on_bus(pick(&mut rng, &all), rng.below(3) != 0)
                    .await;
            }
            5 => {
                let bytes: Vec<u8> = (0..rng.below(5)).map(|_| rng.next() as u8).collect();
                let _ = island.uart(pick(&mut rng, &all), &bytes).await;
            }
            6 | 7 => {
                let msg = Message::DockConfirm { seq, port };
                gw.send(Packet::command(target(&mut rng), msg).to_frame().unwrap())
                    .await
                    .unwrap();
            }
            8 => {
                let msg = Message::PowerSet {
                    seq,
                    on: rng.below(2) == 0,
                };
                gw.send(Packet::command(target(&mut rng), msg).to_frame().unwrap())
                    .await
                    .unwrap();
            }
            9 => {
                let cmd = LedCommand::Steady {
                    color: Rgb::new(seq, 0, 255),
                    brightness: 200,
                };
                let dest = if rng.below(4) == 0 {
                    NodeId::BROADCAST
                } else {
                    pick(&mut rng, &all)
                };
                let msg = Message::LedSet { seq, cmd };
                gw.send(Packet::command(dest, msg).to_frame().unwrap())
                    .await
                    .unwrap();
            }
            _ => {
                // Raw garbage addressed anywhere: the cores must shrug it off.
                let raw = (rng.next() as u32) & 0x1FFF_FFFF;
                let len = rng.below(9) as usize;
                let data: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
                let id = embedded_can::ExtendedId::new(raw).unwrap();
                let frame = <socketcan::CanFrame as embedded_can::Frame>::new(id, &data).unwrap();
                gw.send(frame).await.unwrap();
            }
        }
        // Let debounce and handshakes run now and then (the clock is paused: this is instant).
        tokio::time::sleep(Duration::from_millis(rng.below(120))).await;
        if check_invariants(&island, step, seed).await > 0 {
            powered_steps += 1;
        }
    }
    assert!(
        powered_steps > 0,
        "seed {seed}: no mobile element ever got power"
    );
    island.shutdown().await;
}

#[tokio::test(start_paused = true)]
async fn random_operations_keep_the_physical_rules() {
    for seed in [1, 2, 3, 0xDEAD_BEEF, 42] {
        run(seed, 300).await;
    }
}
