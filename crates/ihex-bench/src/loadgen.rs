//! The MQTT load generator off the gateway's CPU: `ihex-bench loadgen` runs beside the broker (on
//! the host, when the live part runs in the microVM) and publishes the live part's commands and bare
//! ingress messages there, on request, so that only the gateway and the nodes' side share the VM's
//! vCPU. The live part asks over the broker itself ([`Remote`]); the generator counts the commands'
//! answers where it reads them and sends the counts back.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use rumqttc::QoS;
use serde::{Deserialize, Serialize};

use crate::forward;
use crate::live::{answers, bare_message, led_command, led_frame, paced, Mqtt, BARE_IN};

/// Requests to the generator, JSON [`Request`].
const RUN: &str = "ihex-bench/load/run";
/// Its answers, JSON [`Done`].
const DONE: &str = "ihex-bench/load/done";
/// The answers' quiet period: the generator stops counting when none came for this long.
const QUIET: Duration = Duration::from_secs(2);

/// What to publish.
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub(crate) enum Load {
    /// Nothing: a request whose answer says the generator is subscribed and listening.
    Ping,
    /// `led` commands with the indices `base..base + count` on `CommandsTopic`; their
    /// `command_result`s are counted.
    Commands { base: u32 },
    /// Bare messages of `len` bytes on the bare ingress topic (nobody answers them).
    Bare { len: usize },
    /// The `LedSet` frames of commands `base..base + count`, for the plain forwarder
    /// ([`crate::forward`]; nobody answers them).
    Raw { base: u32 },
}

impl Load {
    /// Publication `k` of this load: its topic and payload (`None`: a ping publishes nothing).
    fn publication(self, k: u32) -> Result<Option<(&'static str, Vec<u8>)>> {
        Ok(Some(match self {
            Load::Ping => return Ok(None),
            Load::Commands { base } => ("CommandsTopic", led_command(base + k).into_bytes()),
            Load::Bare { len } => (BARE_IN, bare_message(k, len)),
            Load::Raw { base } => (
                forward::TOPIC,
                forward::message(&led_frame(base + k)?).into_bytes(),
            ),
        }))
    }
}

/// One request: `count` publications of `load` at `rate` per second (`None`: back to back).
#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
pub(crate) struct Request {
    pub id: u32,
    pub load: Load,
    pub count: usize,
    pub rate: Option<f64>,
}

/// What the generator did for request `id`.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub(crate) struct Done {
    pub id: u32,
    /// Publications handed to the client.
    pub sent: usize,
    /// Seconds the publishing took.
    pub secs: f64,
    /// Commands answered `ok`.
    pub results: usize,
    /// Commands answered otherwise, with the first reason.
    pub note: Option<String>,
    /// Why the request could not be carried out.
    pub error: Option<String>,
}

/// `ihex-bench loadgen`: serves requests until the process is killed.
pub(crate) fn serve(broker: SocketAddr) -> Result<()> {
    let mqtt = Mqtt::connect_as("ihex-bench-loadgen", broker, &[RUN, "EventsTopic"])?;
    println!("loadgen: waiting for requests on {RUN} at {broker}");
    loop {
        let Some((_, topic, payload)) = mqtt.recv(Duration::from_secs(3600)) else {
            continue;
        };
        if topic != RUN {
            continue;
        }
        let done = match serde_json::from_slice::<Request>(&payload) {
            Ok(r) => carry_out(&mqtt, r),
            Err(e) => Done {
                error: Some(format!("not a request ({e})")),
                ..Done::default()
            },
        };
        mqtt.client
            .publish(DONE, QoS::AtLeastOnce, false, serde_json::to_vec(&done)?)?;
    }
}

fn carry_out(mqtt: &Mqtt, r: Request) -> Done {
    let mut done = Done {
        id: r.id,
        ..Done::default()
    };
    mqtt.drain();
    if let Load::Ping = r.load {
        return done;
    }
    let publish = |k: u32| -> Result<()> {
        if let Some((topic, payload)) = r.load.publication(k)? {
            mqtt.client
                .publish(topic, QoS::AtLeastOnce, false, payload)?;
        }
        Ok(())
    };
    let sent = match r.rate {
        Some(rate) => paced(r.count, rate, None, publish),
        None => {
            let t0 = Instant::now();
            (0..r.count as u32)
                .try_for_each(publish)
                .map(|()| (r.count, t0.elapsed().as_secs_f64()))
        }
    };
    match sent {
        Ok((sent, secs)) => {
            done.sent = sent;
            done.secs = secs;
        }
        Err(e) => {
            done.error = Some(format!("publishing: {e:#}"));
            return done;
        }
    }
    if let Load::Commands { .. } = r.load {
        (done.results, done.note) = answers(mqtt, done.sent, QUIET);
    }
    done
}

/// The live part's side: asks the generator at the same broker for loads and waits for them.
pub(crate) struct Remote {
    mqtt: Mqtt,
    next_id: u32,
}

impl Remote {
    /// Connects and waits (up to 30 s) until the generator answers a ping.
    pub(crate) fn connect(broker: SocketAddr) -> Result<Remote> {
        let mqtt = Mqtt::connect_as("ihex-bench-remote", broker, &[DONE])?;
        let mut remote = Remote { mqtt, next_id: 1 };
        for _ in 0..30 {
            match remote.ask(Load::Ping, 0, None, Duration::from_secs(1)) {
                Ok(_) => return Ok(remote),
                Err(_) => continue,
            }
        }
        bail!(
            "no load generator answered on {DONE} at {broker} within 30 s \
             (`cargo xtask bench` starts `ihex-bench loadgen` beside the host's broker)"
        )
    }

    /// Carries out `count` publications of `load` at `rate` there; returns when they were
    /// published (and, for commands, answered or quiet for 2 s).
    pub(crate) fn run(&mut self, load: Load, count: usize, rate: Option<f64>) -> Result<Done> {
        let publishing = rate.map_or(count as f64 * 0.01, |r| count as f64 / r);
        let wait = Duration::from_secs_f64(publishing) + QUIET + Duration::from_secs(60);
        let done = self.ask(load, count, rate, wait)?;
        if let Some(e) = done.error {
            bail!("the load generator: {e}");
        }
        Ok(done)
    }

    fn ask(&mut self, load: Load, count: usize, rate: Option<f64>, wait: Duration) -> Result<Done> {
        let id = self.next_id;
        self.next_id += 1;
        let request = Request {
            id,
            load,
            count,
            rate,
        };
        self.mqtt.drain();
        self.mqtt
            .client
            .publish(RUN, QoS::AtLeastOnce, false, serde_json::to_vec(&request)?)?;
        let deadline = Instant::now() + wait;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Some((_, topic, payload)) = self.mqtt.recv(left) else {
                bail!("the load generator did not answer request {id} within {wait:?}");
            };
            if topic != DONE {
                continue;
            }
            let done: Done =
                serde_json::from_slice(&payload).context("the load generator's answer")?;
            if done.id == id {
                return Ok(done);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_read_back_as_written() {
        for load in [
            Load::Ping,
            Load::Commands { base: 7 },
            Load::Bare { len: 42 },
            Load::Raw { base: 9 },
        ] {
            let r = Request {
                id: 3,
                load,
                count: 10,
                rate: Some(250.0),
            };
            let back: Request = serde_json::from_slice(&serde_json::to_vec(&r).unwrap()).unwrap();
            assert_eq!(format!("{back:?}"), format!("{r:?}"));
        }
    }
}
