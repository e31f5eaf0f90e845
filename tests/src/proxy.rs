//! A TCP proxy for fault injection (between a gateway and its broker, or between two bridged
//! brokers): every connection can be passed, delayed, half-opened or cut, and switched at run time.
//!
//! [`Proxy::start`] listens on a free loopback port and connects each accepted client to the
//! upstream address. [`Proxy::set`] changes the [`Mode`] of every live connection and of those to
//! come; [`Proxy::links`] gives each live connection's [`Link`] to switch or inspect it alone.
//!
//! Each direction of a connection is a reader task feeding a bounded queue of chunks and a writer
//! task draining it, so a delay is a latency (every chunk leaves `delay` after it was read, in
//! order), not a throughput cap, and a half-open direction holds what it has read (at most
//! [`HOLD_CHUNKS`] chunks; then the sender's kernel buffers fill, as on a dead network path) and
//! delivers it intact, in order, if the link is passed again.

use std::io;
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch};
use tokio::task::{JoinHandle, JoinSet};
use tokio::time::Instant;

/// Chunks a direction holds between its reader and its writer before the reader waits.
pub const HOLD_CHUNKS: usize = 64;

/// Largest chunk read at once.
const CHUNK: usize = 16 * 1024;

/// A direction of a proxied connection.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Direction {
    /// Client to server (the side that connected to the proxy towards the upstream).
    ToServer,
    /// Server to client.
    ToClient,
    /// Both.
    Both,
}

impl Direction {
    fn includes(self, d: Direction) -> bool {
        self == Direction::Both || self == d
    }
}

/// What a connection does with its bytes.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Mode {
    /// Forward both ways as soon as read.
    Pass,
    /// Forward both ways, each chunk `delay` after it was read (order kept).
    Delay(Duration),
    /// Stop forwarding in these directions without closing anything (the "zombie" connection):
    /// bytes and end-of-stream wait in the proxy, nothing reaches the other side, no side learns
    /// that the path is dead except by its own timeouts. Passing again delivers what waited.
    HalfOpen(Direction),
    /// Close both sides of every connection now; new connections are accepted and closed at once
    /// (the peer sees a connection reset or end of stream) until the mode changes.
    Cut,
}

/// Byte counters of one direction.
#[derive(Debug, Default)]
pub struct Counters {
    read: AtomicU64,
    written: AtomicU64,
}

impl Counters {
    /// Bytes read from the sending side.
    pub fn read(&self) -> u64 {
        self.read.load(Ordering::SeqCst)
    }

    /// Bytes written to the receiving side.
    pub fn written(&self) -> u64 {
        self.written.load(Ordering::SeqCst)
    }
}

/// One proxied connection: its mode and byte counters.
#[derive(Clone, Debug)]
pub struct Link {
    id: u64,
    mode: watch::Sender<Mode>,
    to_server: Arc<Counters>,
    to_client: Arc<Counters>,
}

impl Link {
    /// Number of the connection in accept order (0 first).
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Switches this connection alone.
    pub fn set(&self, mode: Mode) {
        self.mode.send_replace(mode);
    }

    /// Its current mode.
    pub fn mode(&self) -> Mode {
        *self.mode.borrow()
    }

    /// Counters of one direction (`Both` is not a direction of its own: it gives `ToServer`).
    pub fn counters(&self, d: Direction) -> &Counters {
        match d {
            Direction::ToClient => &self.to_client,
            _ => &self.to_server,
        }
    }

    /// True while the connection is open (not cut and neither side closed it).
    pub fn is_open(&self) -> bool {
        !self.mode.is_closed()
    }
}

struct Shared {
    upstream: SocketAddr,
    mode: Mutex<Mode>,
    links: Mutex<Vec<Link>>,
    accepted: AtomicU64,
}

impl Shared {
    fn mode(&self) -> Mode {
        *self.mode.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn links(&self) -> std::sync::MutexGuard<'_, Vec<Link>> {
        self.links.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A running proxy; stops (closing every connection) when dropped.
pub struct Proxy {
    addr: SocketAddr,
    shared: Arc<Shared>,
    accept: Option<JoinHandle<()>>,
}

impl Proxy {
    /// Listens on a free loopback port and forwards each connection to `upstream` in [`Mode::Pass`].
    /// Must be called inside a tokio runtime.
    pub async fn start(upstream: SocketAddr) -> io::Result<Proxy> {
        let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await?;
        let addr = listener.local_addr()?;
        let shared = Arc::new(Shared {
            upstream,
            mode: Mutex::new(Mode::Pass),
            links: Mutex::new(Vec::new()),
            accepted: AtomicU64::new(0),
        });
        let accept = Some(tokio::spawn(accept_loop(listener, shared.clone())));
        Ok(Proxy {
            addr,
            shared,
            accept,
        })
    }

    /// Where clients connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Where connections are forwarded.
    pub fn upstream(&self) -> SocketAddr {
        self.shared.upstream
    }

    /// Switches every live connection and every later one.
    pub fn set(&self, mode: Mode) {
        *self.shared.mode.lock().unwrap_or_else(|p| p.into_inner()) = mode;
        for link in self.shared.links().iter() {
            link.set(mode);
        }
    }

    /// The mode new connections get.
    pub fn mode(&self) -> Mode {
        self.shared.mode()
    }

    /// The live connections, oldest first.
    pub fn links(&self) -> Vec<Link> {
        let mut links = self.shared.links();
        links.retain(Link::is_open);
        links.clone()
    }

    /// Stops listening: new connections are refused by the kernel (the client's connect fails with
    /// "connection refused", as when nothing runs at that address), live ones are left as they
    /// are. [`Proxy::listen`] listens on the same port again.
    pub fn refuse(&mut self) {
        if let Some(task) = self.accept.take() {
            task.abort();
        }
    }

    /// Listens again on the same port after [`Proxy::refuse`]. Must be called inside a tokio
    /// runtime.
    pub fn listen(&mut self) -> io::Result<()> {
        if self.accept.is_some() {
            return Ok(());
        }
        // std sets SO_REUSEADDR on Unix listeners, so the port can be bound again at once.
        let std = std::net::TcpListener::bind(self.addr)?;
        std.set_nonblocking(true)?;
        let listener = TcpListener::from_std(std)?;
        self.accept = Some(tokio::spawn(accept_loop(listener, self.shared.clone())));
        Ok(())
    }

    /// Connections accepted so far (including those closed at once while cut).
    pub fn accepted(&self) -> u64 {
        self.shared.accepted.load(Ordering::SeqCst)
    }
}

impl Drop for Proxy {
    fn drop(&mut self) {
        self.refuse();
        for link in self.shared.links().iter() {
            link.set(Mode::Cut);
        }
    }
}

async fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    loop {
        let Ok((client, _)) = listener.accept().await else {
            // Out of descriptors or similar: try again shortly rather than stop proxying.
            tokio::time::sleep(Duration::from_millis(10)).await;
            continue;
        };
        let id = shared.accepted.fetch_add(1, Ordering::SeqCst);
        let mode = shared.mode();
        if mode == Mode::Cut {
            drop(client);
            continue;
        }
        let shared = shared.clone();
        tokio::spawn(async move {
            // The upstream refusing is a fault of its own (a stopped broker): the client sees
            // its connection closed, as it would without the proxy.
            let Ok(server) = TcpStream::connect(shared.upstream).await else {
                return;
            };
            let _ = client.set_nodelay(true);
            let _ = server.set_nodelay(true);
            // The mode may have changed while connecting: take the current one.
            let (tx, rx) = watch::channel(shared.mode());
            let link = Link {
                id,
                mode: tx,
                to_server: Arc::default(),
                to_client: Arc::default(),
            };
            shared.links().push(link.clone());
            run_link(client, server, &link, rx).await;
            shared.links().retain(|l| l.id != id);
        });
    }
}

/// Runs one connection until it is cut or both directions ended.
async fn run_link(
    client: TcpStream,
    server: TcpStream,
    link: &Link,
    mut mode: watch::Receiver<Mode>,
) {
    let (client_r, client_w) = client.into_split();
    let (server_r, server_w) = server.into_split();
    let mut tasks = JoinSet::new();
    for (dir, r, w, counters) in [
        (
            Direction::ToServer,
            client_r,
            server_w,
            link.to_server.clone(),
        ),
        (
            Direction::ToClient,
            server_r,
            client_w,
            link.to_client.clone(),
        ),
    ] {
        let (tx, rx) = mpsc::channel(HOLD_CHUNKS);
        tasks.spawn(read_side(
            dir,
            r,
            tx,
            link.mode.subscribe(),
            counters.clone(),
        ));
        tasks.spawn(write_side(dir, w, rx, link.mode.subscribe(), counters));
    }
    loop {
        tokio::select! {
            changed = mode.changed() => {
                if changed.is_err() || *mode.borrow_and_update() == Mode::Cut {
                    break;
                }
            }
            done = tasks.join_next() => {
                if done.is_none() {
                    break;
                }
            }
        }
    }
    // Aborting drops every socket half: both connections close.
    tasks.abort_all();
    while tasks.join_next().await.is_some() {}
}

/// A chunk read, or the end of the stream, with the time it is due at the other side.
enum Item {
    Data(Vec<u8>, Instant),
    End(Instant),
}

/// Waits until `dir` is not held by a half-open mode; false when the link is cut or gone.
async fn wait_flowing(dir: Direction, mode: &mut watch::Receiver<Mode>) -> bool {
    loop {
        match *mode.borrow_and_update() {
            Mode::Cut => return false,
            Mode::HalfOpen(d) if d.includes(dir) => {}
            _ => return true,
        }
        if mode.changed().await.is_err() {
            return false;
        }
    }
}

fn delay_of(mode: &watch::Receiver<Mode>) -> Duration {
    match *mode.borrow() {
        Mode::Delay(d) => d,
        _ => Duration::ZERO,
    }
}

async fn read_side(
    _dir: Direction,
    mut r: OwnedReadHalf,
    tx: mpsc::Sender<Item>,
    mode: watch::Receiver<Mode>,
    counters: Arc<Counters>,
) {
    let mut buf = vec![0u8; CHUNK];
    loop {
        // Reading goes on while half-open (the writer holds the bytes), so the proxy, not the
        // sender's kernel, decides what waits; the bounded queue stops it after HOLD_CHUNKS.
        let n = match r.read(&mut buf).await {
            Ok(0) | Err(_) => {
                let _ = tx.send(Item::End(Instant::now() + delay_of(&mode))).await;
                return;
            }
            Ok(n) => n,
        };
        counters.read.fetch_add(n as u64, Ordering::SeqCst);
        let due = Instant::now() + delay_of(&mode);
        if tx.send(Item::Data(buf[..n].to_vec(), due)).await.is_err() {
            return;
        }
    }
}

async fn write_side(
    dir: Direction,
    mut w: OwnedWriteHalf,
    mut rx: mpsc::Receiver<Item>,
    mut mode: watch::Receiver<Mode>,
    counters: Arc<Counters>,
) {
    while let Some(item) = rx.recv().await {
        let due = match &item {
            Item::Data(_, due) | Item::End(due) => *due,
        };
        tokio::time::sleep_until(due).await;
        if !wait_flowing(dir, &mut mode).await {
            return;
        }
        match item {
            Item::Data(bytes, _) => {
                if w.write_all(&bytes).await.is_err() {
                    return;
                }
                counters
                    .written
                    .fetch_add(bytes.len() as u64, Ordering::SeqCst);
            }
            Item::End(_) => {
                let _ = w.shutdown().await;
                return;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An upstream that echoes every byte back, and tells how many connections it saw.
    async fn echo_server() -> (SocketAddr, Arc<AtomicU64>) {
        let l = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await.unwrap();
        let addr = l.local_addr().unwrap();
        let conns = Arc::new(AtomicU64::new(0));
        let c = conns.clone();
        tokio::spawn(async move {
            loop {
                let (mut s, _) = l.accept().await.unwrap();
                c.fetch_add(1, Ordering::SeqCst);
                tokio::spawn(async move {
                    let (mut r, mut w) = s.split();
                    let _ = tokio::io::copy(&mut r, &mut w).await;
                });
            }
        });
        (addr, conns)
    }

    /// An upstream that keeps each accepted socket for the test.
    async fn sink_server() -> (SocketAddr, mpsc::Receiver<TcpStream>) {
        let l = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await.unwrap();
        let addr = l.local_addr().unwrap();
        let (tx, rx) = mpsc::channel(8);
        tokio::spawn(async move {
            loop {
                let (s, _) = l.accept().await.unwrap();
                if tx.send(s).await.is_err() {
                    return;
                }
            }
        });
        (addr, rx)
    }

    async fn read_n(s: &mut TcpStream, n: usize) -> Vec<u8> {
        let mut buf = vec![0u8; n];
        crate::within_or_panic(Duration::from_secs(5), "bytes through the proxy", async {
            s.read_exact(&mut buf).await.unwrap();
        })
        .await;
        buf
    }

    async fn until(what: &str, mut cond: impl FnMut() -> bool) {
        crate::within_or_panic(Duration::from_secs(5), what, async {
            while !cond() {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        })
        .await;
    }

    async fn one_link(p: &Proxy) -> Link {
        let mut link = None;
        until("the proxy to register the connection", || {
            link = p.links().into_iter().next();
            link.is_some()
        })
        .await;
        link.unwrap()
    }

    #[tokio::test]
    async fn passes_bytes_both_ways_in_order() {
        let (up, conns) = echo_server().await;
        let p = Proxy::start(up).await.unwrap();
        let mut c = TcpStream::connect(p.addr()).await.unwrap();
        let data: Vec<u8> = (0..100_000u32).map(|i| (i % 251) as u8).collect();
        let (mut r, mut w) = c.split();
        let send = async {
            w.write_all(&data).await.unwrap();
        };
        let mut got = vec![0u8; data.len()];
        let recv = async {
            r.read_exact(&mut got).await.unwrap();
        };
        crate::within_or_panic(Duration::from_secs(10), "echo of 100 kB", async {
            tokio::join!(send, recv)
        })
        .await;
        assert_eq!(got, data);
        assert_eq!(conns.load(Ordering::SeqCst), 1);
        let link = one_link(&p).await;
        assert_eq!(link.counters(Direction::ToServer).written(), 100_000);
        assert_eq!(link.counters(Direction::ToClient).written(), 100_000);
    }

    #[tokio::test]
    async fn delay_holds_every_chunk_at_least_that_long() {
        let (up, _) = echo_server().await;
        let p = Proxy::start(up).await.unwrap();
        let delay = Duration::from_millis(150);
        p.set(Mode::Delay(delay));
        let mut c = TcpStream::connect(p.addr()).await.unwrap();
        for round in 0..3u8 {
            let sent = Instant::now();
            c.write_all(&[round; 10]).await.unwrap();
            assert_eq!(read_n(&mut c, 10).await, [round; 10]);
            // Through the proxy and back: the delay applies once per direction. A lower bound only:
            // the proxy must hold the bytes; how much longer it takes is the machine's business.
            assert!(
                sent.elapsed() >= delay * 2,
                "round {round}: {:?}",
                sent.elapsed()
            );
        }
        // Back to passing: later bytes are not held.
        p.set(Mode::Pass);
        assert_eq!(one_link(&p).await.mode(), Mode::Pass);
        c.write_all(b"x").await.unwrap();
        assert_eq!(read_n(&mut c, 1).await, b"x");
    }

    #[tokio::test]
    async fn half_open_holds_bytes_and_end_of_stream_until_passed_again() {
        let (up, mut servers) = sink_server().await;
        let p = Proxy::start(up).await.unwrap();
        let mut c = TcpStream::connect(p.addr()).await.unwrap();
        let mut s = servers.recv().await.unwrap();
        let link = one_link(&p).await;

        p.set(Mode::HalfOpen(Direction::ToServer));
        c.write_all(b"hello").await.unwrap();
        c.shutdown().await.unwrap();
        let up = link.counters(Direction::ToServer);
        until("the proxy to read the held bytes", || up.read() == 5).await;
        // The other direction still flows while this one is held.
        s.write_all(b"pong").await.unwrap();
        assert_eq!(read_n(&mut c, 4).await, b"pong");
        assert_eq!(up.written(), 0, "held bytes were forwarded");
        let mut probe = [0u8; 8];
        assert!(
            matches!(s.try_read(&mut probe), Err(e) if e.kind() == io::ErrorKind::WouldBlock),
            "the server saw data or an end of stream through a half-open link"
        );
        assert!(link.is_open());

        p.set(Mode::Pass);
        let mut rest = Vec::new();
        crate::within_or_panic(Duration::from_secs(5), "held bytes and EOF", async {
            s.read_to_end(&mut rest).await.unwrap();
        })
        .await;
        assert_eq!(
            rest, b"hello",
            "held bytes arrive intact, then the end of stream"
        );
    }

    #[tokio::test]
    async fn half_open_both_ways_is_a_zombie() {
        let (up, mut servers) = sink_server().await;
        let p = Proxy::start(up).await.unwrap();
        let mut c = TcpStream::connect(p.addr()).await.unwrap();
        let mut s = servers.recv().await.unwrap();
        let link = one_link(&p).await;
        link.set(Mode::HalfOpen(Direction::Both));
        c.write_all(b"ping").await.unwrap();
        s.write_all(b"pong").await.unwrap();
        until("both directions read by the proxy", || {
            link.counters(Direction::ToServer).read() == 4
                && link.counters(Direction::ToClient).read() == 4
        })
        .await;
        let mut probe = [0u8; 8];
        for side in [&mut c, &mut s] {
            assert!(
                matches!(side.try_read(&mut probe), Err(e) if e.kind() == io::ErrorKind::WouldBlock)
            );
        }
        link.set(Mode::Pass);
        assert_eq!(read_n(&mut s, 4).await, b"ping");
        assert_eq!(read_n(&mut c, 4).await, b"pong");
    }

    #[tokio::test]
    async fn cut_closes_both_sides_and_refuses_until_passed() {
        let (up, mut servers) = sink_server().await;
        let p = Proxy::start(up).await.unwrap();
        let mut c = TcpStream::connect(p.addr()).await.unwrap();
        let mut s = servers.recv().await.unwrap();
        let link = one_link(&p).await;

        p.set(Mode::Cut);
        let mut buf = [0u8; 8];
        for (name, side) in [("client", &mut c), ("server", &mut s)] {
            let r = crate::within_or_panic(
                Duration::from_secs(5),
                format!("{name} closed"),
                side.read(&mut buf),
            )
            .await;
            assert!(matches!(r, Ok(0) | Err(_)), "{name} read {r:?} after a cut");
        }
        until("the link to be gone", || {
            !link.is_open() && p.links().is_empty()
        })
        .await;

        // While cut, new connections are closed at once and never reach the server.
        let mut c2 = TcpStream::connect(p.addr()).await.unwrap();
        let r = crate::within_or_panic(
            Duration::from_secs(5),
            "refused connection closed",
            c2.read(&mut buf),
        )
        .await;
        assert!(matches!(r, Ok(0) | Err(_)));
        assert_eq!(p.accepted(), 2);

        // Passing again: a new connection works end to end.
        p.set(Mode::Pass);
        let mut c3 = TcpStream::connect(p.addr()).await.unwrap();
        let mut s3 = servers.recv().await.unwrap();
        c3.write_all(b"again").await.unwrap();
        assert_eq!(read_n(&mut s3, 5).await, b"again");
        assert!(
            servers.try_recv().is_err(),
            "the cut connection reached the server"
        );
    }

    #[tokio::test]
    async fn refusing_closes_the_port_until_listening_again() {
        let (up, _) = echo_server().await;
        let mut p = Proxy::start(up).await.unwrap();
        let mut live = TcpStream::connect(p.addr()).await.unwrap();
        one_link(&p).await;
        p.refuse();
        // The abort takes effect when the accept task next runs (a connection queued in the
        // backlog meanwhile is reset): wait until connects are refused.
        crate::within_or_panic(Duration::from_secs(5), "connections refused", async {
            loop {
                match TcpStream::connect(p.addr()).await {
                    Err(e) if e.kind() == io::ErrorKind::ConnectionRefused => return,
                    _ => tokio::time::sleep(Duration::from_millis(5)).await,
                }
            }
        })
        .await;
        live.write_all(b"still").await.unwrap();
        assert_eq!(
            read_n(&mut live, 5).await,
            b"still",
            "live connections are left alone"
        );
        p.listen().unwrap();
        let mut again = TcpStream::connect(p.addr()).await.unwrap();
        again.write_all(b"back").await.unwrap();
        assert_eq!(read_n(&mut again, 4).await, b"back");
    }

    #[tokio::test]
    async fn one_link_switched_alone() {
        let (up, _) = echo_server().await;
        let p = Proxy::start(up).await.unwrap();
        let mut a = TcpStream::connect(p.addr()).await.unwrap();
        let first = one_link(&p).await;
        let mut b = TcpStream::connect(p.addr()).await.unwrap();
        until("two links", || p.links().len() == 2).await;
        first.set(Mode::Cut);
        let mut buf = [0u8; 1];
        let r =
            crate::within_or_panic(Duration::from_secs(5), "first closed", a.read(&mut buf)).await;
        assert!(matches!(r, Ok(0) | Err(_)));
        b.write_all(b"k").await.unwrap();
        assert_eq!(read_n(&mut b, 1).await, b"k");
        assert_eq!(
            p.mode(),
            Mode::Pass,
            "switching one link leaves the proxy's mode"
        );
    }
}
