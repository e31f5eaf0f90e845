//! The gateway as a program, in two steps (mini-redis' `main` + `server::run`):
//! [`Gateway::build`] makes and checks every resource — the CAN link (first socket open), the MQTT
//! options, and in the demo the embedded broker, the simulated island and its control client — and
//! [`Gateway::run`] only runs them: the CAN tasks, the MQTT task, and the core loop, one task that
//! owns the [`Bridge`], feeds it inputs and timeouts and carries out its outputs without waiting.
//! The loop takes every input already waiting (up to `BATCH` of a kind) before it carries out the
//! outputs, so a busy bus costs one turn of the loop per batch of frames, not per frame.
//! Every channel is bounded, and what gives when one is full is the bridge's choice: frames wait in
//! the bridge while its transmit window is full, publications wait in the bridge (answers kept,
//! state documents coalesced, other events shed and counted) while the MQTT task has no room, and
//! commands wait with the MQTT task (and the broker) while the bridge does not want them. One
//! [`CancellationToken`] stops everything and a `JoinSet` awaits every task.

use std::{
    sync::{atomic::Ordering, Arc},
    time::{Duration, Instant},
};

use ihex_gateway_core::{
    bridge::TRANSMIT_WINDOW, Bridge, Delivery, Interface, PayloadWriter, Publication,
};
use tokio::{sync::mpsc, task::JoinSet};
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use crate::{
    audit::Audit,
    can::{CanInput, CanLink, Handed, Transmitter},
    config::{Config, Link},
    error::GatewayError,
    feed::{Feed, ViewRequests},
    metrics::{CommandMeter, Counted},
    mqtt::{self, MqttInput, MqttStats, MqttTask, Outbound},
    timer::Timer,
    topic::Topics,
};

/// Frames from the CAN tasks waiting for the core.
const CAN_INPUTS: usize = 1024;
/// Messages from the MQTT task waiting for the core.
const MQTT_INPUTS: usize = 256;
/// Commands from the island view waiting for the core (a full queue is answered `503`).
#[cfg(feature = "web")]
const WEB_INPUTS: usize = 64;
/// Publications from the core waiting for the MQTT task (the bridge holds the rest, by its rules).
/// With the task's own `STAGING` and the connection's in-flight window behind it, enough to fill
/// every write; more would only hold serialised text that the bridge keeps smaller (coalesced).
const PUBLICATIONS: usize = 64;
/// Inputs of one kind the core takes per turn of its loop when they are already waiting (the
/// answers' bound [`Bridge::wants_commands`] is checked before each command).
const BATCH: usize = 64;
/// How long the core spends at shutdown handing its last publications to the MQTT task.
const SHUTDOWN_FLUSH: Duration = Duration::from_secs(1);

/// Runs the gateway until `shutdown` is cancelled (then stops every task, publishes `offline` and
/// returns `Ok`), or until a task fails.
pub async fn run(config: Config, shutdown: CancellationToken) -> Result<(), GatewayError> {
    run_with_stats(config, shutdown, Arc::default()).await
}

/// [`run`], counting MQTT traffic in `stats` (tests and benchmarks read them).
pub async fn run_with_stats(
    config: Config,
    shutdown: CancellationToken,
    stats: Arc<MqttStats>,
) -> Result<(), GatewayError> {
    Gateway::build(config, stats).await?.run(shutdown).await
}

/// A gateway whose resources are built and checked, ready to run.
pub struct Gateway {
    config: Config,
    link: CanLink,
    mqtt: MqttTask,
    #[cfg(feature = "demo")]
    demo: crate::demo::Demo,
    #[cfg(feature = "web")]
    web: Option<crate::web::Web>,
    #[cfg(feature = "sila")]
    sila: Option<crate::sila::Sila>,
}

impl Gateway {
    /// Builds every resource `config` asks for; fails on anything that would stop the gateway later
    /// (a bad island file, a taken broker port, CAN filters the kernel refuses, TLS unavailable).
    pub async fn build(config: Config, stats: Arc<MqttStats>) -> Result<Gateway, GatewayError> {
        for w in &config.warnings {
            warn!("{w}");
        }
        if config.can.bitrate != ihex_proto::BITRATE {
            warn!(
                configured = config.can.bitrate,
                island = ihex_proto::BITRATE,
                "bitrate differs from the island's; the interface's own configuration decides"
            );
        }
        // In the order that puts a fatal error before anything else is said or started: the island
        // file and the embedded broker's port (the errors a demo most often meets), then the view's
        // address (its default being taken is only a warning), then the island's boot.
        #[cfg(feature = "demo")]
        let mut demo = crate::demo::Demo::prepare(&config).await?;
        #[cfg(feature = "web")]
        let web = crate::web::Web::bind(&config).await?;
        #[cfg(not(feature = "web"))]
        if config.web.configured && config.web.listen.is_some() {
            return Err(GatewayError::WebUnavailable);
        }
        #[cfg(feature = "sila")]
        let sila = crate::sila::Sila::bind(&config).await?;
        #[cfg(not(feature = "sila"))]
        if config.sila.configured && config.sila.listen.is_some() {
            return Err(GatewayError::SilaUnavailable);
        }
        #[cfg(feature = "demo")]
        let island_link = demo.start_island(&config).await?;
        #[cfg(all(feature = "demo", feature = "web"))]
        let web = web.map(|w| w.with_island_layout(demo.layout()));
        #[cfg(not(feature = "demo"))]
        let island_link: Option<CanLink> = match config.mqtt.broker {
            crate::config::Broker::Embedded { .. } => return Err(GatewayError::DemoUnavailable),
            crate::config::Broker::External { .. } => None,
        };
        let link = match (&config.can.link, island_link) {
            (Link::SocketCan(iface), _) => CanLink::socketcan(iface, config.can.rx_buffer)?,
            (Link::Simulated { .. }, Some(link)) => link,
            (Link::Simulated { .. }, None) => return Err(GatewayError::DemoUnavailable),
        };
        let mqtt = MqttTask {
            options: mqtt::options(&config.mqtt, &config.topics)?,
            topics: config.topics.clone(),
            ha: config.ha.is_some(),
            broker: config.mqtt.broker.to_string(),
            stats,
            ack_timeout: config.mqtt.ack_timeout,
        };
        Ok(Gateway {
            config,
            link,
            mqtt,
            #[cfg(feature = "demo")]
            demo,
            #[cfg(feature = "web")]
            web,
            #[cfg(feature = "sila")]
            sila,
        })
    }

    /// Where the island view listens, when it runs.
    pub fn view_addr(&self) -> Option<std::net::SocketAddr> {
        #[cfg(feature = "web")]
        return self.web.as_ref().map(crate::web::Web::addr);
        #[cfg(not(feature = "web"))]
        None
    }

    /// Where the SiLA server listens, when it runs.
    pub fn sila_addr(&self) -> Option<std::net::SocketAddr> {
        #[cfg(feature = "sila")]
        return self.sila.as_ref().map(crate::sila::Sila::addr);
        #[cfg(not(feature = "sila"))]
        None
    }

    /// Runs until `shutdown` is cancelled (then stops every task, publishes `offline` and returns
    /// `Ok`), or until a task fails.
    pub async fn run(self, shutdown: CancellationToken) -> Result<(), GatewayError> {
        let Gateway {
            config,
            link,
            mqtt,
            #[cfg(feature = "demo")]
            mut demo,
            #[cfg(feature = "web")]
            web,
            #[cfg(feature = "sila")]
            sila,
        } = self;
        let cancel = shutdown.child_token();
        let mqtt_stats = mqtt.stats.clone();
        let mut tasks = JoinSet::new();
        let (can_in_tx, can_in) = mpsc::channel(CAN_INPUTS);
        let (mqtt_in_tx, mqtt_in) = mpsc::channel(MQTT_INPUTS);
        let (pub_tx, pub_rx) = mpsc::channel(PUBLICATIONS);
        let counted = Counted::default();
        let audit = Audit::start(&config.audit, &mut tasks);
        if let Some(a) = &audit {
            a.record(crate::audit::start_record(&config));
        }

        // The island view and the SiLA server read the core through the feed and its views, and
        // send commands into inputs of their own (so their outcomes are counted by interface).
        #[cfg(feature = "web")]
        let has_web = web.is_some();
        #[cfg(not(feature = "web"))]
        let has_web = false;
        #[cfg(feature = "sila")]
        let has_sila = sila.is_some();
        #[cfg(not(feature = "sila"))]
        let has_sila = false;
        let (feed, views, views_tx) = if has_web || has_sila {
            let (views_tx, views) = ViewRequests::channel();
            (Some(Arc::new(Feed::default())), views, Some(views_tx))
        } else {
            (None, ViewRequests::default(), None)
        };
        #[cfg(feature = "web")]
        let (web_in, view_url) = match (web, &feed, &views_tx) {
            (Some(web), Some(feed), Some(views_tx)) => {
                let (web_tx, web_in) = mpsc::channel(WEB_INPUTS);
                let url = web.url();
                let parts = crate::web::Parts {
                    feed: feed.clone(),
                    views: views_tx.clone(),
                    commands: web_tx,
                    mqtt: mqtt.stats.clone(),
                    counted: counted.clone(),
                    audit: audit.as_ref().map(Audit::status),
                };
                web.spawn(parts, &mut tasks, cancel.clone());
                (Some(web_in), Some(url))
            }
            _ => (None, None),
        };
        #[cfg(not(feature = "web"))]
        let (web_in, view_url): (_, Option<String>) = (None, None);
        #[cfg(feature = "sila")]
        let sila_url = sila.as_ref().map(crate::sila::Sila::url);
        #[cfg(not(feature = "sila"))]
        let sila_url: Option<String> = None;
        #[cfg(feature = "sila")]
        let sila_in = match (sila, &feed, &views_tx) {
            (Some(sila), Some(feed), Some(views_tx)) => {
                let (sila_tx, sila_in) = mpsc::channel(crate::sila::SILA_INPUTS);
                let parts = crate::sila::Parts {
                    feed: feed.clone(),
                    views: views_tx.clone(),
                    commands: sila_tx,
                };
                sila.spawn(parts, &mut tasks, cancel.clone());
                Some(sila_in)
            }
            _ => None,
        };
        #[cfg(not(feature = "sila"))]
        let sila_in = None;
        drop(views_tx);
        let can_tx = link.spawn(TRANSMIT_WINDOW, can_in_tx, &mut tasks, cancel.clone());
        tasks.spawn(mqtt.run(pub_rx, mqtt_in_tx, cancel.clone()));
        #[cfg(feature = "demo")]
        demo.spawn(
            &config,
            &mut tasks,
            cancel.clone(),
            view_url.as_deref(),
            sila_url.as_deref(),
        );
        #[cfg(not(feature = "demo"))]
        let _ = (view_url, sila_url);
        info!(
            island = config.island.as_deref().unwrap_or("none"),
            broker = %config.mqtt.broker,
            link = %config.can.link,
            commands = %config.topics.commands,
            events = %config.topics.events,
            "gateway running"
        );

        let started = Instant::now();
        let mut bridge = Bridge::new(config.bridge.clone(), started);
        // Leases show their end as a time of day: the core has no clock of its own.
        bridge.handle_wall_clock(std::time::SystemTime::now(), started);
        if let Some(ha) = &config.ha {
            info!(
                discovery = %ha.topics.ha.discovery_prefix,
                commands = %ha.topics.ha.command_filter(),
                "Home Assistant discovery on"
            );
            bridge = bridge.with_home_assistant(ha.clone());
        }
        let core = Core {
            bridge,
            can_tx,
            pub_tx,
            topics: config.topics.clone(),
            text: PayloadWriter::default(),
            feed,
            views,
            stats: mqtt_stats,
            fw_dir: config.settings.fw_dir.clone(),
            meter: CommandMeter::new(counted),
            audit,
        };
        let inputs = Inputs {
            can: can_in,
            mqtt: mqtt_in,
            web: web_in,
            sila: sila_in,
        };
        // The core is a task of its own, not this future: tokio's current-thread scheduler polls
        // the future it blocks on only after a poll of its I/O driver, so a command the MQTT task
        // handed over waited for an `epoll_wait`, and its frame for the MQTT task's next write.
        let mut core = tokio::spawn(core.run(inputs, cancel.clone()));
        let joined = |r: Result<Result<(), GatewayError>, tokio::task::JoinError>| {
            r.unwrap_or_else(|e| Err(GatewayError::Task(e.to_string())))
        };
        let result = tokio::select! {
            r = &mut core => joined(r),
            r = tasks.join_next() => {
                if cancel.is_cancelled() {
                    // Tasks end on cancellation; the core ends too, after its last publications.
                    joined(core.await)
                } else {
                    // No task ends on its own while the gateway runs.
                    let why = match r {
                        Some(Err(e)) => e.to_string(),
                        _ => "a gateway task ended early".to_owned(),
                    };
                    error!(%why, "stopping the gateway");
                    core.abort();
                    Err(GatewayError::Task(why))
                }
            }
        };

        cancel.cancel();
        let mut failure = result.err();
        while let Some(r) = tasks.join_next().await {
            if let Err(e) = r {
                error!(error = %e, "gateway task failed");
                failure.get_or_insert(GatewayError::Task(e.to_string()));
            }
        }
        #[cfg(feature = "demo")]
        demo.shutdown().await;
        info!("gateway stopped");
        failure.map_or(Ok(()), Err)
    }
}

/// The task that owns the bridge.
struct Core {
    bridge: Bridge,
    can_tx: Transmitter,
    pub_tx: mpsc::Sender<Outbound>,
    topics: Topics,
    /// Where publications' text is written.
    text: PayloadWriter,
    /// The island view's copy of every publication, when it runs.
    feed: Option<Arc<Feed>>,
    /// The island view's requests for views of the bridge.
    views: ViewRequests,
    stats: Arc<MqttStats>,
    /// `--fw-dir`: where `fw_update` images are read from.
    fw_dir: Option<std::path::PathBuf>,
    /// Counts command outcomes by interface for the metrics.
    meter: CommandMeter,
    /// The audit trail, when it is on.
    audit: Option<Audit>,
}

/// The core task's inputs.
struct Inputs {
    can: mpsc::Receiver<CanInput>,
    mqtt: mpsc::Receiver<MqttInput>,
    /// The island view's commands, when it runs.
    web: Option<mpsc::Receiver<MqttInput>>,
    /// The SiLA server's commands, when it runs.
    sila: Option<mpsc::Receiver<MqttInput>>,
}

/// The next message of an optional input; pending forever without one (or once it is closed).
async fn next_of<T>(rx: &mut Option<mpsc::Receiver<T>>) -> T {
    if let Some(r) = rx {
        if let Some(v) = r.recv().await {
            return v;
        }
        *rx = None;
    }
    std::future::pending().await
}

impl Core {
    async fn run(mut self, inputs: Inputs, cancel: CancellationToken) -> Result<(), GatewayError> {
        let Inputs {
            can: mut can_in,
            mqtt: mut mqtt_in,
            web: mut web_in,
            sila: mut sila_in,
        } = inputs;
        let mut timer = Timer::new();
        let mut cancelled = crate::shutdown::stopped(&cancel);
        loop {
            self.carry_out();
            timer.set(Some(self.bridge.poll_timeout()));
            let publications_waiting = self.bridge.publications_waiting();
            let wants_commands = self.bridge.wants_commands();
            let mut due = false;
            // Unbiased on purpose: a timer that is always due must not starve the inputs, nor a
            // flood of frames the timers.
            tokio::select! {
                _ = &mut cancelled => break,
                _ = timer.expired() => {
                    // After a stall (a loaded host, a paused VM) the deadline and the frames read
                    // during it are ready at once; the yield lets the receive task read what the
                    // socket holds (tokio polls its drivers before a yielded task runs again).
                    tokio::task::yield_now().await;
                    due = true;
                }
                Some(input) = can_in.recv() => {
                    on_can(&mut self.bridge, input);
                    // Every frame already waiting, in one turn of the loop: the turn itself (its
                    // timer, the outputs handed on) costs more than a frame.
                    take_frames(&mut self.bridge, &mut can_in);
                }
                req = self.views.next() => {
                    let seq = self.feed.as_ref().map_or(0, |f| f.seq());
                    req.answer(&self.bridge, seq, Instant::now());
                }
                // While answers cannot be handed on, commands stay with the MQTT task (unacknowledged,
                // so the broker holds back more): answers are never dropped and stay bounded.
                Some(input) = mqtt_in.recv(), if wants_commands => {
                    on_mqtt(&mut self.bridge, &mut self.meter, self.audit.as_ref(), input);
                    for _ in 1..BATCH {
                        if !self.bridge.wants_commands() {
                            break;
                        }
                        let Ok(input) = mqtt_in.try_recv() else { break };
                        on_mqtt(&mut self.bridge, &mut self.meter, self.audit.as_ref(), input);
                    }
                }
                input = next_of(&mut web_in), if wants_commands => {
                    on_mqtt(&mut self.bridge, &mut self.meter, self.audit.as_ref(), input);
                }
                input = next_of(&mut sila_in), if wants_commands => {
                    on_mqtt(&mut self.bridge, &mut self.meter, self.audit.as_ref(), input);
                }
                // Room for publications again: the loop's top hands them on.
                _ = self.pub_tx.reserve(), if publications_waiting => {}
            }
            self.take_waiting(&mut can_in, &mut mqtt_in);
            if due {
                // After the echoes and acks that came before it: a command whose node answered
                // during a stall is not reported `timeout`.
                self.bridge.handle_timeout(Instant::now());
            }
        }
        if self.bridge.procedures_running() {
            // Best effort, like the update's: lights off and `procedure_ended` if the tasks run.
            self.bridge
                .cancel_procedures("the gateway stopped", Instant::now());
            self.carry_out();
        }
        if self.bridge.fw_update_running() {
            // Best effort: the aborts and the report go out if the tasks still run.
            self.bridge
                .cancel_fw_update("the gateway stopped", Instant::now());
            self.carry_out();
        }
        self.flush_at_shutdown().await;
        if let Some(a) = &self.audit {
            a.record(ihex_audit::Record::new(
                ihex_audit::Kind::Stop,
                serde_json::Value::Null,
            ));
        }
        Ok(())
    }

    /// Takes what already waits on the CAN and MQTT inputs into the same turn, frames first (an
    /// echo frees a place in the transmit window, an ack ends a command): a command's echo, the
    /// node's ack and the next commands often arrive together, and each turn hands the outputs on
    /// and sets its timer once, whichever input woke it.
    fn take_waiting(
        &mut self,
        can_in: &mut mpsc::Receiver<CanInput>,
        mqtt_in: &mut mpsc::Receiver<MqttInput>,
    ) {
        take_frames(&mut self.bridge, can_in);
        for _ in 0..BATCH {
            if !self.bridge.wants_commands() {
                break;
            }
            let Ok(input) = mqtt_in.try_recv() else { break };
            on_mqtt(
                &mut self.bridge,
                &mut self.meter,
                self.audit.as_ref(),
                input,
            );
        }
    }

    /// Drains the bridge's outputs without ever waiting: frames while its transmit window has room
    /// (the transmit queue holds a whole window, so a full queue is a failed send the bridge hears
    /// about), publications while the MQTT task has room (the bridge keeps the rest).
    fn carry_out(&mut self) {
        while let Some(load) = self.bridge.poll_fw_load() {
            let bytes = crate::fw::read_image(self.fw_dir.as_deref(), &load.image);
            self.bridge.handle_fw_image(load, bytes, Instant::now());
        }
        let now = Instant::now();
        while let Some(t) = self.bridge.poll_transmit(now) {
            let reason = match self.can_tx.send(t, now) {
                Ok(Handed::Written | Handed::Queued) => continue,
                Ok(Handed::Transmitted) => {
                    self.bridge.handle_transmitted(t.packet, now);
                    continue;
                }
                Err(mpsc::error::TrySendError::Full(_)) => "CAN transmit channel full",
                Err(mpsc::error::TrySendError::Closed(_)) => "CAN transmitter stopped",
            };
            self.bridge.handle_send_failed(t.packet, reason, now);
        }
        while let Ok(permit) = self.pub_tx.try_reserve() {
            let Some(publication) = self.bridge.poll_publication() else {
                break;
            };
            self.meter.published(&publication, now);
            permit.send(outbound(
                &self.topics,
                self.feed.as_deref(),
                self.audit.as_ref(),
                &mut self.text,
                publication,
            ));
        }
        self.stats
            .publications_dropped
            .store(self.bridge.publications_dropped(), Ordering::Relaxed);
        self.stats.answers_due.store(
            self.bridge.command_counters().in_flight > 0,
            Ordering::Relaxed,
        );
        self.carry_out_audit(now);
    }

    /// The audit trail's own publications: its `audit_error` event and its retained anchor. Never
    /// waits: without room they wait for the next turn (the health flag keeps saying the error).
    fn carry_out_audit(&mut self, now: Instant) {
        let Some(audit) = &mut self.audit else {
            return;
        };
        if let Ok(permit) = self.pub_tx.try_reserve() {
            if let Some(event) = audit.poll_error() {
                let p = Publication::Event(event);
                // Not recorded: the trail cannot record now.
                let feed = self.feed.as_deref();
                permit.send(outbound(&self.topics, feed, None, &mut self.text, p));
            }
        }
        if let Ok(permit) = self.pub_tx.try_reserve() {
            if let Some(head) = audit.poll_anchor(now) {
                permit.send(Outbound {
                    topic: self.topics.audit_head.clone(),
                    payload: head.into_bytes().into(),
                    retain: true,
                });
            }
        }
    }

    /// Hands the publications the bridge still holds to the MQTT task (which sends them within
    /// its own grace period), for at most [`SHUTDOWN_FLUSH`].
    async fn flush_at_shutdown(&mut self) {
        let deadline = tokio::time::Instant::now() + SHUTDOWN_FLUSH;
        while let Some(publication) = self.bridge.poll_publication() {
            self.meter.published(&publication, Instant::now());
            let p = outbound(
                &self.topics,
                self.feed.as_deref(),
                self.audit.as_ref(),
                &mut self.text,
                publication,
            );
            match tokio::time::timeout_at(deadline, self.pub_tx.send(p)).await {
                Ok(Ok(())) => {}
                _ => {
                    warn!("shutdown: publications the MQTT task could not take were not sent");
                    return;
                }
            }
        }
    }
}

/// One input from the CAN tasks into the bridge.
/// Takes up to `BATCH` frames already waiting on the CAN input.
fn take_frames(bridge: &mut Bridge, can_in: &mut mpsc::Receiver<CanInput>) {
    for _ in 0..BATCH {
        let Ok(input) = can_in.try_recv() else { break };
        on_can(bridge, input);
    }
}

fn on_can(bridge: &mut Bridge, input: CanInput) {
    let now = Instant::now();
    match input {
        CanInput::Packet(p) => bridge.handle_packet(p, now),
        CanInput::Undecodable { raw_id, data, err } => {
            bridge.handle_undecodable(raw_id, &data, err, now)
        }
        CanInput::Bus(ev) => bridge.handle_bus_event(ev, now),
        CanInput::SendFailed(p, reason) => bridge.handle_send_failed(p, &reason, now),
        CanInput::Transmitted(p) => bridge.handle_transmitted(p, now),
        CanInput::Withdrawn(p) => bridge.handle_withdrawn(p, now),
    }
}

/// One input from the MQTT task (or the island view) into the bridge; a command is noted for the
/// metrics as coming from its origin's interface (Home Assistant's are always [`Interface::Ha`]).
fn on_mqtt(bridge: &mut Bridge, meter: &mut CommandMeter, audit: Option<&Audit>, input: MqttInput) {
    let now = Instant::now();
    match input {
        MqttInput::Command {
            payload,
            received,
            retained,
            origin,
        } => {
            if let Some(a) = audit {
                a.command(&origin, &payload, retained);
            }
            let interface = origin.interface;
            let delivery = Delivery {
                received,
                retained,
                origin,
            };
            // The meter learns the request id from the core's own reading of the command, before
            // the answer leaves the core (at the loop's top).
            let request_id = bridge.handle_delivered_command(&payload, delivery, now);
            meter.noted(interface, request_id, received);
        }
        MqttInput::HaCommand { topic, payload } => {
            let id = ihex_gateway_core::ha::command::REQUEST_ID.to_owned();
            meter.noted(Interface::Ha, Some(id), now);
            if let Some(a) = audit {
                a.ha_command(&topic, &payload);
            }
            bridge.handle_ha_command(&topic, &payload, now)
        }
        MqttInput::HaStatus(payload) => bridge.handle_ha_status(&payload, now),
        MqttInput::FwUpload {
            name,
            payload,
            retained,
        } => bridge.handle_fw_upload(&name, payload.to_vec(), retained, now),
        MqttInput::RetainedState { id, payload } => bridge.handle_retained_state(id, &payload, now),
        MqttInput::Connected => bridge.handle_mqtt_connected(now),
    }
}

/// The one place publications leave the core: serialised once, logged (every event at info, so
/// the log alone tells the island's story), copied to the island view and the audit trail,
/// addressed for the MQTT task.
fn outbound(
    topics: &Topics,
    feed: Option<&Feed>,
    audit: Option<&Audit>,
    text: &mut PayloadWriter,
    publication: Publication,
) -> Outbound {
    let payload = text.write(&publication);
    if let Some(a) = audit {
        a.published(&publication, &payload);
    }
    // serde_json writes UTF-8 only; the text is checked only where it is read as text (a log line
    // that is enabled, the island view and the SiLA server's feed), by `str::from_utf8`, which
    // checks ASCII a word at a time, where the lossy form goes character by character.
    let json = || {
        std::str::from_utf8(&payload).map_or_else(
            |_| String::from_utf8_lossy(&payload),
            std::borrow::Cow::Borrowed,
        )
    };
    match &publication {
        Publication::Event(e) => info!(event = e.name(), payload = %json(), "event published"),
        Publication::State(s) => debug!(node = %s.id, payload = %json(), "state published"),
        Publication::Ha(h) => {
            debug!(topic = ?h.topic(), payload = %json(), "Home Assistant published")
        }
        Publication::Cleared(t) => info!(topic = ?t, "retained topic cleared"),
        Publication::Leases(_) => info!(payload = %json(), "leases published"),
        Publication::Procedures(_) => info!(payload = %json(), "procedures published"),
    }
    let topic = topics.resolve(publication.topic());
    let retain = publication.retain();
    if let Some(feed) = feed {
        feed.publish(publication, &json());
    }
    Outbound {
        topic,
        payload,
        retain,
    }
}

#[cfg(test)]
mod tests {
    use ihex_proto::{AckResult, BootRole, Kind, Message, NodeId, Packet, ResetReason};

    use super::*;

    /// A stall (the process not scheduled for longer than the command timeout) while a window of
    /// commands was on the bus and its node's acks came in: when the loop runs again, its timer
    /// and those acks are ready together, and the acks must count first. Before, the loop's
    /// unbiased `select!` usually took the timer first and answered those commands `timeout`
    /// (then read the node's state back) although their acks were waiting.
    ///
    /// Which of the runtime's woken tasks runs first after the stall is not fixed, so a round can
    /// still see the timer first (about one in twenty on a loaded machine: the acks were not read
    /// yet); without the change it is about eight in nine. The test asks for 14 of 20 rounds.
    #[test]
    fn acks_read_during_a_stall_count_before_its_timeouts() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let mut late = Vec::new();
        for round in 0..20 {
            let results = rt.block_on(commands_across_a_stall());
            if let Some(r) = results.iter().find(|r| r["result"] != "ok") {
                late.push(format!("round {round}: {r}"));
            }
        }
        assert!(late.len() <= 6, "{late:#?}");
    }

    /// A core on channels, run by a task of the current runtime, with node 111 known.
    struct Harness {
        can_rx: mpsc::Receiver<ihex_gateway_core::Transmit>,
        pub_rx: mpsc::Receiver<Outbound>,
        can_in_tx: mpsc::Sender<CanInput>,
        mqtt_in_tx: mpsc::Sender<MqttInput>,
        stats: Arc<MqttStats>,
        cancel: CancellationToken,
        core: tokio::task::JoinHandle<Result<(), GatewayError>>,
    }

    const NODE: u16 = 0x111;

    fn from_node(msg: Message) -> CanInput {
        CanInput::Packet(Packet {
            src: NodeId::new(NODE).unwrap(),
            dest: NodeId::GATEWAY,
            msg,
        })
    }

    fn event(p: Outbound) -> serde_json::Value {
        serde_json::from_slice(&p.payload).unwrap_or_default()
    }

    fn led_command(request_id: &str) -> MqttInput {
        let command =
            format!(r#"{{"cmd":"led","node":"111","color":"red","request_id":"{request_id}"}}"#);
        MqttInput::Command {
            payload: command.into(),
            received: Instant::now(),
            retained: false,
            origin: Default::default(),
        }
    }

    fn ok(kind: Kind, seq: u8) -> Message {
        Message::Ack {
            kind,
            seq,
            result: AckResult::Ok,
            detail: 0,
        }
    }

    async fn harness() -> Harness {
        let (can_tx, can_rx) = mpsc::channel(TRANSMIT_WINDOW);
        let (pub_tx, mut pub_rx) = mpsc::channel(PUBLICATIONS);
        let (can_in_tx, can_in) = mpsc::channel(CAN_INPUTS);
        let (mqtt_in_tx, mqtt_in) = mpsc::channel(MQTT_INPUTS);
        let stats = Arc::<MqttStats>::default();
        // Only the commands' frames on the bus.
        let config = ihex_gateway_core::BridgeConfig {
            health_period: Duration::from_secs(3600),
            ..Default::default()
        };
        let core = Core {
            bridge: Bridge::new(config, Instant::now()),
            can_tx: crate::can::Transmitter::queue_only(can_tx),
            pub_tx,
            topics: Topics::seed(),
            text: PayloadWriter::default(),
            feed: None,
            views: ViewRequests::default(),
            stats: stats.clone(),
            fw_dir: None,
            meter: CommandMeter::new(Counted::default()),
            audit: None,
        };
        let inputs = Inputs {
            can: can_in,
            mqtt: mqtt_in,
            web: None,
            sila: None,
        };
        let cancel = CancellationToken::new();
        let core = tokio::spawn(core.run(inputs, cancel.clone()));
        let boot_up = Message::BootUp {
            version: ihex_proto::PROTOCOL_VERSION,
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        can_in_tx.send(from_node(boot_up)).await.unwrap();
        while event(pub_rx.recv().await.unwrap())["event"] != "node_online" {}
        Harness {
            can_rx,
            pub_rx,
            can_in_tx,
            mqtt_in_tx,
            stats,
            cancel,
            core,
        }
    }

    /// The core tells the MQTT task when answers are due (so a lone command's PUBACK may wait for
    /// its answer): from the turn that sent a command until the turn that published its answer.
    #[tokio::test(flavor = "current_thread")]
    async fn answers_are_due_while_a_command_is_out() {
        let mut h = harness().await;
        let due = |h: &Harness| h.stats.answers_due.load(Ordering::Relaxed);
        assert!(!due(&h), "nothing sent yet");
        h.mqtt_in_tx.send(led_command("a")).await.unwrap();
        // The core's turn ends before this task runs again (one thread): its flag is set. (The
        // node's state is also read back, with frames of the core's own, which are no command.)
        let seq = loop {
            let t = h.can_rx.recv().await.unwrap();
            let echo = CanInput::Transmitted(t.packet);
            h.can_in_tx.send(echo).await.unwrap();
            if let Message::LedSet { seq, .. } = t.packet.msg {
                break seq;
            }
        };
        assert!(due(&h), "the command's frame is out, its answer due");
        h.can_in_tx
            .send(from_node(ok(Kind::LedSet, seq)))
            .await
            .unwrap();
        while event(h.pub_rx.recv().await.unwrap())["event"] != "command_result" {}
        assert!(!due(&h), "the answer is out");
        h.cancel.cancel();
        h.core.await.unwrap().unwrap();
    }

    /// `TRANSMIT_WINDOW` LED commands to a known node, their frames written (echoed) at once and
    /// acknowledged by a task whose timer falls due while the runtime's only thread is blocked
    /// past the command timeout. Every `command_result`.
    async fn commands_across_a_stall() -> Vec<serde_json::Value> {
        let Harness {
            mut can_rx,
            mut pub_rx,
            can_in_tx,
            mqtt_in_tx,
            cancel,
            core,
            ..
        } = harness().await;
        let n = TRANSMIT_WINDOW;
        for i in 0..n {
            mqtt_in_tx.send(led_command(&i.to_string())).await.unwrap();
        }
        // Every frame is written at once (its echo); the LED frames' acks are held.
        let mut acks = Vec::new();
        while acks.len() < n {
            let t = can_rx.recv().await.unwrap();
            if let Message::LedSet { seq, .. } = t.packet.msg {
                acks.push(ok(Kind::LedSet, seq));
            }
            let echo = CanInput::Transmitted(t.packet);
            can_in_tx.send(echo).await.unwrap();
        }
        // Sent by a task (as the CAN receive task reads frames) woken by a timer that falls due
        // during the stall, in the same turn as the core's deadlines.
        let (started, running) = tokio::sync::oneshot::channel();
        let node_side = tokio::spawn(async move {
            let _ = started.send(());
            // Registered with the timer in the same poll as the send above.
            tokio::time::sleep(Duration::from_millis(100)).await;
            for ack in acks {
                can_in_tx.send(from_node(ack)).await.unwrap();
            }
        });
        running.await.unwrap();
        // The stall: this thread is the runtime's only one.
        std::thread::sleep(Duration::from_millis(700));
        let mut results = Vec::new();
        while results.len() < n {
            let v = event(pub_rx.recv().await.unwrap());
            if v["event"] == "command_result" {
                results.push(v["payload"].clone());
            }
        }
        cancel.cancel();
        core.await.unwrap().unwrap();
        node_side.await.unwrap();
        results
    }
}
