//! The embedded MQTT broker of the demo (rumqttd on its own std thread: `Broker::start` blocks and
//! builds its own runtimes). rumqttd's default configuration accepts no client at all and it has no
//! ready signal, so this module sets real limits, checks the port first for a clear error, and waits
//! until a TCP connect succeeds. It never turns Nagle's algorithm off either, so this module does
//! that on its listening socket and on any connection accepted before (`no_nagle`).

use std::{
    collections::HashSet,
    io,
    net::{SocketAddr, TcpListener, TcpStream},
    os::fd::RawFd,
    time::{Duration, Instant},
};

use crate::error::BrokerError;

/// How long to wait for the broker to accept connections.
const READY_TIMEOUT: Duration = Duration::from_secs(10);

/// Starts the broker on `listen` and returns once it accepts TCP connections. The broker thread
/// lives until the process exits.
pub fn start(listen: SocketAddr) -> Result<(), BrokerError> {
    use rumqttd::{Config, ConnectionSettings, RouterConfig, ServerSettings};
    use std::collections::HashMap;

    // rumqttd reports a taken port only in its own log: find out first.
    drop(
        TcpListener::bind(listen).map_err(|source| BrokerError::Bind {
            addr: listen,
            source,
        })?,
    );

    let connections = ConnectionSettings {
        connection_timeout_ms: 60_000,
        max_payload_size: 1 << 20,
        max_inflight_count: 500,
        auth: None,
        external_auth: None,
        dynamic_filters: true,
    };
    let server = ServerSettings {
        name: "v4-demo".into(),
        listen,
        tls: None,
        next_connection_delay_ms: 1,
        connections,
    };
    let config = Config {
        id: 0,
        router: RouterConfig {
            max_connections: 1000,
            max_outgoing_packet_count: 1000,
            max_segment_size: 16 << 20,
            max_segment_count: 10,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Default::default(),
        },
        v4: Some(HashMap::from([("1".to_owned(), server)])),
        ..Config::default()
    };
    std::thread::Builder::new()
        .name("embedded-broker".into())
        .spawn(move || {
            let mut broker = rumqttd::Broker::new(config);
            if let Err(e) = broker.start() {
                tracing::error!(error = %e, "embedded broker stopped");
            }
        })
        .map_err(|source| BrokerError::Bind {
            addr: listen,
            source,
        })?;
    wait_ready(listen)?;
    // Before `start` returns, so the gateway's own clients connect with it already set.
    if let Err(e) = no_nagle(listen) {
        tracing::warn!(
            error = %e,
            "embedded broker: Nagle's algorithm stays on for its clients (a command's round trip \
             may wait ~40 ms for a delayed ACK)"
        );
    }
    Ok(())
}

/// Turns Nagle's algorithm off on the broker's listening socket on `listen`, which the connections
/// it accepts from then on inherit (Linux), and on the connections it accepted before. rumqttd
/// 0.20 never sets `TCP_NODELAY` and has no option for it, and with Nagle on, a small packet that
/// follows another on the same socket waits for the client's delayed ACK of the first: a QoS 1
/// command's PUBACK to its publisher, then the `command_result` that publisher waits for, about
/// 40 ms later on Linux, on every round trip.
fn no_nagle(listen: SocketAddr) -> io::Result<()> {
    let fds = own_tcp_sockets(|local, _, state| local == listen.port() && state == TCP_LISTEN)?;
    if fds.is_empty() {
        return Err(io::Error::new(
            io::ErrorKind::NotFound,
            format!(
                "no listening socket of this process on port {}",
                listen.port()
            ),
        ));
    }
    fds.into_iter().try_for_each(crate::sys::set_nodelay)?;
    // The broker listens before this runs, so a client that connects as soon as the port answers
    // (a script waiting for it, the readiness probe) got a socket made without the option. Such a
    // socket is found once rumqttd has accepted it; one still in the accept queue has no
    // descriptor yet (inode 0 in the table) and is waited for, briefly. Best effort: a connection
    // may close between the look and the call.
    let deadline = Instant::now() + EARLY_ACCEPT;
    loop {
        let made =
            tcp_inodes(|local, _, state| local == listen.port() && state == TCP_ESTABLISHED)?;
        for fd in fds_of(&made)? {
            let _ = crate::sys::set_nodelay(fd);
        }
        if !made.contains(&0) || Instant::now() >= deadline {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

/// `st` of a listening socket in /proc/net/tcp.
const TCP_LISTEN: u8 = 0x0A;
/// `st` of an established connection in /proc/net/tcp.
const TCP_ESTABLISHED: u8 = 0x01;
/// How long rumqttd may take to accept a connection made before Nagle was turned off.
const EARLY_ACCEPT: Duration = Duration::from_millis(20);

/// This process's TCP sockets that `wanted(local port, remote port, state)` picks: rumqttd keeps
/// its sockets to itself, so they are found through the kernel's socket tables (/proc/net/tcp and
/// tcp6, whose inodes name the sockets) and this process's descriptors (/proc/self/fd).
fn own_tcp_sockets(wanted: impl Fn(u16, u16, u8) -> bool) -> io::Result<Vec<RawFd>> {
    fds_of(&tcp_inodes(wanted)?)
}

/// The inodes of the kernel's TCP sockets that `wanted(local port, remote port, state)` picks
/// (0: a connection not yet accepted, or one without a socket any more).
fn tcp_inodes(wanted: impl Fn(u16, u16, u8) -> bool) -> io::Result<HashSet<u64>> {
    let hex_port = |a: &str| u16::from_str_radix(a.rsplit(':').next()?, 16).ok();
    let mut inodes = HashSet::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let text = match std::fs::read_to_string(table) {
            Ok(t) => t,
            // A kernel without IPv6 has no tcp6.
            Err(e) if e.kind() == io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        // sl local_address rem_address st tx_queue:rx_queue tr:tm->when retrnsmt uid timeout inode …
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split_whitespace().collect();
            let (Some(local), Some(remote), Some(state), Some(inode)) = (
                f.get(1).and_then(|a| hex_port(a)),
                f.get(2).and_then(|a| hex_port(a)),
                f.get(3).and_then(|s| u8::from_str_radix(s, 16).ok()),
                f.get(9).and_then(|i| i.parse::<u64>().ok()),
            ) else {
                continue;
            };
            if wanted(local, remote, state) {
                inodes.insert(inode);
            }
        }
    }
    Ok(inodes)
}

/// This process's descriptors of the sockets `inodes` names.
fn fds_of(inodes: &HashSet<u64>) -> io::Result<Vec<RawFd>> {
    let mut fds = Vec::new();
    for entry in std::fs::read_dir("/proc/self/fd")? {
        let entry = entry?;
        // Descriptors closed since the listing have no link any more.
        let Ok(target) = std::fs::read_link(entry.path()) else {
            continue;
        };
        let inode = target.to_str().and_then(|t| {
            t.strip_prefix("socket:[")?
                .strip_suffix(']')?
                .parse::<u64>()
                .ok()
        });
        let fd = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<RawFd>().ok());
        if let (Some(inode), Some(fd)) = (inode, fd) {
            if inodes.contains(&inode) {
                fds.push(fd);
            }
        }
    }
    Ok(fds)
}

/// Polls a TCP connect until it succeeds or `READY_TIMEOUT` passes.
pub fn wait_ready(addr: SocketAddr) -> Result<(), BrokerError> {
    let deadline = Instant::now() + READY_TIMEOUT;
    while Instant::now() < deadline {
        if TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_ok() {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    Err(BrokerError::NotReady(addr))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_taken_port_is_a_clear_error() {
        let taken = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = taken.local_addr().unwrap();
        match start(addr) {
            Err(BrokerError::Bind { addr: a, .. }) => assert_eq!(a, addr),
            other => panic!("expected a bind error, got {other:?}"),
        }
    }

    /// A client that connected between the broker's listen and [`no_nagle`] (a benchmark waiting
    /// for the port got 44 ms round trips) has Nagle off too, and later ones inherit it.
    #[test]
    fn a_connection_accepted_before_nagle_was_turned_off_has_it_off_too() {
        use std::os::fd::AsRawFd;
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let _early = TcpStream::connect(addr).unwrap();
        let (early, _) = listener.accept().unwrap();
        assert!(!crate::sys::nodelay(early.as_raw_fd()).unwrap());
        no_nagle(addr).unwrap();
        assert!(
            crate::sys::nodelay(early.as_raw_fd()).unwrap(),
            "a connection accepted before keeps Nagle's algorithm on"
        );
        let _late = TcpStream::connect(addr).unwrap();
        let (late, _) = listener.accept().unwrap();
        assert!(crate::sys::nodelay(late.as_raw_fd()).unwrap());
        // The clients' own ends are theirs: left as they were made.
        assert!(!crate::sys::nodelay(_early.as_raw_fd()).unwrap());
    }

    /// What users saw before: every command round trip through the demo broker waited ~40 ms
    /// for a delayed ACK, because the broker's side of each client connection had Nagle on.
    #[test]
    fn the_broker_side_of_a_client_connection_has_nagle_off() {
        let addr = {
            let free = TcpListener::bind("127.0.0.1:0").unwrap();
            free.local_addr().unwrap()
        };
        start(addr).unwrap();
        let client = TcpStream::connect(addr).unwrap();
        let client_port = client.local_addr().unwrap().port();
        // The broker's end of this connection: local port `addr`'s, remote port the client's,
        // once rumqttd has accepted it (a descriptor of this process then).
        let deadline = Instant::now() + READY_TIMEOUT;
        let fd = loop {
            let fds =
                own_tcp_sockets(|local, remote, _| local == addr.port() && remote == client_port)
                    .unwrap();
            if let [fd] = fds[..] {
                break fd;
            }
            assert!(
                Instant::now() < deadline,
                "rumqttd never accepted the connection"
            );
            std::thread::sleep(Duration::from_millis(10));
        };
        assert!(
            crate::sys::nodelay(fd).unwrap(),
            "the embedded broker's socket to a client still has Nagle's algorithm on"
        );
        // The client's own end is not the broker's business: it stays as the client made it.
        let fd = own_tcp_sockets(|local, remote, _| local == client_port && remote == addr.port())
            .unwrap();
        assert_eq!(fd.len(), 1);
        assert!(!crate::sys::nodelay(fd[0]).unwrap());
    }
}
