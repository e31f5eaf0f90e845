//! The fault suite: the gateway's delivery contract (`docs/gateway.md`) under broker and gateway
//! kill -9, a proxy that cuts, delays and half-opens the MQTT connection, the CAN interface going
//! down, node resets and off-bus periods, with random commands and dockings all along
//! (`ihex_tests::fault`). Seeded: `IHEX_FAULT_SEED=N` repeats a plan; `IHEX_FAULT_MINUTES=M` turns
//! the bounded run (every kind of fault once) into a soak (`cargo xtask soak`).
#![cfg(feature = "vcan")]

use std::time::Duration;

use ihex_tests::fault::{check, harness::Rig, plan};
use tokio::time::Instant;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_keeps_its_contract_under_faults() {
    let seed = plan::seed_from_env();
    eprintln!(
        "fault suite: seed {seed} ({}={seed} repeats this plan)",
        plan::SEED_ENV
    );
    let mut rig = Rig::start(seed)
        .await
        .unwrap_or_else(|e| panic!("fault suite seed {seed}: {e}"));
    let started = Instant::now();
    match plan::soak_from_env() {
        None => {
            for f in rig.every_fault_once() {
                eprintln!("fault suite: {f:?}");
                rig.fault(f).await;
            }
        }
        Some(length) => {
            while started.elapsed() < length {
                let f = rig.any_fault();
                eprintln!("fault suite: {f:?}");
                rig.fault(f).await;
            }
        }
    }
    let tail = rig.timing().ms(1000);
    let (trace, logs) = rig.finish(tail).await;
    let path = std::env::temp_dir().join(format!("ihex-faults-{seed}.jsonl"));
    let written = std::fs::write(
        &path,
        trace
            .records
            .iter()
            .map(|r| serde_json::to_string(r).unwrap_or_default() + "\n")
            .collect::<String>(),
    );
    eprintln!(
        "fault suite: {:.0} s, trace {} ({})",
        started.elapsed().as_secs_f64(),
        path.display(),
        match written {
            Ok(()) => "written".to_string(),
            Err(e) => e.to_string(),
        }
    );
    match check::assert_contract(&trace) {
        Ok(report) => eprintln!("fault suite: seed {seed}: {report}"),
        Err(text) => panic!(
            "fault suite seed {seed} ({}={seed} repeats this plan):\n{text}\ngateway logs:\n{logs}",
            plan::SEED_ENV
        ),
    }
    let _ = Duration::ZERO;
}
