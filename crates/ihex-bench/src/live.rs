//! The live benchmark: the real `mc-gateway` process between a real SocketCAN interface and a real
//! Mosquitto broker, driven and observed from outside (a CAN writer/reader and an MQTT client), plus
//! a bare SocketCAN writer/reader pair measured in the same run as the kernel's own ceiling.
//!
//! Everything runs in one place (the microVM, or a host with native vcan) so that all processes
//! share the same CPUs and clock, except, when asked, the broker and the load generator of the
//! MQTT → CAN trials ([`crate::loadgen`]), which then run beside each other off the gateway's CPU.
//! Timestamps are taken with [`Instant`] right after a read returns or right before a
//! write/publish, in this process; the bare pair is timed the same way.

use std::collections::HashSet;
use std::io::{Read, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use ihex_gateway_core::event::{Event, Outcome};
use ihex_proto::{
    AckResult, BootRole, HealthFlags, HealthReply, Kind, LedCommand, Message, NodeId, Packet,
    ResetReason, Rgb,
};
use rumqttc::{Client, Event as MqttEvent, MqttOptions, Packet as MqttPacket, QoS};
use socketcan::{CanFilter, CanFrame, CanSocket, EmbeddedFrame, Socket, SocketOptions};

use ihex_bench::bus::{Limit, PairLimit};
use ihex_bench::results::{Bare, CostRound, CpuShare, LiveResults, MqttBare, Trial};
use ihex_bench::stats::Summary;

use crate::affinity::Pinning;
use crate::forward;
use crate::loadgen::{Load, Remote};
use crate::stamp::{micros_between, Tap, Way};
use crate::trace::{self, Trace};
use crate::watchdog::Watchdog;

/// Idle commands traced by the kernel ([`Bench::trace_idle`]) for the gateway and the forwarder.
const TRACED: usize = 5;
/// The pause before each traced idle command.
const IDLE_GAP: Duration = Duration::from_millis(100);
/// Rounds of the command cost comparison: a gateway trial, then a forwarder trial ([`CostRound`]).
const COST_ROUNDS: usize = 5;
/// The cost rounds' first rate unless rates are given: the rate of issue 34's reference figures,
/// at which in the microVM a command mostly arrives on its own (its own wake-ups and system
/// calls, none shared with the next command).
const REFERENCE_COST_RATE: f64 = 1000.0;

/// The cost rounds' rates unless given: [`REFERENCE_COST_RATE`], then 80 % of the sustained
/// command rate `cps`, where commands arrive together and share wake-ups and system calls (left
/// out when it is not clearly faster).
fn default_cost_rates(cps: f64) -> Vec<f64> {
    let busy = (cps * 0.8).round();
    if busy > REFERENCE_COST_RATE * 1.25 {
        vec![REFERENCE_COST_RATE, busy]
    } else {
        vec![REFERENCE_COST_RATE]
    }
}
/// Bitrate of the island bus.
pub const BITRATE: u32 = 500_000;
/// Nodes the benchmark makes known to the gateway (ids 1..=NODES).
pub const NODES: u16 = 256;
/// Distinct report indices: node × reset code (`other_4` .. `other_253`). With 256 nodes the
/// gateway can also hold 256 × 256 unanswered commands (one per sequence number and node) before
/// it answers `busy`, enough for every command of a run (nothing acks them).
const INDEX_SPACE: u32 = NODES as u32 * 250;
const EFF: u32 = 0x8000_0000;
const KIND_MASK: u32 = 0x1f << 24;
const SO_RCVBUFFORCE: i32 = 33;
const SO_RCVBUF: i32 = 8;
const SOL_SOCKET: i32 = 1;
/// Clock ticks per second of `/proc/PID/stat` (USER_HZ, 100 on every Linux architecture we target).
pub(crate) const USER_HZ: f64 = 100.0;

/// Settings of one live run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// SocketCAN interface (vcan0).
    pub iface: String,
    /// The plain forwarder's interface (vcan1): its frames stay off the gateway's bus.
    pub forward_iface: String,
    /// The `mc-gateway` binary.
    pub gateway: PathBuf,
    /// The `mosquitto` binary (started on a free loopback port).
    pub mosquitto: PathBuf,
    /// Latency probes per series.
    pub probes: usize,
    /// Seconds of traffic per rate trial.
    pub trial_secs: f64,
    /// Messages per second of the cost rounds, one series of rounds per rate, the first the
    /// headline; empty: [`REFERENCE_COST_RATE`] and 80 % of the sustained command rate.
    pub cost_rates: Vec<f64>,
    /// Commands in the MQTT → CAN burst.
    pub commands: usize,
    /// Leave Mosquitto's default `set_tcp_nodelay false` (Nagle on its sockets) instead of turning
    /// it off; with Nagle, command → frame takes a delayed-ACK period (~40 ms) once commands are acked.
    pub mosquitto_nagle: bool,
    /// Take the kernel's trace of idle commands ([`Bench::traced`]).
    pub trace: bool,
    /// A broker already running elsewhere (the host's Mosquitto, seen from the microVM at
    /// 10.0.2.2), used instead of starting one here: it does not share the gateway's CPU, and
    /// its CPU is not counted.
    pub broker: Option<SocketAddr>,
    /// Publish the commands and the bare ingress messages from `ihex-bench loadgen` beside the
    /// broker (asked over the broker) instead of from this process, which then only writes and
    /// reads CAN frames during those trials: the load generator is off the gateway's CPU.
    pub remote_load: bool,
    /// Run the gateway and the plain forwarder alone on CPU 0, this process on the others
    /// ([`Pinning`]).
    pub pin: bool,
}

// ---------------------------------------------------------------------------------------------
// CAN side

pub(crate) fn open_can(iface: &str, notes: &mut Vec<String>) -> Result<CanSocket> {
    let s =
        CanSocket::open(iface).with_context(|| format!("opening SocketCAN interface {iface}"))?;
    let size: i32 = 8 << 20;
    if s.set_socket_option_int(SOL_SOCKET, SO_RCVBUFFORCE, size)
        .is_err()
    {
        let _ = s.set_socket_option_int(SOL_SOCKET, SO_RCVBUF, size);
        let note = "bench sockets: SO_RCVBUFFORCE refused (not root), used SO_RCVBUF".to_string();
        if !notes.contains(&note) {
            notes.push(note);
        }
    }
    Ok(s)
}

fn kind_filter(kind_of: &Packet) -> CanFilter {
    let (id, _) = kind_of.encode();
    CanFilter::new(EFF | (id & KIND_MASK), EFF | KIND_MASK)
}

pub(crate) fn frame(p: &Packet) -> Result<CanFrame> {
    p.to_frame::<CanFrame>()
        .ok_or_else(|| anyhow!("packet {p:?} does not fit a frame"))
}

pub(crate) fn write(s: &CanSocket, f: &CanFrame) -> Result<()> {
    loop {
        match s.write_frame(f) {
            Ok(()) => return Ok(()),
            // ENOBUFS: the queue is full for a moment; vcan drains it at once.
            Err(e) if e.raw_os_error() == Some(105) => {
                std::thread::sleep(Duration::from_micros(50))
            }
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e).context("writing a CAN frame"),
        }
    }
}

fn node(i: u32) -> NodeId {
    NodeId::new(1 + (i % u32::from(NODES)) as u16).expect("1..=NODES are SC ids")
}

/// The `BootUp` report of index `i` (node and reset code carry the index).
fn report(i: u32) -> Packet {
    let i = i % INDEX_SPACE;
    Packet::report(
        node(i),
        Message::BootUp {
            version: (1, 0),
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::Other(4 + (i / u32::from(NODES)) as u8),
        },
    )
}

/// Index of a `node_rebooted` event, or `None` for other events.
fn report_index(event: &Event) -> Option<u32> {
    let Event::NodeRebooted(r) = event else {
        return None;
    };
    let id = u32::from(r.id.0.get());
    let ResetReason::Other(code) = r.reset else {
        return None;
    };
    let code = u32::from(code);
    (1..=u32::from(NODES)).contains(&id).then_some(())?;
    Some((code.checked_sub(4)?) * u32::from(NODES) + (id - 1))
}

fn background(i: u32) -> Packet {
    Packet::report(
        node(i),
        Message::HealthReply(HealthReply {
            seq: 0,
            flags: HealthFlags(0),
            loops: 0,
            tec: 0,
            rec: 0,
            uptime_s: 100,
        }),
    )
}

/// The LedSet frame of command `i`'s colour, as an index.
fn led_index(p: &Packet) -> Option<u32> {
    match p.msg {
        Message::LedSet {
            cmd: LedCommand::Steady { color, .. },
            ..
        } => Some(u32::from(color.r) | u32::from(color.g) << 8),
        _ => None,
    }
}

/// The JSON `led` command of command index `i` (node `i % NODES`, colour `i & 0xffff`).
pub(crate) fn led_command(i: u32) -> String {
    format!(
        r#"{{"cmd":"led","node":"{}","color":[{},{},0]}}"#,
        node(i),
        i & 0xff,
        i >> 8 & 0xff
    )
}

/// The `LedSet` frame command `i` becomes (what the raw forward trial forwards in its place).
pub(crate) fn led_frame(i: u32) -> Result<CanFrame> {
    frame(&Packet::command(
        node(i),
        Message::LedSet {
            seq: i as u8,
            cmd: LedCommand::Steady {
                color: Rgb {
                    r: i as u8,
                    g: (i >> 8) as u8,
                    b: 0,
                },
                brightness: 255,
            },
        },
    ))
}

fn led_filter() -> CanFilter {
    kind_filter(&Packet::command(
        node(0),
        Message::LedSet {
            seq: 0,
            cmd: LedCommand::Off,
        },
    ))
}

/// Reads answers until `want` `led` commands were answered `ok` or nothing came for `quiet`:
/// the `ok` count, and the failed or rejected ones with the first reason seen.
pub(crate) fn answers(mqtt: &Mqtt, want: usize, quiet: Duration) -> (usize, Option<String>) {
    let (mut ok, mut n, mut first) = (0usize, 0usize, None);
    while ok < want {
        let Some((_, ev)) = mqtt.next_event(quiet) else {
            break;
        };
        let reason = match ev {
            Event::CommandResult(r) if r.result == Outcome::Ok => {
                ok += usize::from(r.cmd == "led");
                continue;
            }
            Event::CommandResult(r) if r.result != Outcome::Ok => {
                let outcome = serde_json::to_value(r.result).unwrap_or_default();
                format!(
                    "{}: {}",
                    outcome.as_str().unwrap_or("?"),
                    r.reason.unwrap_or_default()
                )
            }
            Event::CommandRejected(r) => format!("rejected: {}", r.reason),
            _ => continue,
        };
        n += 1;
        first.get_or_insert(reason);
    }
    let note = first.map(|r| format!("{n} commands failed or rejected, e.g. {r}"));
    (ok, note)
}

/// The nodes' side of commands: acks every LedSet addressed to a known node, as an SC does, so the
/// gateway's pending-command table stays as small as on a real island. Without acks it only counts
/// (the plain forwarder's bus, where nothing waits for an answer).
struct Responder {
    stop: Arc<AtomicBool>,
    thread: JoinHandle<u64>,
}

/// Every `LedSet` the responder read: when, and its command index ([`led_index`]). The command
/// trials count frames from here instead of from a reader of their own, so that a command costs
/// the benchmark one CAN read, not two (the load generator shares the gateway's CPU).
type Seen = Receiver<(Instant, u32)>;

impl Responder {
    fn start(iface: &str, ack: bool, notes: &mut Vec<String>) -> Result<(Responder, Seen)> {
        let sock = open_can(iface, notes)?;
        sock.set_filters(&[led_filter()])?;
        let stop = Arc::new(AtomicBool::new(false));
        let st = stop.clone();
        let (seen_tx, seen) = mpsc::channel();
        let thread = std::thread::spawn(move || {
            let mut acked = 0u64;
            while !st.load(Ordering::Relaxed) {
                let Ok(f) = sock.read_frame_timeout(Duration::from_millis(200)) else {
                    continue;
                };
                let t = Instant::now();
                let Ok(p) = Packet::from_frame(&f) else {
                    continue;
                };
                if let Some(i) = led_index(&p) {
                    let _ = seen_tx.send((t, i));
                }
                let Message::LedSet { seq, .. } = p.msg else {
                    continue;
                };
                if ack {
                    let ack = Packet::report(
                        p.dest,
                        Message::Ack {
                            kind: Kind::LedSet,
                            seq,
                            result: AckResult::Ok,
                            detail: 0,
                        },
                    );
                    if frame(&ack).and_then(|f| write(&sock, &f)).is_ok() {
                        acked += 1;
                    }
                }
            }
            acked
        });
        Ok((Responder { stop, thread }, seen))
    }

    fn stop(self) -> u64 {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.join().unwrap_or(0)
    }
}

/// Sends `count` frames made by `make` at `rate` frames/s; returns (sent, seconds taken).
pub(crate) fn paced(
    count: usize,
    rate: f64,
    stop: Option<&AtomicBool>,
    mut send: impl FnMut(u32) -> Result<()>,
) -> Result<(usize, f64)> {
    let t0 = Instant::now();
    let mut sent = 0usize;
    while sent < count {
        if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
            break;
        }
        let due = t0 + Duration::from_secs_f64(sent as f64 / rate);
        let now = Instant::now();
        if due > now {
            // Sleep, never spin: the gateway may share this CPU.
            std::thread::sleep(due - now);
        }
        // Catch up with every frame already due (timer granularity makes small bursts).
        let due_now = ((t0.elapsed().as_secs_f64() * rate) as usize + 1).min(count);
        while sent < due_now {
            send(sent as u32)?;
            sent += 1;
        }
    }
    Ok((sent, t0.elapsed().as_secs_f64()))
}

fn bare_pair(iface: &str, n: usize, rounds: usize, notes: &mut Vec<String>) -> Result<Bare> {
    let probe = report(0);
    let rx = open_can(iface, notes)?;
    rx.set_filters(&[kind_filter(&probe)])?;
    let tx = open_can(iface, notes)?;
    let f = frame(&probe)?;
    let reader = std::thread::spawn(move || -> (usize, Option<Instant>) {
        let mut got = 0;
        let mut last = None;
        while got < n {
            match rx.read_frame_timeout(Duration::from_secs(2)) {
                Ok(_) => {
                    got += 1;
                    last = Some(Instant::now());
                }
                Err(_) => break,
            }
        }
        (got, last)
    });
    let cpu0 = cpu_ms(std::process::id())?;
    let t0 = Instant::now();
    for _ in 0..n {
        write(&tx, &f)?;
    }
    let (received, last) = reader.join().map_err(|_| anyhow!("bare reader panicked"))?;
    let cpu_ms_per_1k = (cpu_ms(std::process::id())? - cpu0) * 1000.0 / received.max(1) as f64;
    let secs = last.map_or(f64::INFINITY, |l| (l - t0).as_secs_f64());
    let rate_fps = received as f64 / secs;

    // Round trip: writer -> echo thread (other kind) -> writer.
    let echo_in = frame(&background(0))?;
    let echo_out = frame(&report(1))?;
    let a = open_can(iface, notes)?;
    a.set_filters(&[kind_filter(&report(1))])?;
    let b = open_can(iface, notes)?;
    b.set_filters(&[kind_filter(&background(0))])?;
    let echo = std::thread::spawn(move || {
        for _ in 0..rounds {
            if b.read_frame_timeout(Duration::from_secs(2)).is_err() {
                return;
            }
            let _ = b.write_frame(&echo_out);
        }
    });
    let mut rtt = Vec::with_capacity(rounds);
    for _ in 0..rounds {
        let t = Instant::now();
        write(&a, &echo_in)?;
        if a.read_frame_timeout(Duration::from_secs(2)).is_err() {
            notes.push("bare RTT: an echo did not come back within 2 s".into());
            break;
        }
        rtt.push(t.elapsed().as_secs_f64() * 1e6);
    }
    let _ = echo.join();
    Ok(Bare {
        rate_fps,
        sent: n,
        received,
        rtt: Summary::of(rtt),
        process_rtt: process_round_trip(rounds)?,
        cpu_ms_per_1k,
    })
}

/// One byte to `ihex-bench echo` in a child process and back, `rounds` times: two process
/// switches each. Threads of one process (the bare CAN RTT) switch without changing the address
/// space; the gateway, Mosquitto and this benchmark are processes.
fn process_round_trip(rounds: usize) -> Result<Summary> {
    let mut child = Command::new(std::env::current_exe()?)
        .arg("echo")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .context("starting `ihex-bench echo`")?;
    let (Some(mut to), Some(mut from)) = (child.stdin.take(), child.stdout.take()) else {
        bail!("`ihex-bench echo` without pipes");
    };
    let mut rtt = Vec::with_capacity(rounds);
    let mut byte = [0u8; 1];
    for _ in 0..rounds {
        let t = Instant::now();
        to.write_all(&byte)?;
        from.read_exact(&mut byte)?;
        rtt.push(t.elapsed().as_secs_f64() * 1e6);
    }
    drop(to);
    child.wait()?;
    Ok(Summary::of(rtt))
}

/// Copies standard input to standard output, each read at once (the far end of
/// `process_round_trip`), until the input ends.
pub(crate) fn echo() -> Result<()> {
    let mut input = std::io::stdin().lock();
    let mut output = std::io::stdout().lock();
    let mut buf = [0u8; 64];
    loop {
        let n = input.read(&mut buf)?;
        if n == 0 {
            return Ok(());
        }
        output.write_all(&buf[..n])?;
        output.flush()?;
    }
}

// ---------------------------------------------------------------------------------------------
// MQTT side

pub(crate) struct Mqtt {
    pub(crate) client: Client,
    rx: Receiver<(Instant, String, Vec<u8>)>,
    overflow: Arc<AtomicU64>,
    _thread: JoinHandle<()>,
}

impl Mqtt {
    pub(crate) fn connect(addr: SocketAddr, topics: &[&str]) -> Result<Mqtt> {
        Mqtt::connect_as("ihex-bench", addr, topics)
    }

    /// [`Mqtt::connect`] with the client id `NAME-PID` (a second client of this process needs
    /// another name: the broker would close the first connection of an id taken again).
    pub(crate) fn connect_as(name: &str, addr: SocketAddr, topics: &[&str]) -> Result<Mqtt> {
        let mut o = MqttOptions::new(
            format!("{name}-{}", std::process::id()),
            addr.ip().to_string(),
            addr.port(),
        );
        o.set_keep_alive(Duration::from_secs(30))
            .set_clean_session(true)
            .set_inflight(1000)
            .set_max_packet_size(1 << 20, 1 << 20);
        let (client, mut conn) = Client::new(o, 4096);
        let mut net = conn.eventloop.network_options();
        net.set_tcp_nodelay(true);
        conn.eventloop.set_network_options(net);
        for t in topics {
            client.subscribe(*t, QoS::AtLeastOnce)?;
        }
        let (tx, rx): (SyncSender<_>, _) = mpsc::sync_channel(1 << 18);
        let overflow = Arc::new(AtomicU64::new(0));
        let of = overflow.clone();
        let thread = std::thread::spawn(move || {
            for ev in conn.iter() {
                match ev {
                    Ok(MqttEvent::Incoming(MqttPacket::Publish(p))) => {
                        let item = (Instant::now(), p.topic.clone(), p.payload.to_vec());
                        if let Err(mpsc::TrySendError::Full(_)) = tx.try_send(item) {
                            of.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Ok(_) => {}
                    Err(_) => std::thread::sleep(Duration::from_millis(100)),
                }
            }
        });
        Ok(Mqtt {
            client,
            rx,
            overflow,
            _thread: thread,
        })
    }

    pub(crate) fn drain(&self) {
        while self.rx.try_recv().is_ok() {}
    }

    /// The next message on any subscribed topic within `timeout`: (arrival, topic, payload).
    pub(crate) fn recv(&self, timeout: Duration) -> Option<(Instant, String, Vec<u8>)> {
        self.rx.recv_timeout(timeout).ok()
    }

    /// Times the receive queue was full and a message was dropped.
    pub(crate) fn overflows(&self) -> u64 {
        self.overflow.load(Ordering::Relaxed)
    }

    /// The next event on `EventsTopic`, read as the gateway core's typed event (others are skipped).
    pub(crate) fn next_event(&self, timeout: Duration) -> Option<(Instant, Event)> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.checked_duration_since(Instant::now())?;
            let (t, topic, payload) = self.rx.recv_timeout(left).ok()?;
            if topic == "EventsTopic" {
                if let Ok(v) = serde_json::from_slice(&payload) {
                    return Some((t, v));
                }
            }
        }
    }

    fn wait_topic(&self, topic: &str, payload: &[u8], timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        loop {
            let Some(left) = deadline.checked_duration_since(Instant::now()) else {
                return false;
            };
            match self.rx.recv_timeout(left) {
                Ok((_, t, p)) if t == topic && p == payload => return true,
                Ok(_) => {}
                Err(_) => return false,
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Processes

pub(crate) struct Proc {
    pub(crate) child: Child,
    pub(crate) name: &'static str,
    /// Where its output goes, when to a file: an early exit's error quotes its last line.
    log: Option<PathBuf>,
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Proc {
    pub(crate) fn pid(&self) -> u32 {
        self.child.id()
    }

    pub(crate) fn check_alive(&mut self) -> Result<()> {
        if let Some(status) = self.child.try_wait()? {
            let Some(log) = &self.log else {
                bail!("{} exited during the benchmark ({status})", self.name);
            };
            let text = std::fs::read_to_string(log).unwrap_or_default();
            let last = text.lines().rev().find(|l| !l.trim().is_empty());
            bail!(
                "{} exited during the benchmark ({status}); its last line: {} (log: {})",
                self.name,
                last.unwrap_or("(none)"),
                log.display()
            );
        }
        Ok(())
    }

    /// Starts `cmd` as `name`, its output going to the file `log`.
    pub(crate) fn spawn(mut cmd: Command, log: &Path, name: &'static str) -> Result<Proc> {
        let file = std::fs::File::create(log)?;
        let child = cmd
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .spawn()
            .with_context(|| format!("starting {name} ({:?})", cmd.get_program()))?;
        Ok(Proc {
            child,
            name,
            log: Some(log.to_owned()),
        })
    }

    /// Waits until `addr` accepts TCP connections (or the process ends, or `within` passes).
    pub(crate) fn wait_listening(&mut self, addr: SocketAddr, within: Duration) -> Result<()> {
        let deadline = Instant::now() + within;
        while TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_err() {
            self.check_alive()?;
            if Instant::now() > deadline {
                bail!("{} did not listen on {addr} within {within:?}", self.name);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(())
    }
}

pub(crate) fn free_port() -> Result<u16> {
    Ok(TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
        .local_addr()?
        .port())
}

/// Starts Mosquitto on a free loopback port with its configuration in `dir` (unlimited queues,
/// `set_tcp_nodelay` unless `nagle`), `extra` appended to that configuration.
pub(crate) fn start_mosquitto(
    bin: &Path,
    dir: &Path,
    nagle: bool,
    extra: &str,
) -> Result<(Proc, SocketAddr)> {
    let port = free_port()?;
    let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    let conf = dir.join("mosquitto.conf");
    // Unlimited queues: a slow subscriber must not turn into broker-side loss we would blame on
    // the gateway.
    std::fs::write(
        &conf,
        format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\n\
             max_queued_messages 0\nmax_inflight_messages 0\nset_tcp_nodelay {}\n\
             log_dest stderr\nlog_type error\n{extra}",
            !nagle
        ),
    )?;
    let child = Command::new(bin)
        .arg("-c")
        .arg(&conf)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .spawn()
        .with_context(|| format!("starting {}", bin.display()))?;
    let mut p = Proc {
        child,
        name: "mosquitto",
        log: None,
    };
    p.wait_listening(addr, Duration::from_secs(20))?;
    Ok((p, addr))
}

fn start_gateway(bin: &Path, iface: &str, broker: SocketAddr, dir: &Path) -> Result<Proc> {
    let mut cmd = Command::new(bin);
    cmd.args(["--can", iface, "--broker", &broker.to_string()])
        // No health checks during the run: silent nodes would be declared lost, and a lost node's
        // BootUp is `node_online`, not `node_rebooted`. Commands keep the
        // deployed timeout (500 ms): the bench's responder acks them as the nodes would.
        .args(["--health-period-ms", "3600000"])
        .args(["--log-dir", "-", "--log", "warn"]);
    Proc::spawn(cmd, &dir.join("gateway.log"), "mc-gateway")
}

/// utime and stime of `pid`, ms.
fn cpu_times(pid: u32) -> Result<(f64, f64)> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = stat
        .rsplit_once(')')
        .map(|(_, r)| r)
        .ok_or_else(|| anyhow!("odd /proc/{pid}/stat"))?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ms = |i: usize| -> Result<f64> {
        let ticks: f64 = f
            .get(i)
            .ok_or_else(|| anyhow!("odd /proc/{pid}/stat"))?
            .parse()?;
        Ok(ticks * 1000.0 / USER_HZ)
    };
    Ok((ms(11)?, ms(12)?))
}

/// utime + stime of `pid`, ms.
pub(crate) fn cpu_ms(pid: u32) -> Result<f64> {
    let (user, system) = cpu_times(pid)?;
    Ok(user + system)
}

/// Answered commands of the shorter core-alone run ([`core_alone_ms`]); the longer one runs twice
/// as many.
const CORE_ALONE_N: u32 = 10_000;

/// CPU per 1,000 answered commands of the gateway's sans-IO core alone: `ihex-bench workload
/// --path answered` (a command parsed, checked and tracked, its frame, the node's ack, its
/// `command_result` and the element's state document written as JSON; no I/O, no tokio) run as a
/// child on the measured CPU for [`CORE_ALONE_N`] commands and for twice as many; the difference of
/// the two runs' CPU over the difference of their commands, so that start-up and set-up cancel.
fn core_alone_ms(pinning: Option<&Pinning>) -> Result<f64> {
    let run = |n: u32| -> Result<f64> {
        let before = children_cpu_ms()?;
        let status = Pinning::measured(pinning, || {
            Command::new(std::env::current_exe()?)
                .args(["workload", "--path", "answered", "--n", &n.to_string()])
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .status()
                .context("running the core-alone workload")
        })?;
        if !status.success() {
            bail!("the core-alone workload (ihex-bench workload --path answered) failed: {status}");
        }
        Ok(children_cpu_ms()? - before)
    };
    let short = run(CORE_ALONE_N)?;
    let long = run(2 * CORE_ALONE_N)?;
    Ok((long - short).max(0.0) * 1000.0 / f64::from(CORE_ALONE_N))
}

/// User + system CPU of this process's children that have been waited for, ms.
fn children_cpu_ms() -> Result<f64> {
    use nix::sys::resource::{getrusage, UsageWho};
    let u = getrusage(UsageWho::RUSAGE_CHILDREN).context("getrusage(RUSAGE_CHILDREN)")?;
    let ms = |t: nix::sys::time::TimeVal| t.tv_sec() as f64 * 1e3 + t.tv_usec() as f64 / 1e3;
    Ok(ms(u.user_time()) + ms(u.system_time()))
}

/// Context switches of `pid` so far, voluntary and not, summed over its threads (threads that
/// have ended no longer count: the gateway and Mosquitto keep theirs).
pub(crate) fn switches(pid: u32) -> Result<u64> {
    let (voluntary, preempted) = switches_split(pid)?;
    Ok(voluntary + preempted)
}

/// [`switches`] in its two parts: voluntary (a thread blocked: it had nothing to do) and not
/// (preempted by another runnable process).
pub(crate) fn switches_split(pid: u32) -> Result<(u64, u64)> {
    let (mut voluntary, mut preempted) = (0, 0);
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let Ok(status) = std::fs::read_to_string(task?.path().join("status")) else {
            continue; // the thread ended meanwhile
        };
        for line in status.lines() {
            if let Some(n) = line.strip_prefix("voluntary_ctxt_switches:") {
                voluntary += n.trim().parse::<u64>()?;
            } else if let Some(n) = line.strip_prefix("nonvoluntary_ctxt_switches:") {
                preempted += n.trim().parse::<u64>()?;
            }
        }
    }
    Ok((voluntary, preempted))
}

/// CPU times of the three processes of a live trial (and the gateway's and broker's context
/// switches), to share out its cost.
#[derive(Clone, Copy)]
struct CpuSnapshot {
    gateway: (f64, f64),
    broker: f64,
    bench: f64,
    /// The gateway's voluntary and preempted switches, the broker's (all).
    switches: (u64, u64, u64),
}

impl CpuSnapshot {
    /// `broker` is `None` when it runs elsewhere (not counted: 0).
    fn take(gateway: u32, broker: Option<u32>) -> Result<CpuSnapshot> {
        let (voluntary, preempted) = switches_split(gateway)?;
        Ok(CpuSnapshot {
            gateway: cpu_times(gateway)?,
            broker: broker.map_or(Ok(0.0), cpu_ms)?,
            bench: cpu_ms(std::process::id())?,
            switches: (voluntary, preempted, broker.map_or(Ok(0), switches)?),
        })
    }

    fn gateway_ms(&self) -> f64 {
        self.gateway.0 + self.gateway.1
    }

    /// What each process used since `self`, per 1,000 of `delivered`.
    fn share_since(&self, now: &CpuSnapshot, delivered: usize) -> CpuShare {
        let per_1k = 1000.0 / delivered.max(1) as f64;
        CpuShare {
            gateway_user: (now.gateway.0 - self.gateway.0) * per_1k,
            gateway_system: (now.gateway.1 - self.gateway.1) * per_1k,
            broker: (now.broker - self.broker) * per_1k,
            bench: (now.bench - self.bench) * per_1k,
            gateway_switches: (now.switches.0 + now.switches.1)
                .saturating_sub(self.switches.0 + self.switches.1)
                as f64
                * per_1k,
            gateway_voluntary: now.switches.0.saturating_sub(self.switches.0) as f64 * per_1k,
            broker_switches: now.switches.2.saturating_sub(self.switches.2) as f64 * per_1k,
        }
    }
}

/// `VmHWM` and `VmRSS` of `pid`, KiB.
pub(crate) fn memory_kib(pid: u32) -> Result<(u64, u64)> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let field = |name: &str| -> u64 {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next()?.parse().ok())
            .unwrap_or(0)
    };
    Ok((field("VmHWM:"), field("VmRSS:")))
}

// ---------------------------------------------------------------------------------------------
// The run

/// Which latency series a phase takes (the command → frame series always).
#[derive(Clone, Copy)]
struct Probes {
    /// The broker's own round trip.
    mqtt_loop: bool,
    /// Frame → event.
    events: bool,
    /// The kernel-stamped series beside the end-to-end ones ([`crate::stamp`]).
    stamps: bool,
}

/// What one latency phase measured.
struct Latency {
    mqtt_loop: Option<Summary>,
    frame_to_event: Option<Summary>,
    cmd_to_frame: Summary,
    frame_to_event_kernel: Option<Summary>,
    cmd_to_frame_kernel: Option<Summary>,
}

struct Bench {
    s: Settings,
    can: CanSocket,
    mqtt: Mqtt,
    gw: Proc,
    /// Mosquitto's process id (`None`: it runs elsewhere).
    broker: Option<u32>,
    next_index: u32,
    /// Next command index (never reused: every command stays pending at the gateway).
    next_cmd: u32,
    /// The `LedSet` frames the responder read, once it runs.
    seen: Option<Seen>,
    /// The load generator beside the broker ([`Settings::remote_load`]).
    remote: Option<Remote>,
    /// Where the broker listens, as seen from here.
    broker_addr: SocketAddr,
    /// The plain forwarder, once started ([`Bench::start_forwarder`]).
    forwarder: Option<Forwarder>,
    /// Whom the command trials and probes address: the gateway, or the forwarder.
    target: Target,
    /// The measured processes' CPU, when [`Settings::pin`].
    pinning: Option<Pinning>,
    notes: Vec<String>,
}

/// Whom the command trials, probes and traces address.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Target {
    Gateway,
    Forwarder,
}

impl Target {
    /// The forwarder (`&` or `&mut`), when it is the one addressed.
    fn forwarder<F>(self, forwarder: Option<F>) -> Option<F> {
        forwarder.filter(|_| self == Target::Forwarder)
    }

    /// How the notes name it.
    fn name(self) -> &'static str {
        match self {
            Target::Forwarder => "plain forwarder",
            Target::Gateway => "gateway",
        }
    }
}

/// The plain forwarder running beside the gateway, on a bus of its own.
struct Forwarder {
    proc: Proc,
    /// Its interface ([`Settings::forward_iface`]).
    iface: String,
    /// Its frames, counted as the responder counts the gateway's (nothing acks them).
    counter: Responder,
    seen: Seen,
}

impl Bench {
    /// The process the trials measure.
    fn measured(&mut self) -> &mut Proc {
        match self.target.forwarder(self.forwarder.as_mut()) {
            Some(f) => &mut f.proc,
            None => &mut self.gw,
        }
    }

    fn measured_pid(&self) -> u32 {
        self.target
            .forwarder(self.forwarder.as_ref())
            .map_or(self.gw.pid(), |f| f.proc.pid())
    }

    /// The bus the measured process writes its frames to.
    fn measured_iface(&self) -> String {
        let f = self.target.forwarder(self.forwarder.as_ref());
        f.map_or(&self.s.iface, |f| &f.iface).clone()
    }

    /// Waits (up to 5 s) until the gateway has used no CPU for 200 ms, so that a trial does not
    /// pay for the previous one's backlog.
    fn settle(&self) -> Result<()> {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let pid = self.measured_pid();
            let c0 = cpu_ms(pid)?;
            std::thread::sleep(Duration::from_millis(200));
            if cpu_ms(pid)? - c0 <= 1000.0 / USER_HZ || Instant::now() > deadline {
                return Ok(());
            }
        }
    }

    /// Collects distinct report indices in `want` until all came or nothing came for `quiet`.
    fn collect(&self, want: &HashSet<u32>, quiet: Duration) -> (usize, Option<Instant>) {
        let mut got = HashSet::new();
        let mut last = None;
        while got.len() < want.len() {
            let Some((t, v)) = self.mqtt.next_event(quiet) else {
                break;
            };
            if let Some(i) = report_index(&v) {
                if want.contains(&i) && got.insert(i) {
                    last = Some(t);
                }
            }
        }
        (got.len(), last)
    }

    fn trial(&mut self, rate: f64) -> Result<Trial> {
        let count = ((rate * self.s.trial_secs) as usize).clamp(200, INDEX_SPACE as usize - 1);
        self.settle()?;
        self.mqtt.drain();
        let base = self.next_index;
        self.next_index = (self.next_index + count as u32) % INDEX_SPACE;
        let want: HashSet<u32> = (0..count as u32)
            .map(|k| (base + k) % INDEX_SPACE)
            .collect();
        let cpu0 = CpuSnapshot::take(self.gw.pid(), self.broker)?;
        let (sent, secs) = paced(count, rate, None, |k| {
            write(&self.can, &frame(&report(base + k))?)
        })?;
        let t_end = Instant::now();
        let (received, last) = self.collect(&want, Duration::from_secs(2));
        let cpu1 = CpuSnapshot::take(self.gw.pid(), self.broker)?;
        self.gw.check_alive()?;
        let t = Trial {
            gateway_cpu_ms: cpu1.gateway_ms() - cpu0.gateway_ms(),
            share: Some(cpu0.share_since(&cpu1, received)),
            ..counted(rate, sent, secs, received, last, t_end)
        };
        println!(
            "bench: CAN->MQTT {:>8.0} fps offered, {:>8.0} sent, {}/{} events, lag {:.0} ms{}",
            t.offered_fps,
            t.sent_fps,
            t.received,
            t.sent,
            t.lag_ms,
            if t.sustained() {
                ""
            } else {
                "  (not sustained)"
            }
        );
        // Let any backlog clear before the next trial.
        std::thread::sleep(Duration::from_millis(300));
        Ok(t)
    }

    /// Steps the rate up by doubling, then bisects between the last sustained and the first failed.
    fn search(
        &mut self,
        start: f64,
        ceiling: f64,
        trial: fn(&mut Self, f64) -> Result<Trial>,
    ) -> Result<(f64, Vec<Trial>)> {
        search(start, ceiling, |r| trial(self, r))
    }

    /// The latency series `which` asks for, interleaved: each round takes one probe of each, 3 ms
    /// apart, so a VM that slows down or speeds up during the phase moves every series alike — the
    /// gateway-added estimate subtracts their medians from each other.
    fn latency(&mut self, probes: usize, which: Probes) -> Result<Latency> {
        let rx = self.led_socket()?;
        let mut stamps = if which.stamps {
            // The bench's own reports, as the bus carried them (CAN_RAW_LOOPBACK).
            let reports = open_can(&self.s.iface, &mut self.notes)?;
            reports.set_filters(&[kind_filter(&report(0))])?;
            reports.set_recv_timestamp(true)?;
            let tap = Tap::open(self.broker_addr.port())?;
            // Timestamping is switched on for the whole machine when a socket first asks for it.
            std::thread::sleep(Duration::from_millis(100));
            Some((tap, reports))
        } else {
            None
        };
        let mut mqtt_loop = Series::new("MQTT loop", probes);
        let mut to_event = Series::new("frame->event", probes);
        let mut to_frame = Series::new("cmd->frame", probes);
        let mut to_event_k = Series::new("frame->event packet (kernel)", probes);
        let mut to_frame_k = Series::new("command packet->frame (kernel)", probes);
        for k in 0..probes {
            if which.mqtt_loop {
                mqtt_loop.add(self.loop_probe(k)?);
                std::thread::sleep(Duration::from_millis(3));
            }
            if which.events {
                let (e2e, kernel) = self.event_probe(stamps.as_mut())?;
                to_event.add(e2e);
                to_event_k.add(kernel);
                std::thread::sleep(Duration::from_millis(3));
            }
            let (e2e, kernel) = self.command_probe(&rx, stamps.as_mut().map(|(t, _)| t))?;
            to_frame.add(e2e);
            to_frame_k.add(kernel);
            std::thread::sleep(Duration::from_millis(3));
            if to_event.dead() || to_frame.dead() {
                self.notes.push(format!(
                    "latency: 10 probes in a row got no answer (frame->event {}, cmd->frame {}); \
                     series stopped",
                    to_event.missed, to_frame.missed
                ));
                break;
            }
        }
        let notes = &mut self.notes;
        Ok(Latency {
            mqtt_loop: which.mqtt_loop.then(|| mqtt_loop.finish(notes)),
            frame_to_event: which.events.then(|| to_event.finish(notes)),
            cmd_to_frame: to_frame.finish(notes),
            frame_to_event_kernel: (which.events && which.stamps).then(|| to_event_k.finish(notes)),
            cmd_to_frame_kernel: which.stamps.then(|| to_frame_k.finish(notes)),
        })
    }

    /// A socket reading the `LedSet` frames on the bus, with their kernel timestamps: where the
    /// command probes see their frames.
    fn led_socket(&mut self) -> Result<CanSocket> {
        let rx = open_can(&self.measured_iface(), &mut self.notes)?;
        rx.set_filters(&[led_filter()])?;
        rx.set_recv_timestamp(true)?;
        Ok(rx)
    }

    /// `n` idle commands to the measured process under the kernel's trace ([`crate::trace`]):
    /// one note per command, with when the process was woken, ran and wrote the frame.
    fn trace_idle(&mut self, n: usize) -> Result<Vec<String>> {
        let who = self.target.name();
        let pid = self.measured_pid();
        let rx = self.led_socket()?;
        let t = Trace::start(pid)?;
        for k in 0..n {
            // Idle at the TCP level too: past the kernel's delayed-ACK timer (40 ms at least) of
            // whatever the previous command left unanswered (its `command_result`'s PUBACK).
            std::thread::sleep(IDLE_GAP);
            t.mark(&format!("ihex-probe {k} sent"))?;
            self.command_probe(&rx, None)?;
            t.mark(&format!("ihex-probe {k} frame"))?;
        }
        let t0 = Instant::now();
        let text = t.stop()?;
        println!(
            "bench: kernel trace: {} KiB read in {:.0} ms",
            text.len() / 1024,
            t0.elapsed().as_secs_f64() * 1e3
        );
        let us = |t: Option<f64>| t.map_or("-".to_owned(), |t| format!("{t:.0}"));
        Ok(trace::probes(&text, pid)
            .iter()
            .enumerate()
            .map(|(k, p)| {
                format!(
                    "kernel trace, {who}, idle command {k} (us after the publish): woken {}, \
                     running {}, last read entered {} and returned {}, frame written {}; its \
                     system calls before: {}",
                    us(p.woken_us),
                    us(p.running_us),
                    us(p.read_entered_us),
                    us(p.read_us),
                    us(p.frame_us),
                    p.calls.join(" ")
                )
            })
            .collect())
    }

    /// [`Bench::trace_idle`] into the notes, or why there is no trace (none without
    /// [`Settings::trace`]).
    fn traced(&mut self, n: usize) {
        if !self.s.trace {
            return;
        }
        println!("bench: kernel trace of {n} idle commands");
        match self.trace_idle(n) {
            Ok(lines) => self.notes.extend(lines),
            Err(e) => self
                .notes
                .push(format!("no kernel trace of idle commands: {e:#}")),
        }
    }

    /// With [`Settings::trace`], [`Bench::census_note`] into the notes, or why there is none.
    fn census(&mut self, rate: f64) {
        if !self.s.trace {
            return;
        }
        let who = self.target.name();
        println!("bench: system calls of the {who} over a trial at {rate:.0} msg/s");
        let note = self
            .census_note(rate)
            .unwrap_or_else(|e| format!("no system call census of the {who}: {e:#}"));
        self.notes.push(note);
    }

    /// One command trial at `rate` to the measured process while the kernel counts its system
    /// calls ([`trace::census`]): the calls per 1,000 commands by kind. Outside the cost rounds:
    /// tracing costs CPU of its own.
    fn census_note(&mut self, rate: f64) -> Result<String> {
        let t = Trace::start_calls(self.measured_pid())?;
        let trial = self.command_trial(rate);
        let text = t.stop()?;
        let trial = trial?;
        let (counts, lost) = trace::census(&text);
        let per_1k = |c: u64| c as f64 * 1000.0 / trial.received.max(1) as f64;
        let total: u64 = counts.iter().map(|(_, c)| c).sum();
        let kinds: Vec<String> = counts
            .iter()
            .map(|(k, c)| format!("{k} {:.0}", per_1k(*c)))
            .collect();
        let lost = if lost > 0 {
            format!(" ({lost} trace events lost: the counts are short)")
        } else {
            String::new()
        };
        Ok(format!(
            "system calls per 1,000 commands, {} ({} of {} at {rate:.0}/s, every thread): {:.0}: {}{lost}",
            self.target.name(),
            trial.received,
            trial.sent,
            per_1k(total),
            kinds.join(", ")
        ))
    }

    /// One `BootUp` frame to its `node_rebooted` event, µs (`None`: no event within 2 s); with
    /// `stamps`, also from the frame on the bus to the event's packet leaving for the broker.
    fn event_probe(
        &mut self,
        mut stamps: Option<&mut (Tap, CanSocket)>,
    ) -> Result<(Option<f64>, Option<f64>)> {
        self.mqtt.drain();
        if let Some((tap, reports)) = stamps.as_mut() {
            tap.drain()?;
            reports.set_nonblocking(true)?;
            while reports.read_frame().is_ok() {}
            reports.set_nonblocking(false)?;
        }
        let i = self.next_index;
        self.next_index = (self.next_index + 1) % INDEX_SPACE;
        let f = frame(&report(i))?;
        let t0 = Instant::now();
        write(&self.can, &f)?;
        let deadline = t0 + Duration::from_secs(2);
        let e2e = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.mqtt.next_event(left) {
                Some((t, v)) if report_index(&v) == Some(i) => {
                    break (t - t0).as_secs_f64() * 1e6;
                }
                Some(_) => {}
                None => return Ok((None, None)),
            }
        };
        let Some((tap, reports)) = stamps else {
            return Ok((Some(e2e), None));
        };
        reports.set_read_timeout(Duration::from_millis(200))?;
        let on_bus = loop {
            match reports.read_frame_with_timestamp() {
                Ok((g, at)) if g.id() == f.id() && g.data() == f.data() => break Some(at),
                Ok(_) => {}
                Err(_) => break None,
            }
        };
        let sent = tap.find(Way::ToBroker, b"node_rebooted", Duration::from_millis(200))?;
        Ok((
            Some(e2e),
            on_bus.zip(sent).map(|(a, b)| micros_between(a, b)),
        ))
    }

    /// One `led` command (or, to the plain forwarder, its frame's message) to its `LedSet` frame
    /// on `rx`, µs (`None`: no frame within 2 s); with `tap`, also from the command's packet
    /// entering this machine to the frame on the bus.
    fn command_probe(
        &mut self,
        rx: &CanSocket,
        mut tap: Option<&mut Tap>,
    ) -> Result<(Option<f64>, Option<f64>)> {
        let k = self.next_cmd;
        self.next_cmd += 1;
        let (topic, payload) = if self.target == Target::Forwarder {
            (forward::TOPIC, forward::message(&led_frame(k)?))
        } else {
            ("CommandsTopic", led_command(k))
        };
        if let Some(tap) = tap.as_mut() {
            tap.drain()?;
        }
        let t0 = Instant::now();
        self.mqtt
            .client
            .publish(topic, QoS::AtLeastOnce, false, payload.clone())?;
        let deadline = t0 + Duration::from_secs(2);
        let (e2e, on_bus) = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok((None, None));
            }
            rx.set_read_timeout(left)?;
            let Ok((f, at)) = rx.read_frame_with_timestamp() else {
                return Ok((None, None));
            };
            let t = Instant::now();
            if Packet::from_frame(&f).ok().as_ref().and_then(led_index) == Some(k & 0xffff) {
                break ((t - t0).as_secs_f64() * 1e6, at);
            }
        };
        let Some(tap) = tap else {
            return Ok((Some(e2e), None));
        };
        let arrived = tap.find(
            Way::FromBroker,
            payload.as_bytes(),
            Duration::from_millis(200),
        )?;
        Ok((Some(e2e), arrived.map(|a| micros_between(a, on_bus))))
    }

    /// Publishes `count` commands at `rate` (or back to back when `rate` is infinite) and counts
    /// the distinct LedSet frames that reach the bus.
    fn command_trial(&mut self, rate: f64) -> Result<Trial> {
        let count = if rate.is_finite() {
            ((rate * self.s.trial_secs) as usize).clamp(200, 6000)
        } else {
            self.s.commands
        };
        self.command_run(count, rate)
    }

    fn command_run(&mut self, count: usize, rate: f64) -> Result<Trial> {
        self.settle()?;
        // The measured process's frames as read (by the responder, or the forwarder's counter).
        let seen = match self.target.forwarder(self.forwarder.as_ref()) {
            Some(f) => Some(&f.seen),
            None => self.seen.as_ref(),
        }
        .ok_or_else(|| anyhow!("command trial without the responder"))?;
        while seen.try_recv().is_ok() {}
        let base = self.next_cmd;
        self.next_cmd += count as u32;
        let want: HashSet<u32> = (0..count as u32).map(|k| (base + k) & 0xffff).collect();
        self.mqtt.drain();
        let pid = self.measured_pid();
        let cpu0 = CpuSnapshot::take(pid, self.broker)?;
        let rate_or_burst = rate.is_finite().then_some(rate);
        let raw = self.target == Target::Forwarder;
        // Published here, or by the generator beside the broker, which also counts the answers
        // (they come when the frames did, so the frames are read below from the responder's
        // queue either way).
        let (sent, secs, t_end, remote_answers) = if let Some(remote) = &mut self.remote {
            let t0 = Instant::now();
            let load = if raw {
                Load::Raw { base }
            } else {
                Load::Commands { base }
            };
            let done = remote.run(load, count, rate_or_burst)?;
            let t_end = t0 + Duration::from_secs_f64(done.secs);
            (done.sent, done.secs, t_end, Some((done.results, done.note)))
        } else {
            let client = self.mqtt.client.clone();
            let publish = |k: u32| -> Result<()> {
                let (topic, payload) = if raw {
                    (forward::TOPIC, forward::message(&led_frame(base + k)?))
                } else {
                    ("CommandsTopic", led_command(base + k))
                };
                client.publish(topic, QoS::AtLeastOnce, false, payload)?;
                Ok(())
            };
            let (sent, secs) = match rate_or_burst {
                Some(rate) => paced(count, rate, None, publish)?,
                None => {
                    let t0 = Instant::now();
                    (0..count as u32).try_for_each(publish)?;
                    (count, t0.elapsed().as_secs_f64())
                }
            };
            (sent, secs, Instant::now(), None)
        };
        let (mut got, mut last) = (HashSet::new(), None);
        while got.len() < want.len() {
            let Ok((t, i)) = seen.recv_timeout(Duration::from_secs(2)) else {
                break;
            };
            if want.contains(&i) && got.insert(i) {
                last = Some(t);
            }
        }
        let received = got.len();
        // Every command's answer: the bench acked each frame as its node, so each must end in a
        // `command_result` ok on EventsTopic. The gateway's CPU is read once they are in, so it
        // includes publishing them.
        // A raw forward has no answers.
        let (results, note) = match remote_answers {
            _ if raw => (None, None),
            Some((results, note)) => (Some(results), note),
            None => {
                let (results, note) = answers(&self.mqtt, sent, Duration::from_secs(2));
                (Some(results), note)
            }
        };
        let cpu1 = CpuSnapshot::take(pid, self.broker)?;
        self.measured().check_alive()?;
        let t = Trial {
            gateway_cpu_ms: cpu1.gateway_ms() - cpu0.gateway_ms(),
            note,
            results,
            share: Some(cpu0.share_since(&cpu1, received)),
            ..counted(rate, sent, secs, received, last, t_end)
        };
        println!(
            "bench: MQTT->CAN {}{:>8.0} msg/s offered, {:>8.0} sent, {}/{} frames, {} results ok, lag {:.0} ms{}{}",
            if raw { "raw forward " } else { "" },
            t.offered_fps,
            t.sent_fps,
            t.received,
            t.sent,
            results.map_or("no".into(), |r| r.to_string()),
            t.lag_ms,
            if t.sustained() {
                ""
            } else {
                "  (not sustained)"
            },
            t.note
                .as_deref()
                .map(|n| format!(" — {n}"))
                .unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(300));
        Ok(t)
    }

    /// Starts [`forward`] beside the gateway, on its own interface and the same broker, and waits
    /// until it forwards. The gateway stays up and idle: the trials then alternate between them
    /// ([`Bench::cost_rounds`]).
    fn start_forwarder(&mut self, dir: &Path) -> Result<()> {
        let iface = self.s.forward_iface.clone();
        let mut c = Command::new(std::env::current_exe()?);
        c.args(["forward", "--iface", &iface, "--broker"])
            .arg(self.broker_addr.to_string());
        let log = dir.join("forward.log");
        let proc = Pinning::measured(self.pinning.as_ref(), || {
            Proc::spawn(c, &log, "ihex-bench forward")
        })?;
        let (counter, seen) = Responder::start(&iface, false, &mut self.notes)
            .with_context(|| format!("the plain forwarder's bus (--forward-iface {iface})"))?;
        self.forwarder = Some(Forwarder {
            proc,
            iface,
            counter,
            seen,
        });
        // Subscribed once a frame comes through.
        let ready = self.addressing(Target::Forwarder, |b| {
            for _ in 0..50 {
                if b.command_run(1, f64::INFINITY)?.received == 1 {
                    return Ok(true);
                }
            }
            Ok(false)
        })?;
        if !ready {
            bail!(
                "the raw forwarder forwarded nothing within 50 tries; its log: {}",
                std::fs::read_to_string(dir.join("forward.log")).unwrap_or_default()
            );
        }
        Ok(())
    }

    /// Runs `f` with the trials and probes addressed to `target`, then to the gateway again.
    fn addressing<T>(
        &mut self,
        target: Target,
        f: impl FnOnce(&mut Self) -> Result<T>,
    ) -> Result<T> {
        self.target = target;
        let out = f(self);
        self.target = Target::Gateway;
        out
    }

    /// [`COST_ROUNDS`] rounds of a gateway command trial, a forwarder trial at `rate` and the
    /// core alone ([`core_alone_ms`]), one after the other; returns them with every trial,
    /// gateway and forwarder alternately.
    fn cost_rounds(&mut self, rate: f64) -> Result<(Vec<CostRound>, Vec<Trial>)> {
        let per_1k = |t: &Trial| t.gateway_cpu_ms * 1000.0 / t.received.max(1) as f64;
        let (mut rounds, mut trials) = (Vec::new(), Vec::new());
        for round in 1..=COST_ROUNDS {
            let gateway = self.command_trial(rate)?;
            let forward = self.addressing(Target::Forwarder, |b| b.command_trial(rate))?;
            let r = CostRound {
                rate,
                gateway_ms: per_1k(&gateway),
                forward_ms: per_1k(&forward),
                gateway_share: gateway.share,
                forward_share: forward.share,
                core_ms: Some(core_alone_ms(self.pinning.as_ref())?),
            };
            println!(
                "bench: cost round {round}/{COST_ROUNDS}: gateway {:.0} ms, forwarder {:.0} ms, the core alone {:.0} ms per 1,000 ({:.2}x and {:.2}x the forwarder's)",
                r.gateway_ms,
                r.forward_ms,
                r.core_ms.unwrap_or_default(),
                r.ratio(),
                r.core_share().unwrap_or_default()
            );
            rounds.push(r);
            trials.extend([gateway, forward]);
        }
        Ok((rounds, trials))
    }

    /// Runs `f` while a background thread fills the bus with `HealthReply` frames at `rate`.
    fn under_load<T>(
        &mut self,
        rate: f64,
        f: impl FnOnce(&mut Self) -> Result<T>,
    ) -> Result<(T, f64, f64)> {
        let stop = Arc::new(AtomicBool::new(false));
        let s = open_can(&self.s.iface, &mut self.notes)?;
        let st = stop.clone();
        let gen = std::thread::spawn(move || {
            paced(usize::MAX, rate, Some(&st), |k| {
                write(&s, &frame(&background(k))?)
            })
        });
        // Let the load settle before measuring.
        std::thread::sleep(Duration::from_millis(500));
        let cpu0 = cpu_ms(self.gw.pid())?;
        let t0 = Instant::now();
        let out = f(self);
        stop.store(true, Ordering::Relaxed);
        let (sent, secs) = gen
            .join()
            .map_err(|_| anyhow!("load generator panicked"))??;
        let cpu = cpu_ms(self.gw.pid())? - cpu0;
        let during = t0.elapsed().as_secs_f64();
        let sent_fps = sent as f64 / secs;
        let bg_frames = sent_fps * during;
        Ok((out?, sent_fps, cpu * 1000.0 / bg_frames.max(1.0)))
    }

    /// One publication to the benchmark's own subscription through the broker, µs (`None`: not
    /// back within 2 s).
    fn loop_probe(&mut self, k: usize) -> Result<Option<f64>> {
        self.mqtt.drain();
        let payload = format!("loop-{k}");
        let t0 = Instant::now();
        self.mqtt
            .client
            .publish("ihex-bench/loop", QoS::AtLeastOnce, false, payload.clone())?;
        Ok(self
            .mqtt
            .wait_topic(
                "ihex-bench/loop",
                payload.as_bytes(),
                Duration::from_secs(2),
            )
            .then(|| t0.elapsed().as_secs_f64() * 1e6))
    }
}

/// A trial's counts: `sent` in `secs` at `rate` offered, `received` of them, the last at `last`
/// (lag measured from `t_end`, when the sending ended); the rest default.
fn counted(
    rate: f64,
    sent: usize,
    secs: f64,
    received: usize,
    last: Option<Instant>,
    t_end: Instant,
) -> Trial {
    Trial {
        offered_fps: rate,
        sent_fps: sent as f64 / secs,
        sent,
        received,
        loss: 1.0 - received as f64 / sent as f64,
        lag_ms: last.map_or(f64::NAN, |l| {
            l.saturating_duration_since(t_end).as_secs_f64() * 1e3
        }),
        ..Trial::default()
    }
}

/// Steps the rate up from `start` by doubling (up to twice `ceiling`), then bisects between the
/// last sustained and the first failed rate (up to 4 steps, stopping at 10 % resolution).
fn search(
    start: f64,
    ceiling: f64,
    mut trial: impl FnMut(f64) -> Result<Trial>,
) -> Result<(f64, Vec<Trial>)> {
    let mut trials = Vec::new();
    let (mut good, mut bad) = (0.0f64, f64::NAN);
    let mut r = start;
    while r <= ceiling * 2.0 {
        let t = trial(r)?;
        let ok = t.sustained();
        trials.push(t);
        if ok {
            good = r;
            r *= 2.0;
        } else {
            bad = r;
            break;
        }
    }
    if bad.is_finite() {
        for _ in 0..4 {
            let mid = (good + bad) / 2.0;
            if good > 0.0 && (bad - good) / good < 0.1 {
                break;
            }
            let t = trial(mid)?;
            let ok = t.sustained();
            trials.push(t);
            if ok {
                good = mid;
            } else {
                bad = mid;
            }
        }
    }
    Ok((good, trials))
}

/// Topic of the bare MQTT path's ingress messages (the gateway's commands' way), and of its
/// egress messages (the events' way); the gateway uses neither.
pub(crate) const BARE_IN: &str = "ihex-bench/bare/in";
const BARE_OUT: &str = "ihex-bench/bare/out";

/// Message `k` of a bare MQTT trial: its index in decimal, padded with spaces to `len` bytes (the
/// size of the gateway's message on that way).
pub(crate) fn bare_message(k: u32, len: usize) -> Vec<u8> {
    let mut m = k.to_string().into_bytes();
    m.resize(len.max(m.len()), b' ');
    m
}

/// Who publishes a bare MQTT trial's messages.
enum BareFrom<'a> {
    /// A client of this process.
    Here(&'a Mqtt),
    /// The load generator beside the broker (ingress only: it publishes on [`BARE_IN`]).
    Remote(&'a mut Remote),
}

/// One trial of the bare MQTT path: `rate × trial_secs` QoS 1 messages of `len` bytes published
/// by `from` on `topic`, counted at `to` (distinct indices; read until all came or none for 2 s).
fn bare_mqtt_trial(
    from: &mut BareFrom<'_>,
    to: &Mqtt,
    topic: &str,
    len: usize,
    rate: f64,
    trial_secs: f64,
) -> Result<Trial> {
    let count = ((rate * trial_secs) as usize).clamp(200, 100_000);
    std::thread::sleep(Duration::from_millis(300));
    to.drain();
    let (sent, secs, t_end) = match from {
        BareFrom::Here(from) => {
            let (sent, secs) = paced(count, rate, None, |k| {
                from.client
                    .publish(topic, QoS::AtLeastOnce, false, bare_message(k, len))?;
                Ok(())
            })?;
            (sent, secs, Instant::now())
        }
        BareFrom::Remote(remote) => {
            let t0 = Instant::now();
            let done = remote.run(Load::Bare { len }, count, Some(rate))?;
            (
                done.sent,
                done.secs,
                t0 + Duration::from_secs_f64(done.secs),
            )
        }
    };
    let mut got = HashSet::new();
    let mut last = None;
    while got.len() < sent {
        let Some((t, tp, payload)) = to.recv(Duration::from_secs(2)) else {
            break;
        };
        let k = std::str::from_utf8(&payload)
            .ok()
            .and_then(|p| p.trim_end().parse::<u32>().ok());
        if let (true, Some(k)) = (tp == topic, k) {
            if (k as usize) < sent && got.insert(k) {
                last = Some(t);
            }
        }
    }
    let received = got.len();
    let t = counted(rate, sent, secs, received, last, t_end);
    println!(
        "bench: bare MQTT {topic} {:>8.0} msg/s offered, {:>8.0} sent, {}/{} received, lag {:.0} ms{}",
        t.offered_fps,
        t.sent_fps,
        t.received,
        t.sent,
        t.lag_ms,
        if t.sustained() { "" } else { "  (not sustained)" }
    );
    Ok(t)
}

/// The bare MQTT path through the broker at `addr`, both ways, before the gateway starts: a second
/// client of this process plays the gateway's part (subscribed to the ingress topic, publishing on
/// the egress topic), `main` the benchmark's (publishing commands, reading events), or `remote`
/// publishes the ingress messages when the commands come from there.
fn bare_mqtt(
    main: &Mqtt,
    remote: Option<&mut Remote>,
    addr: SocketAddr,
    trial_secs: f64,
) -> Result<MqttBare> {
    let peer = Mqtt::connect_as("ihex-bench-peer", addr, &[BARE_IN])?;
    // Both subscriptions in place before the first message (a round through each).
    for (m, topic) in [(&peer, BARE_IN), (main, BARE_OUT)] {
        let mut ok = false;
        for _ in 0..50 {
            m.client.publish(topic, QoS::AtLeastOnce, false, "ready")?;
            if m.wait_topic(topic, b"ready", Duration::from_millis(200)) {
                ok = true;
                break;
            }
        }
        if !ok {
            bail!("bare MQTT: no message came back on {topic} within 10 s");
        }
    }
    // The sizes of the gateway's own messages on each way.
    let command_len = led_command(0xffff).len();
    let event_len = r#"{"event":"node_rebooted","payload":{"id":"256","reset":"other_253","version":"1.0","role":"static"}}"#.len();
    println!("bench: bare MQTT ingress ({command_len}-byte messages)");
    let mut from = match remote {
        Some(r) => BareFrom::Remote(r),
        None => BareFrom::Here(main),
    };
    let (ingress_mps, ingress_trials) = search(250.0, 16_000.0, |r| {
        bare_mqtt_trial(&mut from, &peer, BARE_IN, command_len, r, trial_secs)
    })?;
    println!("bench: bare MQTT egress ({event_len}-byte messages)");
    let (egress_mps, egress_trials) = search(250.0, 16_000.0, |r| {
        bare_mqtt_trial(
            &mut BareFrom::Here(&peer),
            main,
            BARE_OUT,
            event_len,
            r,
            trial_secs,
        )
    })?;
    Ok(MqttBare {
        ingress_mps,
        egress_mps,
        ingress_trials,
        egress_trials,
    })
}

/// One latency series being collected: its samples and the probes that got no answer.
struct Series {
    name: &'static str,
    probes: usize,
    lat: Vec<f64>,
    missed: usize,
}

impl Series {
    fn new(name: &'static str, probes: usize) -> Series {
        Series {
            name,
            probes,
            lat: Vec::with_capacity(probes),
            missed: 0,
        }
    }

    fn add(&mut self, sample: Option<f64>) {
        match sample {
            Some(us) => self.lat.push(us),
            None => self.missed += 1,
        }
    }

    /// Ten probes and not one answer: the gateway is not answering at all.
    fn dead(&self) -> bool {
        self.missed >= 10 && self.lat.is_empty()
    }

    /// The summary, with a note when probes went unanswered.
    fn finish(self, notes: &mut Vec<String>) -> Summary {
        if self.missed > 0 {
            notes.push(format!(
                "{}: {} of {} probes got no answer in 2 s",
                self.name, self.missed, self.probes
            ));
        }
        Summary::of(self.lat)
    }
}

/// Kernel, CPU count and model of this machine, and its CPU count.
pub(crate) fn environment() -> (String, usize) {
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = cpuinfo
        .lines()
        .find_map(|l| l.strip_prefix("model name"))
        .map(|m| m.trim_start_matches([' ', '\t', ':']).to_string())
        .unwrap_or_else(|| "unknown CPU".into());
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    (
        format!("Linux {}, {cpus} CPU(s), {model}", kernel.trim()),
        cpus,
    )
}

/// Runs the whole live benchmark.
pub fn run(s: Settings) -> Result<LiveResults> {
    let (environment, cpus) = environment();
    println!("bench: {environment}");
    // No phase takes minutes: one that does is written out, thread by thread.
    let dog = Watchdog::start(Duration::from_secs(240));
    let mut notes = Vec::new();
    if s.mosquitto_nagle {
        notes.push("Mosquitto ran with its default set_tcp_nodelay false (Nagle)".into());
    }
    let dir = std::env::temp_dir().join(format!("ihex-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;

    println!("bench: bare SocketCAN pair on {}", s.iface);
    let bare = bare_pair(&s.iface, 20_000, s.probes.max(200), &mut notes)?;
    println!(
        "bench: bare pair {:.0} fps ({}/{}), RTT p50 {:.0} us",
        bare.rate_fps, bare.received, bare.sent, bare.rtt.p50_us
    );
    // After the bare pair, which may use every CPU (the most the kernel path gives), and before
    // the threads that stay: every later one inherits the benchmark's CPUs.
    let pinning = s.pin.then(|| Pinning::start(cpus)).transpose()?;
    let cpu_layout = if pinning.is_some() {
        Pinning::layout(cpus)
    } else {
        String::new()
    };

    // `_broker` lives as long as the run: dropping it stops the broker.
    let (_broker, broker_pid, addr, broker_layout) = match s.broker {
        Some(addr) => (
            None,
            None,
            addr,
            format!("Mosquitto elsewhere, at {addr} (not on these CPUs; its CPU is not counted)"),
        ),
        None => {
            let (p, addr) = start_mosquitto(&s.mosquitto, &dir, s.mosquitto_nagle, "")?;
            let pid = p.pid();
            (
                Some(p),
                Some(pid),
                addr,
                "Mosquitto here, sharing the CPUs with the gateway and the benchmark".to_owned(),
            )
        }
    };
    let broker_layout = if s.remote_load {
        format!(
            "{broker_layout}; the commands and the bare ingress messages published beside it by \
             `ihex-bench loadgen` (not on these CPUs; its CPU is not counted)"
        )
    } else {
        broker_layout
    };
    println!("bench: {broker_layout}");
    let mqtt = Mqtt::connect(
        addr,
        &[
            "EventsTopic",
            "ihex/gateway/availability",
            "ihex-bench/loop",
            BARE_OUT,
        ],
    )?;
    let mut remote = if s.remote_load {
        let r = Remote::connect(addr)?;
        println!(
            "bench: commands and bare ingress messages come from the load generator at {addr}"
        );
        Some(r)
    } else {
        None
    };
    let mqtt_bare = bare_mqtt(&mqtt, remote.as_mut(), addr, s.trial_secs)?;
    println!(
        "bench: bare MQTT ingress {:.0} msg/s, egress {:.0} msg/s (zero loss)",
        mqtt_bare.ingress_mps, mqtt_bare.egress_mps
    );
    let mut gw = Pinning::measured(pinning.as_ref(), || {
        start_gateway(&s.gateway, &s.iface, addr, &dir)
    })?;
    let gw_log = || std::fs::read_to_string(dir.join("gateway.log")).unwrap_or_default();
    let mut waited = 0;
    while !mqtt.wait_topic(
        "ihex/gateway/availability",
        b"online",
        Duration::from_secs(1),
    ) {
        if let Err(e) = gw.check_alive() {
            bail!("{e}; its log: {}", gw_log());
        }
        waited += 1;
        if waited == 60 {
            bail!(
                "the gateway did not come online within 60 s; its log: {}",
                gw_log()
            );
        }
    }
    let (_, rss_start) = memory_kib(gw.pid())?;
    let can = open_can(&s.iface, &mut notes)?;
    let mut b = Bench {
        s: s.clone(),
        can,
        mqtt,
        gw,
        broker: broker_pid,
        next_index: 0,
        next_cmd: 0,
        seen: None,
        remote,
        broker_addr: addr,
        forwarder: None,
        target: Target::Gateway,
        pinning,
        notes,
    };

    // Make the nodes known: their first BootUp is `node_online`, every later one `node_rebooted`.
    for i in 0..u32::from(NODES) {
        write(&b.can, &frame(&report(i))?)?;
    }
    let mut online = 0;
    while online < NODES {
        match b.mqtt.next_event(Duration::from_secs(10)) {
            Some((_, Event::NodeOnline(_))) => online += 1,
            Some(_) => {}
            None => bail!("only {online} of {NODES} nodes came online at the gateway"),
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    b.next_index = u32::from(NODES);
    let (responder, seen) = Responder::start(&s.iface, true, &mut b.notes)?;
    b.seen = Some(seen);

    // Which phase sets the gateway's peak: its VmHWM after each.
    let mut peaks: Vec<(&str, u64)> = vec![("start", memory_kib(b.gw.pid())?.0)];
    println!("bench: latency at idle");
    dog.phase("latency at idle", &[b.gw.pid()]);
    let idle = b.latency(
        s.probes,
        Probes {
            mqtt_loop: true,
            events: true,
            stamps: true,
        },
    )?;

    peaks.push(("idle latency", memory_kib(b.gw.pid())?.0));
    dog.phase("kernel trace", &[b.gw.pid()]);
    b.traced(TRACED);
    println!("bench: CAN->MQTT rate search");
    dog.phase("CAN->MQTT rate search", &[b.gw.pid()]);
    let ceiling = bare.rate_fps.max(1000.0);
    let (best, mut trials) = b.search(250.0, ceiling, Bench::trial)?;
    let at_double = if best > 0.0 {
        b.trial(best * 2.0)?
    } else {
        Trial::default()
    };
    // Cost: a dedicated run at 80 % of the sustained rate.
    let cost_rate = (best * 0.8).max(100.0);
    let cost = b.trial(cost_rate)?;
    let cpu_ms_per_1k_reports = cost.gateway_cpu_ms * 1000.0 / cost.received.max(1) as f64;
    let share_reports = cost.share;
    trials.push(cost);

    peaks.push(("CAN->MQTT rates", memory_kib(b.gw.pid())?.0));
    println!("bench: MQTT->CAN rate");
    dog.phase("MQTT->CAN rate search", &[b.gw.pid()]);
    if b.remote.is_some() {
        // The answers are counted by the generator: not delivered here too.
        b.mqtt.client.unsubscribe("EventsTopic")?;
    }
    let (cps, mut command_trials) = b.search(250.0, ceiling, Bench::command_trial)?;
    peaks.push(("MQTT->CAN rates", memory_kib(b.gw.pid())?.0));
    println!("bench: MQTT->CAN burst of {} commands", s.commands);
    dog.phase("MQTT->CAN burst", &[b.gw.pid()]);
    let burst = b.command_trial(f64::INFINITY)?;
    let burst_secs = burst.sent as f64 / burst.sent_fps + burst.lag_ms.max(0.0) / 1e3;

    peaks.push(("burst", memory_kib(b.gw.pid())?.0));
    if b.remote.is_some() {
        b.mqtt.client.subscribe("EventsTopic", QoS::AtLeastOnce)?;
        // The subscription in place before the next probes (they time the events).
        std::thread::sleep(Duration::from_secs(1));
        b.mqtt.drain();
    }
    let limit_background = Limit::new(BITRATE, frame(&background(0))?.data().len() as u8);
    let load_rate = limit_background.fps_worst;
    println!("bench: latency with the bus at {load_rate:.0} background frames/s");
    dog.phase("latency with the bus full", &[b.gw.pid()]);
    let ((frame_to_event_load, cmd_to_frame_load), load_sent_fps, cpu_ms_per_1k_background) = b
        .under_load(load_rate, |b| {
            let l = b.latency(
                s.probes,
                Probes {
                    mqtt_loop: false,
                    events: true,
                    stamps: false,
                },
            )?;
            Ok((l.frame_to_event.unwrap_or_default(), l.cmd_to_frame))
        })?;

    b.gw.check_alive()?;
    let (hwm, rss) = memory_kib(b.gw.pid())?;
    peaks.push(("bus load", hwm));
    // Cost: the gateway and the plain forwarder alternately, at each rate given, else at the
    // reference rate and at 80 % of the sustained rate.
    let given = if b.s.cost_rates.is_empty() {
        default_cost_rates(cps)
    } else {
        b.s.cost_rates.clone()
    };
    // A rate given twice is one series (the results group the rounds by rate).
    let mut cost_rates: Vec<f64> = Vec::new();
    for rate in given {
        if !cost_rates.contains(&rate) {
            cost_rates.push(rate);
        }
    }
    dog.phase("cost rounds", &[b.gw.pid()]);
    b.start_forwarder(&dir)?;
    let forwarder = b.forwarder.as_ref().map_or(0, |f| f.proc.pid());
    dog.phase("cost rounds", &[b.gw.pid(), forwarder]);
    let mut series = Vec::new();
    for &rate in &cost_rates {
        println!(
            "bench: MQTT->CAN cost at {rate:.0} msg/s, the gateway and a plain forwarder \
             (on {}) alternately, {COST_ROUNDS} rounds",
            s.forward_iface
        );
        series.push(b.cost_rounds(rate)?);
    }
    let (headline, headline_trials) = &series[0];
    // The gateway's figures from the headline rate's median round (by CPU), the forwarder's last
    // trial at that rate for its counts; the ratios are the rounds' own
    // ([`LiveResults::cost_ratio`]).
    let median = CostRound::median(headline).copied().unwrap_or_default();
    let cpu_ms_per_1k_commands = median.gateway_ms;
    let share_commands = median.gateway_share;
    let raw_forward = headline_trials.last().cloned();
    let mut cost_rounds = Vec::new();
    for (rounds, trials) in series {
        cost_rounds.extend(rounds);
        command_trials.extend(trials.into_iter().step_by(2));
    }
    for &rate in &cost_rates {
        b.census(rate);
        b.addressing(Target::Forwarder, |b| {
            b.census(rate);
            Ok(())
        })?;
    }
    println!("bench: latency of the raw MQTT->CAN forward at idle");
    dog.phase("forwarder latency and trace", &[forwarder]);
    let raw_idle = b.addressing(Target::Forwarder, |b| {
        let l = b.latency(
            s.probes,
            Probes {
                mqtt_loop: false,
                events: false,
                stamps: true,
            },
        )?;
        b.traced(TRACED);
        Ok(l)
    })?;
    let peaks: Vec<String> = peaks.iter().map(|(p, k)| format!("{p} {k}")).collect();
    b.notes.push(format!(
        "gateway VmHWM (KiB) after each phase: {}",
        peaks.join(", ")
    ));
    let acked = responder.stop();
    if let Some(f) = b.forwarder.take() {
        f.counter.stop();
    }
    b.notes.push(format!(
        "the bench acked {acked} LedSet commands as their nodes (each ack -> one command_result)"
    ));
    // What the gateway logged at `--log warn` during the run: nothing, when all went well.
    let log = gw_log();
    let lines: Vec<&str> = log.lines().collect();
    if !lines.is_empty() {
        b.notes.push(format!(
            "the gateway logged {} lines at --log warn; the last ones: {}",
            lines.len(),
            lines[lines.len().saturating_sub(3)..].join(" | ")
        ));
    }
    let overflow = b.mqtt.overflow.load(Ordering::Relaxed);
    if overflow > 0 {
        b.notes.push(format!(
            "bench MQTT receive queue overflowed {overflow} times"
        ));
    }
    let r = LiveResults {
        environment,
        broker_layout,
        cpu_layout,
        mqtt_bare: Some(mqtt_bare),
        cpus,
        bare,
        trials,
        can_to_mqtt_fps: best,
        at_double,
        command_trials,
        mqtt_to_can_cps: cps,
        commands_sent: burst.sent,
        commands_delivered: burst.received,
        burst_cps: burst.received as f64 / burst_secs,
        burst_note: burst.note.clone(),
        cmd_to_frame_idle: idle.cmd_to_frame,
        frame_to_event_idle: idle.frame_to_event.unwrap_or_default(),
        cmd_to_frame_idle_kernel: idle.cmd_to_frame_kernel,
        frame_to_event_idle_kernel: idle.frame_to_event_kernel,
        raw_cmd_to_frame_idle: Some(raw_idle.cmd_to_frame),
        raw_cmd_to_frame_idle_kernel: raw_idle.cmd_to_frame_kernel,
        cmd_to_frame_load,
        frame_to_event_load,
        load_offered_fps: load_rate,
        load_sent_fps,
        mqtt_loop: idle.mqtt_loop.unwrap_or_default(),
        cpu_ms_per_1k_reports,
        cpu_ms_per_1k_commands,
        raw_forward,
        cost_rounds,
        share_reports,
        share_commands,
        cpu_ms_per_1k_background,
        gateway_vmhwm_kib: hwm,
        gateway_vmrss_kib: rss,
        gateway_vmrss_start_kib: rss_start,
        limit_report: Limit::new(BITRATE, frame(&report(0))?.data().len() as u8),
        limit_background,
        limit_command: Limit::new(BITRATE, 8),
        limit_command_pair: PairLimit::new(
            BITRATE,
            Message::len_of(Kind::LedSet),
            Message::len_of(Kind::Ack),
        ),
        notes: b.notes.clone(),
    };
    let _ = std::fs::remove_dir_all(&dir);
    Ok(r)
}

/// Sends the results as one JSON line to `addr` (the host's `cargo xtask bench` listening).
pub fn send(results: &impl serde::Serialize, addr: &str) -> Result<()> {
    let mut s = TcpStream::connect(addr).with_context(|| format!("connecting to {addr}"))?;
    let mut line = serde_json::to_vec(results)?;
    line.push(b'\n');
    s.write_all(&line)?;
    s.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_early_exit_names_the_last_line_of_the_log() {
        let dir = std::env::temp_dir().join(format!("ihex-bench-proc-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let log = dir.join("out.log");
        let mut cmd = Command::new("sh");
        cmd.args([
            "-c",
            "echo starting; echo 'no such feature: pass --x off' >&2; exit 3",
        ]);
        let mut p = Proc::spawn(cmd, &log, "tool").unwrap();
        p.child.wait().unwrap();
        let e = p.check_alive().unwrap_err().to_string();
        std::fs::remove_dir_all(&dir).unwrap();
        assert!(
            e.starts_with("tool exited during the benchmark (exit status: 3)"),
            "{e}"
        );
        assert!(
            e.contains("its last line: no such feature: pass --x off"),
            "{e}"
        );
        assert!(e.contains("out.log"), "{e}");
    }

    #[test]
    fn report_index_round_trips_through_the_event_json() {
        for i in [0, 1, 63, 64, 1000, INDEX_SPACE - 1] {
            let p = report(i);
            let Message::BootUp { reset, .. } = p.msg else {
                unreachable!()
            };
            let ResetReason::Other(code) = reset else {
                panic!("index {i} must use an unknown reset code")
            };
            // The event as the gateway publishes it, read back as the bench reads it.
            let json = serde_json::json!({"event": "node_rebooted", "payload": {
                "id": p.src.to_string(), "reset": format!("other_{code}"), "version": "1.0", "role": "static"}});
            let ev: Event = serde_json::from_value(json).unwrap();
            assert_eq!(report_index(&ev), Some(i));
        }
        let other: Event = serde_json::from_str(
            r#"{"event":"node_online","payload":{"id":"1","role":null,"first_seen":true}}"#,
        )
        .unwrap();
        assert_eq!(report_index(&other), None);
    }

    #[test]
    fn led_index_matches_the_command_colour() {
        let p = Packet::command(
            node(3),
            Message::LedSet {
                seq: 0,
                cmd: LedCommand::Steady {
                    color: ihex_proto::Rgb {
                        r: 0x34,
                        g: 0x12,
                        b: 0,
                    },
                    brightness: 255,
                },
            },
        );
        assert_eq!(led_index(&p), Some(0x1234));
        assert!(led_command(0x1234).contains("[52,18,0]"));
    }

    #[test]
    fn the_cost_rounds_run_at_the_reference_rate_and_near_the_sustained_one() {
        assert_eq!(default_cost_rates(3750.0), [1000.0, 3000.0]);
        // Not clearly above the reference: one series.
        assert_eq!(default_cost_rates(1500.0), [1000.0]);
        assert_eq!(default_cost_rates(0.0), [1000.0]);
    }

    #[test]
    fn cpu_and_memory_of_this_process_are_readable() {
        let pid = std::process::id();
        assert!(cpu_ms(pid).unwrap() >= 0.0);
        let (hwm, rss) = memory_kib(pid).unwrap();
        assert!(hwm >= rss && rss > 0);
    }

    #[test]
    fn each_sleep_counts_as_a_context_switch() {
        let pid = std::process::id();
        let before = switches(pid).unwrap();
        for _ in 0..3 {
            std::thread::sleep(Duration::from_millis(1));
        }
        let after = switches(pid).unwrap();
        assert!(after >= before + 3, "{before} -> {after}");
    }

    #[test]
    fn a_waited_for_child_adds_its_cpu_to_the_childrens() {
        let before = children_cpu_ms().unwrap();
        // About a quarter of a second of the shell's arithmetic.
        let status = Command::new("sh")
            .args(["-c", "i=0; while [ $i -lt 300000 ]; do i=$((i+1)); done"])
            .status()
            .unwrap();
        assert!(status.success());
        let spent = children_cpu_ms().unwrap() - before;
        assert!(spent > 20.0, "{spent} ms");
    }
}
