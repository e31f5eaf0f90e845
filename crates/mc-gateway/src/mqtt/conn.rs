//! The gateway's MQTT connection, driven here instead of by rumqttc's `EventLoop`, so that every
//! packet queued in one turn of the MQTT task leaves in one write.
//!
//! rumqttc 0.25's event loop takes one request per `poll()` and flushes after each
//! (bytebeamio/rumqtt#810): on a busy island that is a system call, a wake-up of the broker and a
//! TCP segment per publication, and it was most of what a bridged frame cost. This module keeps
//! rumqttc's MQTT 3.1.1 packet types and codec, keeps the client state in [`super::state`] (packet
//! ids, the in-flight window, acks, the awaited PINGRESP) and does the I/O itself:
//! [`Connection::publish`] and friends only encode into a write buffer, and [`Connection::poll`]
//! writes whatever is buffered, reads whatever arrived, and returns the next incoming packet. `poll`
//! is cancel-safe (all its state lives in the [`Connection`], including a connection attempt under
//! way), so the MQTT task can select on it beside its channels. When to ping and when to give a
//! silent link up is the session's decision ([`super::session`]): the connection pings when asked
//! ([`Connection::ping`]) and closes when told ([`Connection::close`]).

use std::{
    future::Future,
    io,
    os::fd::AsRawFd,
    os::fd::RawFd,
    pin::Pin,
    sync::atomic::{AtomicU64, Ordering},
    sync::Arc,
    task::Poll,
    time::{Duration, Instant},
};

use bytes::{Buf, Bytes, BytesMut};
use rumqttc::{
    mqttbytes, ConnAck, Connect, ConnectReturnCode, ConnectionError, Event, MqttOptions, Outgoing,
    Packet, PubAck, Publish, QoS, Request, StateError, Subscribe, Transport, Unsubscribe,
};
use tokio::{
    io::{AsyncRead, AsyncWrite, AsyncWriteExt},
    net::TcpSocket,
};

use super::state::State;
use crate::sys as sockopt;

/// Anything a connection can run over (TCP, TLS over TCP).
trait Stream: AsyncRead + AsyncWrite + Send + Unpin {}
impl<T: AsyncRead + AsyncWrite + Send + Unpin> Stream for T {}

type Attempt = Pin<Box<dyn Future<Output = Result<(Up, ConnAck), ConnectionError>> + Send>>;

/// Bytes read from the socket at a time (a buffer grows to the largest packet it must hold).
const READ_CHUNK: usize = 16 * 1024;
/// Publications encoded ahead of one write, in bytes. The write buffer keeps the largest size it
/// ever had: without this bound a window of Home Assistant configs (3 KB each, up to 100 in flight)
/// at start-up could grow it to hundreds of KiB for good. The rest waits, already serialised, for
/// the next round.
pub const WRITE_BATCH: usize = READ_CHUNK;
/// Publications in flight from which their PUBACKs are read in batches: the socket's receive
/// low-water mark is raised to that many PUBACKs' bytes, so the kernel wakes the gateway once per
/// batch instead of once per acknowledgement (below it, see [`wanted_lowat`]).
const ACK_BATCH: u16 = 16;
/// A PUBACK's encoded size: the fewest bytes on the wire per acknowledgement (TLS only adds).
const PUBACK_LEN: u16 = 4;
/// PUBACKs a connection holds back at most while answers are due ([`Connection::hold_acks`]): far
/// inside any broker's window of unacknowledged deliveries (Mosquitto's `max_inflight_messages` is
/// 20 by default), so holding them never stops the broker from sending more commands.
pub const ACKS_HELD: usize = 4;
/// A quiet spell after which the next read first puts the socket back into delayed-ACK mode
/// ([`Up::delay_acks`]). The kernel leaves that mode when its delayed-ACK timer fires, at least
/// 40 ms after a segment came that nothing answered, such as the PUBACK of a `command_result`; a
/// command read after that sent a bare ACK of its own at once, ahead of its frame, and its PUBACK
/// went as a second packet. Reads closer together than this cost no system call.
const ACK_QUIET: Duration = Duration::from_millis(10);

/// One MQTT 3.1.1 client connection that reconnects when polled after a failure.
pub struct Connection {
    options: MqttOptions,
    /// Largest packet accepted from the broker.
    max_incoming: usize,
    /// Largest packet written.
    max_outgoing: usize,
    /// Limit of the TCP connect, TLS handshake and CONNECT/CONNACK exchange together.
    connect_timeout: Duration,
    state: State,
    link: Link,
    /// A DISCONNECT is queued: `poll` says so once it has been written.
    disconnecting: bool,
    /// What `poll` returns next, before anything else.
    notice: Option<Event>,
    /// A request the state refused or that could not be encoded, or the session gave the link up:
    /// the connection is broken.
    broken: Option<ConnectionError>,
    /// SUBSCRIBEs and UNSUBSCRIBEs of this connection whose SUBACK or UNSUBACK has not come yet
    /// (a request made while down is never sent).
    replies_due: usize,
    /// The fewest bytes a PUBLISH the broker may deliver on this connection takes on the wire:
    /// the smallest over its subscriptions (an unsubscription does not raise it: a delivery may
    /// still be on its way). `None` before any subscription, and over TLS, whose records the
    /// kernel counts and whose partial records the TLS layer holds.
    smallest_publish: Option<u16>,
    /// Successful writes to the broker's socket, over every connection: each a system call and,
    /// with `TCP_NODELAY`, a segment that wakes the broker.
    writes: Arc<AtomicU64>,
    /// PUBACKs queued and not yet encoded, oldest first: encoded ahead of any other packet, and
    /// written with it, or on their own unless [`Connection::hold_acks`] holds them back.
    acks: Vec<u16>,
    /// Whether PUBACKs alone (fewer than [`ACKS_HELD`]) wait for the next write of something else.
    hold_acks: bool,
}

enum Link {
    Down,
    Connecting(Attempt),
    Up(Up),
}

/// An established connection and its buffers.
struct Up {
    stream: Box<dyn Stream>,
    /// The TCP socket under `stream`, for its receive low-water mark.
    fd: RawFd,
    /// The low-water mark set on `fd` (bytes); `None` once the system refused one.
    lowat: Option<u16>,
    /// Received bytes not yet parsed (starts with what followed the CONNACK).
    read: BytesMut,
    /// Encoded packets not yet written.
    write: BytesMut,
    /// Written to the stream but not flushed yet (TLS buffers).
    unflushed: bool,
    /// When bytes were last read or delayed-ACK mode last renewed, whichever came later;
    /// `None` once the system refused the mode.
    acks_delayed_at: Option<Instant>,
}

/// What one round of I/O produced.
enum Io {
    /// New bytes in the read buffer.
    Read,
    /// The broker closed the connection.
    Closed,
    /// Everything queued was written and flushed.
    Flushed,
}

impl Connection {
    /// A connection to the broker of `options` (its keep-alive, clean session, credentials, last
    /// will, in-flight window, packet size limits, manual acks and transport apply), not yet
    /// attempted: the first [`poll`](Self::poll) connects.
    pub fn new(options: MqttOptions, max_outgoing: usize, connect_timeout: Duration) -> Connection {
        let max_incoming = options.max_packet_size();
        let state = State::new(options.inflight(), options.manual_acks());
        Connection {
            options,
            max_incoming,
            max_outgoing,
            connect_timeout,
            state,
            link: Link::Down,
            disconnecting: false,
            notice: None,
            broken: None,
            replies_due: 0,
            smallest_publish: None,
            writes: Arc::default(),
            acks: Vec::new(),
            hold_acks: false,
        }
    }

    /// Counts the writes to the broker's socket in `counter` from now on.
    pub fn count_writes_in(&mut self, counter: Arc<AtomicU64>) {
        self.writes = counter;
    }

    /// Connected (a CONNACK accepted and no error since).
    pub fn is_up(&self) -> bool {
        matches!(self.link, Link::Up(_))
    }

    /// Queues a QoS 1 publication, unless the connection is not up, the in-flight window (the
    /// options' `inflight`) is full or [`WRITE_BATCH`] bytes already wait for the next write: then
    /// it is handed back, to be offered again later.
    pub fn publish(
        &mut self,
        topic: String,
        payload: Bytes,
        retain: bool,
    ) -> Result<(), (String, Bytes)> {
        let Link::Up(up) = &self.link else {
            return Err((topic, payload));
        };
        if up.write.len() >= WRITE_BATCH || self.state.window_full() {
            return Err((topic, payload));
        }
        let mut p = Publish::from_bytes(topic, QoS::AtLeastOnce, payload);
        p.retain = retain;
        self.request(Request::Publish(p));
        Ok(())
    }

    /// Queues a subscription.
    pub fn subscribe(&mut self, filter: String, qos: QoS) {
        if self.is_up() && matches!(self.options.transport(), Transport::Tcp) {
            let smallest = smallest_publish(&filter);
            self.smallest_publish =
                Some(self.smallest_publish.map_or(smallest, |s| s.min(smallest)));
        }
        self.replies_due += usize::from(self.is_up());
        self.request(Request::Subscribe(Subscribe::new(filter, qos)));
    }

    /// Queues an unsubscription.
    pub fn unsubscribe(&mut self, filter: String) {
        self.replies_due += usize::from(self.is_up());
        self.request(Request::Unsubscribe(Unsubscribe::new(filter)));
    }

    /// Queues the acknowledgement of a received QoS 1 publication (manual acks). It leaves with the
    /// next packet written, or on its own as [`Connection::hold_acks`] says.
    pub fn ack(&mut self, pkid: u16) {
        if self.is_up() {
            self.acks.push(pkid);
        }
    }

    /// Whether PUBACKs with nothing else to write wait (while fewer than [`ACKS_HELD`]) for the next
    /// packet that is: the caller holds them when it knows that something will be written soon —
    /// the gateway while the core has commands out whose answers it will publish and none waits
    /// for it, so that a lone command's PUBACK leaves with its answer, one write and one segment
    /// instead of two. Holding an acknowledgement only delays when the broker may count the
    /// delivery done; it never changes that it is acknowledged.
    pub fn hold_acks(&mut self, hold: bool) {
        self.hold_acks = hold;
    }

    /// Queues a PINGREQ (the session asks for one at the keep-alive, and to probe a silent link;
    /// never while one is awaited).
    pub fn ping(&mut self) {
        self.request(Request::PingReq(rumqttc::PingReq));
    }

    /// Gives the link up: the next `poll` ends the connection with `why` (an I/O error of kind
    /// `TimedOut`), like a broken socket, and the one after reconnects.
    pub fn close(&mut self, why: String) {
        if self.is_up() {
            let e = io::Error::new(io::ErrorKind::TimedOut, why);
            self.broken.get_or_insert(ConnectionError::Io(e));
        }
    }

    /// Queues a DISCONNECT; `poll` returns `Event::Outgoing(Outgoing::Disconnect)` once it (and
    /// everything queued before it) is written.
    pub fn disconnect(&mut self) {
        self.disconnecting = true;
        self.request(Request::Disconnect(rumqttc::Disconnect));
    }

    /// After a connection error: the publications the broker had not acknowledged, oldest first.
    /// The next session is clean, so they are the caller's to send again.
    pub fn take_back(&mut self) -> Vec<Publish> {
        self.state.take_back()
    }

    /// Encodes a request into the write buffer (nothing is written before the next `poll`). A
    /// request the state refuses or that cannot be encoded breaks the connection: the next `poll`
    /// reports it.
    fn request(&mut self, request: Request) {
        self.encode_acks();
        self.encode(request);
    }

    /// Encodes the queued PUBACKs, in the order their publications came (MQTT 3.1.1, 4.6).
    fn encode_acks(&mut self) {
        let mut acks = std::mem::take(&mut self.acks);
        for pkid in acks.drain(..) {
            self.encode(Request::PubAck(PubAck::new(pkid)));
        }
        // The same allocation next time.
        self.acks = acks;
    }

    fn encode(&mut self, request: Request) {
        let Link::Up(up) = &mut self.link else {
            return;
        };
        if let Err(e) = self.state.send(request, &mut up.write, self.max_outgoing) {
            self.broken.get_or_insert(e.into());
        }
    }

    /// Writes what is queued, reads what arrived, reconnects after a failure, and returns the next
    /// event: every incoming packet (the first after a connection is its `ConnAck`), and
    /// `Outgoing::Disconnect` once a queued DISCONNECT is written. An error ends the connection;
    /// the next call starts a new attempt. Cancel-safe.
    pub async fn poll(&mut self) -> Result<Event, ConnectionError> {
        loop {
            if let Some(event) = self.next_event() {
                return Ok(event);
            }
            let step = match self.broken.take() {
                Some(e) => Err(e),
                None => self.advance().await,
            };
            match step {
                Ok(()) => {}
                Err(e) => {
                    self.link = Link::Down;
                    self.disconnecting = false;
                    // Acknowledgements of the lost connection's deliveries mean nothing on the next.
                    self.acks.clear();
                    self.state.forget_incoming();
                    return Err(e);
                }
            }
        }
    }

    /// The next event [`Connection::poll`] would return without reading or writing: what the last
    /// read brought and is not handed out yet. `None` once all of it was.
    pub fn next_read(&mut self) -> Option<Event> {
        self.next_event()
    }

    /// The next event: a notice (the ConnAck of a new connection, a DISCONNECT written), else the
    /// next incoming packet the state has buffered (its outgoing notices are dropped: the caller
    /// knows what it queued).
    fn next_event(&mut self) -> Option<Event> {
        if let Some(event) = self.notice.take() {
            return Some(event);
        }
        self.state.next_incoming().map(Event::Incoming)
    }

    /// One step: start or continue a connection attempt, or one round of I/O.
    async fn advance(&mut self) -> Result<(), ConnectionError> {
        if self.acks_due() {
            self.encode_acks();
        }
        match &mut self.link {
            Link::Down => {
                self.link = Link::Connecting(Box::pin(connect(
                    self.options.clone(),
                    self.max_incoming,
                    self.connect_timeout,
                )));
                Ok(())
            }
            Link::Connecting(attempt) => {
                let (up, connack) = attempt.as_mut().await?;
                self.link = Link::Up(up);
                self.replies_due = 0;
                self.smallest_publish = None;
                self.notice = Some(Event::Incoming(Packet::ConnAck(connack)));
                // What came right behind the CONNACK.
                Ok(self.parse()?)
            }
            Link::Up(up) => {
                up.set_lowat(wanted_lowat(
                    self.state.inflight(),
                    self.state.awaits_pingresp(),
                    self.replies_due,
                    !up.read.is_empty(),
                    self.smallest_publish,
                    self.options.inflight(),
                ));
                let writes = &self.writes;
                let io = std::future::poll_fn(|cx| up.poll_io(cx, writes)).await?;
                match io {
                    Io::Closed => Err(ConnectionError::MqttState(StateError::ConnectionAborted)),
                    Io::Flushed => {
                        if std::mem::take(&mut self.disconnecting) {
                            self.notice = Some(Event::Outgoing(Outgoing::Disconnect));
                        }
                        Ok(())
                    }
                    Io::Read => Ok(self.parse()?),
                }
            }
        }
    }
}

impl Connection {
    /// Queued PUBACKs are to be written in this round of I/O: nothing holds them, there are
    /// [`ACKS_HELD`] of them, or other packets go anyway.
    fn acks_due(&self) -> bool {
        let Link::Up(up) = &self.link else {
            return false;
        };
        !self.acks.is_empty()
            && (!self.hold_acks || self.acks.len() >= ACKS_HELD || !up.write.is_empty())
    }

    /// Hands every complete packet in the read buffer to the state; its replies are queued.
    fn parse(&mut self) -> Result<(), StateError> {
        let Link::Up(up) = &mut self.link else {
            return Ok(());
        };
        loop {
            let packet = match Packet::read(&mut up.read, self.max_incoming) {
                Ok(p) => p,
                Err(mqttbytes::Error::InsufficientBytes(_)) => return Ok(()),
                Err(e) => return Err(StateError::Deserialization(e)),
            };
            if let Packet::SubAck(_) | Packet::UnsubAck(_) = packet {
                self.replies_due = self.replies_due.saturating_sub(1);
            }
            self.state
                .handle_incoming(packet, &mut up.write, self.max_outgoing)?;
        }
    }
}

impl Up {
    fn new(stream: Box<dyn Stream>, fd: RawFd, read: BytesMut) -> Up {
        Up {
            stream,
            fd,
            lowat: Some(1),
            read,
            write: BytesMut::with_capacity(READ_CHUNK),
            unflushed: false,
            acks_delayed_at: Some(Instant::now()),
        }
    }

    /// Puts the socket back into delayed-ACK mode before a read when neither a read nor a renewal
    /// came within [`ACK_QUIET`], so that the read does not send a bare ACK: the command's
    /// PUBACK, written after its frame, carries it. A system that refuses the option acknowledges
    /// as before.
    fn delay_acks(&mut self) {
        if self.acks_delayed_at.is_none_or(|t| t.elapsed() < ACK_QUIET) {
            return;
        }
        // `fd` is the TCP socket under `stream`, which lives as long as `self`.
        match sockopt::delay_acks(self.fd) {
            Ok(()) => self.acks_delayed_at = Some(Instant::now()),
            Err(e) => {
                tracing::debug!("TCP_QUICKACK refused ({e}): reads may acknowledge at once");
                self.acks_delayed_at = None;
            }
        }
    }

    /// Sets the socket's receive low-water mark: the kernel reports the socket readable only once
    /// `bytes` have arrived (or the connection ended). Linux wakes a reader at once when a lowered
    /// mark is already reached. A system that refuses the option keeps the mark at 1 (every PUBACK
    /// wakes the gateway, as without it).
    fn set_lowat(&mut self, bytes: u16) {
        if self.lowat.is_none_or(|now| now == bytes) {
            return;
        }
        // `fd` is the TCP socket under `stream`, which lives as long as `self`.
        match sockopt::set_rcvlowat(self.fd, bytes) {
            Ok(()) => self.lowat = Some(bytes),
            Err(e) => {
                tracing::debug!("SO_RCVLOWAT refused ({e}): every PUBACK is read as it comes");
                self.lowat = None;
            }
        }
    }

    /// Writes and flushes everything queued (counting the writes in `writes`), then waits for
    /// input.
    fn poll_io(
        &mut self,
        cx: &mut std::task::Context<'_>,
        writes: &AtomicU64,
    ) -> Poll<Result<Io, ConnectionError>> {
        while !self.write.is_empty() {
            match Pin::new(&mut self.stream).poll_write(cx, &self.write) {
                Poll::Ready(Ok(0)) => return Poll::Ready(Ok(Io::Closed)),
                Poll::Ready(Ok(n)) => {
                    self.write.advance(n);
                    self.unflushed = true;
                    writes.fetch_add(1, Ordering::Relaxed);
                }
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e.into())),
                Poll::Pending => break,
            }
        }
        if self.write.is_empty() && self.unflushed {
            match Pin::new(&mut self.stream).poll_flush(cx) {
                Poll::Ready(Ok(())) => {
                    self.unflushed = false;
                    return Poll::Ready(Ok(Io::Flushed));
                }
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e.into())),
                Poll::Pending => {}
            }
        }
        if self.read.capacity() - self.read.len() < READ_CHUNK / 4 {
            self.read.reserve(READ_CHUNK);
        }
        self.delay_acks();
        match tokio_util::io::poll_read_buf(Pin::new(&mut self.stream), cx, &mut self.read) {
            Poll::Ready(Ok(0)) => return Poll::Ready(Ok(Io::Closed)),
            Poll::Ready(Ok(_)) => {
                if let Some(t) = &mut self.acks_delayed_at {
                    *t = Instant::now();
                }
                return Poll::Ready(Ok(Io::Read));
            }
            Poll::Ready(Err(e)) => return Poll::Ready(Err(e.into())),
            Poll::Pending => {}
        }
        Poll::Pending
    }
}

/// The receive low-water mark for the connection's state, the largest that strands nothing:
///
/// - 1 byte while a PINGRESP, SUBACK or UNSUBACK is awaited (any smaller than a raised mark), or
///   while the read buffer holds the start of a packet (its rest may be short);
/// - else the smallest PUBLISH the broker may deliver (`smallest_publish`): a command always wakes
///   the gateway at once, and up to a few PUBACKs, which need no answer, wait in the kernel for the
///   next wake-up (a command, more PUBACKs, the keep-alive's PINGRESP) instead of each waking it;
/// - and while more than [`ACK_BATCH`] publications are in flight, at least that many PUBACKs'
///   bytes: they are sure to come, and a command waits at most for them.
///
/// Never more than the PUBACKs of a full in-flight window (`window`) bring, so a window waiting
/// for room is always woken.
fn wanted_lowat(
    inflight: u16,
    awaits_pingresp: bool,
    replies_due: usize,
    partial: bool,
    smallest_publish: Option<u16>,
    window: u16,
) -> u16 {
    if awaits_pingresp || replies_due > 0 || partial {
        return 1;
    }
    let acks = if inflight > ACK_BATCH {
        ACK_BATCH * PUBACK_LEN
    } else {
        1
    };
    acks.max(smallest_publish.unwrap_or(1))
        .min(window.saturating_mul(PUBACK_LEN))
        .max(1)
}

/// The fewest bytes of a PUBLISH whose topic matches `filter`: a 2-byte fixed header, the topic's
/// 2-byte length, the shortest topic matching (`+` may match an empty level, `/#` no level at all,
/// and a topic has at least one byte), no packet id (QoS 0) and no payload.
fn smallest_publish(filter: &str) -> u16 {
    let filter = filter
        .strip_suffix("/#")
        .or_else(|| filter.strip_suffix('#'))
        .unwrap_or(filter);
    let topic: usize = filter
        .split('/')
        .map(|level| if level == "+" { 0 } else { level.len() })
        .sum::<usize>()
        + filter.matches('/').count();
    u16::try_from(4 + topic.max(1)).unwrap_or(u16::MAX)
}

/// TCP (with `TCP_NODELAY`: every QoS 1 round trip would otherwise wait for Nagle), TLS when the
/// options ask for it, then CONNECT and an accepted CONNACK, all within `timeout`.
async fn connect(
    options: MqttOptions,
    max_incoming: usize,
    timeout: Duration,
) -> Result<(Up, ConnAck), ConnectionError> {
    let attempt = async {
        let (host, port) = options.broker_address();
        let tcp = tcp_connect(&host, port).await?;
        let fd = tcp.as_raw_fd();
        let mut stream: Box<dyn Stream> = match options.transport() {
            Transport::Tcp => Box::new(tcp),
            #[cfg(feature = "tls")]
            Transport::Tls(tls) => Box::new(tls_connect(&host, tls, tcp).await?),
            #[allow(unreachable_patterns)]
            _ => {
                return Err(ConnectionError::Io(io::Error::other(
                    "this transport is not supported by the gateway",
                )))
            }
        };
        let mut connect = Connect::new(options.client_id());
        connect.keep_alive = options.keep_alive().as_secs().min(u16::MAX as u64) as u16;
        connect.clean_session = options.clean_session();
        connect.last_will = options.last_will();
        connect.login = options.credentials();
        let mut buf = BytesMut::new();
        Packet::Connect(connect)
            .write(&mut buf, usize::MAX)
            .map_err(StateError::Deserialization)?;
        stream.write_all(&buf).await?;
        stream.flush().await?;
        let mut read = BytesMut::with_capacity(READ_CHUNK);
        let connack = loop {
            match Packet::read(&mut read, max_incoming) {
                Ok(Packet::ConnAck(c)) if c.code == ConnectReturnCode::Success => break c,
                Ok(Packet::ConnAck(c)) => return Err(ConnectionError::ConnectionRefused(c.code)),
                Ok(other) => return Err(ConnectionError::NotConnAck(other)),
                Err(mqttbytes::Error::InsufficientBytes(_)) => {}
                Err(e) => return Err(StateError::Deserialization(e).into()),
            }
            read.reserve(READ_CHUNK);
            if tokio::io::AsyncReadExt::read_buf(&mut stream, &mut read).await? == 0 {
                return Err(StateError::ConnectionAborted.into());
            }
        };
        Ok((Up::new(stream, fd, read), connack))
    };
    tokio::time::timeout(timeout, attempt)
        .await
        .map_err(|_| ConnectionError::NetworkTimeout)?
}

async fn tcp_connect(host: &str, port: u16) -> io::Result<tokio::net::TcpStream> {
    let mut last = None;
    for addr in tokio::net::lookup_host((host, port)).await? {
        let socket = if addr.is_ipv4() {
            TcpSocket::new_v4()?
        } else {
            TcpSocket::new_v6()?
        };
        socket.set_nodelay(true)?;
        match socket.connect(addr).await {
            Ok(s) => return Ok(s),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| {
        io::Error::new(
            io::ErrorKind::InvalidInput,
            "the broker's name resolves to no address",
        )
    }))
}

#[cfg(feature = "tls")]
async fn tls_connect(
    host: &str,
    tls: rumqttc::TlsConfiguration,
    tcp: tokio::net::TcpStream,
) -> Result<rumqttc::tokio_rustls::client::TlsStream<tokio::net::TcpStream>, ConnectionError> {
    use rumqttc::tokio_rustls::rustls::pki_types::ServerName;
    let config = match tls {
        rumqttc::TlsConfiguration::Rustls(config) => config,
        #[allow(unreachable_patterns)]
        _ => {
            return Err(ConnectionError::Io(io::Error::other(
                "TLS configuration not built by the gateway",
            )))
        }
    };
    let name = ServerName::try_from(host.to_owned())
        .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
    let connector = rumqttc::tokio_rustls::TlsConnector::from(config);
    Ok(connector.connect(name, tcp).await?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mqtt::test_broker::{broker, broker_seeing, puback, Script};
    use rumqttc::Incoming;

    const PUBLISHED: u16 = ACK_BATCH + 4;

    /// The socket's receive low-water mark as the kernel has it.
    fn kernel_lowat(conn: &Connection) -> libc::c_int {
        let Link::Up(up) = &conn.link else {
            panic!("not connected")
        };
        sockopt::rcvlowat(up.fd).unwrap()
    }

    /// Polls until `n` PUBACKs came (other events are not expected), within 5 s.
    async fn acks(conn: &mut Connection, n: usize) -> Vec<u16> {
        let mut got = Vec::new();
        while got.len() < n {
            let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
            match ev.expect("PUBACKs within 5 s").unwrap() {
                Event::Incoming(Incoming::PubAck(a)) => got.push(a.pkid),
                other => panic!("{other:?}"),
            }
        }
        got
    }

    /// Connected (its CONNACK read).
    async fn connected(options: MqttOptions) -> Connection {
        let mut conn = Connection::new(options, 1 << 20, Duration::from_secs(5));
        let ev = conn.poll().await.unwrap();
        assert!(
            matches!(ev, Event::Incoming(Incoming::ConnAck(_))),
            "{ev:?}"
        );
        conn
    }

    /// `n` publications written, none acknowledged.
    async fn publish(conn: &mut Connection, n: u16) {
        for n in 0..n {
            conn.publish("EventsTopic".into(), vec![n as u8].into(), false)
                .unwrap();
        }
        // Writes them, then waits for input that does not come yet.
        let _ = tokio::time::timeout(Duration::from_millis(100), conn.poll()).await;
    }

    /// Connected, with `PUBLISHED` publications written and none acknowledged.
    async fn connected_with_publications(options: MqttOptions) -> Connection {
        let mut conn = connected(options).await;
        publish(&mut conn, PUBLISHED).await;
        conn
    }

    /// Many publications in flight: their PUBACKs are read a batch at a time (the kernel holds a
    /// lone one back), and none is stranded once fewer remain in flight than a batch.
    #[tokio::test]
    async fn acknowledgements_are_read_in_batches_and_none_is_stranded() {
        let (port, broker) = broker(None).await;
        let mut conn =
            connected_with_publications(MqttOptions::new("lowat", "127.0.0.1", port)).await;
        assert_eq!(
            kernel_lowat(&conn),
            libc::c_int::from(ACK_BATCH * PUBACK_LEN)
        );

        broker.send(puback(1)).unwrap();
        let early = tokio::time::timeout(Duration::from_millis(300), conn.poll()).await;
        assert!(early.is_err(), "a lone PUBACK woke the client: {early:?}");
        for pkid in 2..=ACK_BATCH {
            broker.send(puback(pkid)).unwrap();
        }
        let batch = acks(&mut conn, ACK_BATCH.into()).await;
        assert_eq!(batch, (1..=ACK_BATCH).collect::<Vec<_>>());

        // Four left in flight: each PUBACK is read as it comes.
        for pkid in ACK_BATCH + 1..=PUBLISHED {
            broker.send(puback(pkid)).unwrap();
            assert_eq!(acks(&mut conn, 1).await, vec![pkid]);
        }
    }

    /// A read after a quiet spell first puts the socket into delayed-ACK mode: the read of a
    /// command sends no bare ACK of its own, its PUBACK carries it.
    #[tokio::test]
    async fn a_read_after_a_quiet_spell_leaves_the_ack_to_the_reply() {
        let (port, broker) = broker(None).await;
        let mut conn = connected(MqttOptions::new("delayed-acks", "127.0.0.1", port)).await;
        let quickack = |conn: &Connection| {
            let Link::Up(up) = &conn.link else {
                panic!("not connected")
            };
            sockopt::quickack(up.fd).unwrap()
        };
        assert!(quickack(&conn), "a new connection acknowledges at once");
        tokio::time::sleep(ACK_QUIET * 2).await;
        let (publish, _) = command("CommandsTopic", usize::MAX);
        broker.send(publish).unwrap();
        let ev = next(&mut conn).await;
        assert!(
            matches!(&ev, Event::Incoming(Incoming::Publish(p)) if p.topic == "CommandsTopic"),
            "{ev:?}"
        );
        assert!(!quickack(&conn), "the read left the ACK to the reply");
    }

    /// A QoS 0 PUBLISH of `topic`, empty, cut after `cut` bytes: (head, rest).
    fn command(topic: &str, cut: usize) -> (Vec<u8>, Vec<u8>) {
        let mut p = vec![0x30, 2 + topic.len() as u8, 0, topic.len() as u8];
        p.extend_from_slice(topic.as_bytes());
        let rest = p.split_off(cut.min(p.len()));
        (p, rest)
    }

    /// Subscribed to `CommandsTopic` (its SUBACK read), then `n` publications written and none
    /// acknowledged (packet ids 1..=n).
    async fn subscribed_with_publications(port: u16, broker: &Script, n: u16) -> Connection {
        let options = MqttOptions::new("lowat-commands", "127.0.0.1", port);
        // Subscriptions take the packet ids above the publications'.
        let [hi, lo] = (options.inflight() + 1).to_be_bytes();
        let mut conn = connected(options).await;
        conn.subscribe("CommandsTopic".into(), QoS::AtLeastOnce);
        broker.send(vec![0x90, 0x03, hi, lo, 0x01]).unwrap(); // SUBACK, granted QoS 1
        let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
        assert!(
            matches!(ev, Ok(Ok(Event::Incoming(Incoming::SubAck(_))))),
            "{ev:?}"
        );
        publish(&mut conn, n).await;
        conn
    }

    /// The next event within 5 s.
    async fn next(conn: &mut Connection) -> Event {
        let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
        ev.expect("an event within 5 s").unwrap()
    }

    /// What the broker read within `wait`, and the writes counted meanwhile, polling `conn`.
    async fn written(
        conn: &mut Connection,
        seen: &mut tokio::sync::mpsc::UnboundedReceiver<Vec<u8>>,
        writes: &AtomicU64,
        wait: Duration,
    ) -> (Vec<u8>, u64) {
        let before = writes.load(Ordering::Relaxed);
        let _ = tokio::time::timeout(wait, conn.poll()).await;
        let mut bytes = Vec::new();
        while let Ok(b) = seen.try_recv() {
            bytes.extend(b);
        }
        (bytes, writes.load(Ordering::Relaxed) - before)
    }

    /// Held PUBACKs wait for the next packet written and leave in its write, ahead of it; with
    /// [`ACKS_HELD`] of them, or once not held, they leave on their own.
    #[tokio::test]
    async fn held_acks_leave_with_the_next_write() {
        let (port, _broker, mut seen) = broker_seeing(None).await;
        let mut conn = connected(MqttOptions::new("held-acks", "127.0.0.1", port)).await;
        let writes = Arc::new(AtomicU64::new(0));
        conn.count_writes_in(writes.clone());
        let wait = Duration::from_millis(200);

        conn.hold_acks(true);
        conn.ack(7);
        let (bytes, n) = written(&mut conn, &mut seen, &writes, wait).await;
        assert_eq!((bytes.len(), n), (0, 0), "a held PUBACK was written alone");
        conn.publish("EventsTopic".into(), Bytes::from_static(b"x"), false)
            .unwrap();
        let (bytes, n) = written(&mut conn, &mut seen, &writes, wait).await;
        assert_eq!(n, 1, "the PUBACK and the publication took {n} writes");
        assert_eq!(bytes[..4], puback(7), "{bytes:02x?}");
        assert!(
            bytes.windows(11).any(|w| w == b"EventsTopic"),
            "{bytes:02x?}"
        );

        let held = u16::try_from(ACKS_HELD).unwrap();
        for pkid in 1..held {
            conn.ack(pkid);
        }
        let (bytes, n) = written(&mut conn, &mut seen, &writes, wait).await;
        assert_eq!(
            (bytes.len(), n),
            (0, 0),
            "fewer than ACKS_HELD were written"
        );
        conn.ack(held);
        let (bytes, n) = written(&mut conn, &mut seen, &writes, wait).await;
        assert_eq!(n, 1);
        assert_eq!(bytes, (1..=held).flat_map(puback).collect::<Vec<_>>());

        conn.hold_acks(false);
        conn.ack(9);
        let (bytes, n) = written(&mut conn, &mut seen, &writes, wait).await;
        assert_eq!((bytes, n), (puback(9), 1), "an ack not held waited");
    }

    /// PUBACKs held when the connection breaks are not written on the next one, whose deliveries
    /// they do not acknowledge.
    #[tokio::test]
    async fn held_acks_end_with_their_connection() {
        let (port, _broker, _seen) = broker_seeing(Some(0)).await;
        let mut conn = connected(MqttOptions::new("held-acks-lost", "127.0.0.1", port)).await;
        conn.hold_acks(true);
        conn.ack(3);
        // The broker hangs up at once (`Some(0)` reads): the next poll reports it.
        let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
        assert!(matches!(ev, Ok(Err(_))), "{ev:?}");
        assert!(conn.acks.is_empty());
    }

    /// The smallest publication a subscription can bring, for the filters the gateway subscribes.
    #[test]
    fn smallest_publication_of_a_filter() {
        assert_eq!(smallest_publish("CommandsTopic"), 4 + 13);
        assert_eq!(smallest_publish("ihex/node/+/state"), 4 + 16);
        assert_eq!(smallest_publish("ihex/ha/+/+/set"), 4 + 13);
        assert_eq!(smallest_publish("ihex/fw/#"), 4 + 7);
        assert_eq!(smallest_publish("#"), 5);
        assert_eq!(smallest_publish("+"), 5);
        assert_eq!(smallest_publish("+/+"), 5);
    }

    /// The low-water mark never holds a command back: whatever the state, a PUBLISH the
    /// subscriptions allow reaches the mark at once unless more than a batch of PUBACKs, which the
    /// broker sends right behind the publications, is sure to come first; and a full window's
    /// PUBACKs always reach it.
    #[test]
    fn the_low_water_mark_never_holds_a_command_back() {
        let window = 100;
        for inflight in 0..=window {
            for smallest in [None, Some(5), Some(17), Some(40), Some(500)] {
                for (ping, replies, partial) in [
                    (false, 0, false),
                    (true, 0, false),
                    (false, 1, false),
                    (false, 0, true),
                ] {
                    let mark = wanted_lowat(inflight, ping, replies, partial, smallest, window);
                    assert!(mark >= 1);
                    if ping || replies > 0 || partial {
                        assert_eq!(
                            mark, 1,
                            "an awaited reply or a packet's rest is read at once"
                        );
                        continue;
                    }
                    if inflight <= ACK_BATCH {
                        assert!(
                            mark <= smallest.unwrap_or(1),
                            "{inflight} in flight: a command of {smallest:?} bytes waits (mark {mark})"
                        );
                    } else {
                        assert!(mark <= smallest.unwrap_or(1).max(ACK_BATCH * PUBACK_LEN));
                    }
                    assert!(
                        mark <= window * PUBACK_LEN,
                        "a full window's PUBACKs do not wake it"
                    );
                }
            }
        }
    }

    /// With a few publications in flight, a lone PUBACK waits in the kernel, while a command (the
    /// smallest the subscription allows) wakes the client at once and brings the PUBACK with it.
    #[tokio::test]
    async fn a_lone_acknowledgement_waits_but_a_command_does_not() {
        let (port, broker) = broker(None).await;
        let mut conn = subscribed_with_publications(port, &broker, 2).await;
        assert_eq!(
            kernel_lowat(&conn),
            libc::c_int::from(smallest_publish("CommandsTopic"))
        );

        broker.send(puback(1)).unwrap();
        let early = tokio::time::timeout(Duration::from_millis(300), conn.poll()).await;
        assert!(early.is_err(), "a lone PUBACK woke the client: {early:?}");

        broker.send(command("CommandsTopic", 17).0).unwrap();
        assert!(
            matches!(next(&mut conn).await, Event::Incoming(Incoming::PubAck(a)) if a.pkid == 1)
        );
        match next(&mut conn).await {
            Event::Incoming(Incoming::Publish(p)) => assert_eq!(p.topic, "CommandsTopic"),
            other => panic!("{other:?}"),
        }
        // The last PUBACK with nothing behind it: held too, never lost.
        broker.send(puback(2)).unwrap();
        let early = tokio::time::timeout(Duration::from_millis(300), conn.poll()).await;
        assert!(early.is_err(), "a lone PUBACK woke the client: {early:?}");
        assert_eq!(conn.state.inflight(), 1);
    }

    /// The start of a command read with a batch of PUBACKs: its short rest wakes the client.
    #[tokio::test]
    async fn the_rest_of_a_command_read_in_part_is_not_held_back() {
        let (port, broker) = broker(None).await;
        let mut conn = subscribed_with_publications(port, &broker, 5).await;
        let (head, rest) = command("CommandsTopic", 5);
        let mut burst: Vec<u8> = (1..=5).flat_map(puback).collect();
        burst.extend_from_slice(&head);
        broker.send(burst).unwrap();
        assert_eq!(acks(&mut conn, 5).await, vec![1, 2, 3, 4, 5]);

        assert!(rest.len() < usize::from(smallest_publish("CommandsTopic")));
        broker.send(rest).unwrap();
        match next(&mut conn).await {
            Event::Incoming(Incoming::Publish(p)) => assert_eq!(p.topic, "CommandsTopic"),
            other => panic!("{other:?}"),
        }
    }

    /// A SUBACK or a PINGRESP awaited is read at once, however many publications are in flight.
    #[tokio::test]
    async fn awaited_replies_are_not_held_back() {
        let (port, broker) = broker(None).await;
        let options = MqttOptions::new("lowat-replies", "127.0.0.1", port);
        // Subscriptions take the packet ids above the publications'.
        let [hi, lo] = (options.inflight() + 1).to_be_bytes();
        let mut conn = connected_with_publications(options).await;

        conn.subscribe("CommandsTopic".into(), QoS::AtLeastOnce);
        broker.send(vec![0x90, 0x03, hi, lo, 0x01]).unwrap(); // SUBACK, granted QoS 1
        let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
        assert!(
            matches!(ev, Ok(Ok(Event::Incoming(Incoming::SubAck(_))))),
            "{ev:?}"
        );

        // A PINGREQ (the session asks for one at the keep-alive): its 2-byte answer is read.
        conn.ping();
        let _ = tokio::time::timeout(Duration::from_millis(300), conn.poll()).await;
        assert!(conn.state.awaits_pingresp(), "the PINGREQ went out");
        broker.send(vec![0xd0, 0x00]).unwrap(); // PINGRESP
        let ev = tokio::time::timeout(Duration::from_secs(5), conn.poll()).await;
        assert!(
            matches!(ev, Ok(Ok(Event::Incoming(Incoming::PingResp)))),
            "{ev:?}"
        );
    }
}
