//! `serial` against a pseudo-terminal whose far end runs the real SC core (`ihex_sc_core::Node`):
//! the same bytes a NUCLEO's ST-Link port would carry, answered by the same behaviour the firmware runs.

use std::{
    fs::File,
    io::{Read, Write},
    os::fd::OwnedFd,
    path::{Path, PathBuf},
    process::Command,
    sync::{
        atomic::{AtomicBool, Ordering},
        Arc, Mutex,
    },
    thread,
    time::{Duration, Instant},
};

use ihex_proto::test_util::id;
use ihex_proto::{
    uart::{UartError, UartRequest},
    BootRole, NodeId, ResetReason, Uid,
};
use ihex_provision::serial::{SerialError, SerialPort, Session};
use ihex_sc_core::{Config, Millis, Node, Output, UpdateConfig};
use rustix::{
    event::{poll, PollFd, PollFlags, Timespec},
    pty::{grantpt, openpt, ptsname, unlockpt, OpenptFlags},
    termios,
};

/// What the simulated board did, for the test to check.
#[derive(Default, Debug)]
struct Seen {
    /// Bytes the board received.
    rx: Vec<u8>,
    /// IDs it asked to persist.
    stored: Vec<NodeId>,
    /// Its ID as the core reports it.
    node_id: Option<NodeId>,
}

/// A pty whose master end is served by a thread running a real SC core.
struct Board {
    path: PathBuf,
    seen: Arc<Mutex<Seen>>,
    stop: Arc<AtomicBool>,
    thread: Option<thread::JoinHandle<()>>,
    // The slave stays open here so the master never sees a hang-up between the tool's runs.
    _slave: File,
}

impl Board {
    /// `fail_store`: the board's flash write fails (the core must refuse).
    fn start(node_id: Option<NodeId>, fail_store: bool) -> Board {
        let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).expect("openpt");
        grantpt(&master).unwrap();
        unlockpt(&master).unwrap();
        let path = PathBuf::from(ptsname(&master, Vec::new()).unwrap().into_string().unwrap());
        let slave = File::options().read(true).write(true).open(&path).unwrap();
        // Raw from the start, so nothing the board sends is echoed or line-buffered.
        let mut t = termios::tcgetattr(&slave).unwrap();
        t.make_raw();
        termios::tcsetattr(&slave, termios::OptionalActions::Now, &t).unwrap();

        let config = Config {
            role: BootRole::Static,
            ports: 6,
            uid: Uid([0x11; 12]),
            node_id,
            reset: ResetReason::PowerOn,
            firmware: Default::default(),
            update: UpdateConfig {
                board: ihex_image::Board::NUCLEO_F303RE,
                key: ihex_image::test_key::PUBLIC,
                layout: &ihex_image::board::F303RE,
                reverted: false,
            },
        };
        let seen = Arc::new(Mutex::new(Seen {
            node_id,
            ..Seen::default()
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let (seen2, stop2) = (seen.clone(), stop.clone());
        let thread = thread::spawn(move || serve(master, config, fail_store, seen2, stop2));
        Board {
            path,
            seen,
            stop,
            thread: Some(thread),
            _slave: slave,
        }
    }

    fn seen(&self) -> std::sync::MutexGuard<'_, Seen> {
        self.seen.lock().unwrap()
    }
}

impl Drop for Board {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The board's main loop: bytes in -> core -> UART replies out, timers ticked, store requests honoured.
fn serve(
    master: OwnedFd,
    config: Config,
    fail_store: bool,
    seen: Arc<Mutex<Seen>>,
    stop: Arc<AtomicBool>,
) {
    let origin = Instant::now();
    let now = || Millis(origin.elapsed().as_millis() as u64);
    let mut node = Node::new(config, now());
    let mut file = File::from(master);
    let mut buf = [0u8; 64];
    while !stop.load(Ordering::Relaxed) {
        drain(&mut node, &mut file, fail_store, &seen, now());
        let ready = {
            let mut fds = [PollFd::new(&file, PollFlags::IN)];
            let ts = Timespec {
                tv_sec: 0,
                tv_nsec: 10_000_000,
            };
            poll(&mut fds, Some(&ts)).unwrap_or(0) > 0 && fds[0].revents().contains(PollFlags::IN)
        };
        if ready {
            let n = match file.read(&mut buf) {
                Ok(n) => n,
                Err(_) => continue,
            };
            for &b in &buf[..n] {
                seen.lock().unwrap().rx.push(b);
                node.handle_uart_byte(b, now());
                drain(&mut node, &mut file, fail_store, &seen, now());
            }
        }
        node.tick(now());
    }
}

fn drain(node: &mut Node, file: &mut File, fail_store: bool, seen: &Mutex<Seen>, now: Millis) {
    while let Some(out) = node.poll_output() {
        match out {
            Output::Uart(bytes) => file.write_all(&bytes).unwrap(),
            Output::StoreId(id) => {
                seen.lock().unwrap().stored.push(id);
                if fail_store {
                    node.handle_store_failed(now);
                }
            }
            // Frames go nowhere (no bus here), and no update reaches a board over its UART.
            _ => {}
        }
    }
    seen.lock().unwrap().node_id = node.node_id();
}

fn session(path: &Path) -> Session {
    Session::new(SerialPort::open(path).unwrap(), Duration::from_secs(2))
}

#[test]
fn set_and_query_against_the_real_core() {
    let board = Board::start(None, false);
    let mut s = session(&board.path);
    assert_eq!(s.query_id().unwrap(), NodeId::UNCONFIGURED);
    assert_eq!(s.set_id(id(0x123)).unwrap(), id(0x123));
    assert_eq!(s.query_id().unwrap(), id(0x123));
    let seen = board.seen();
    assert_eq!(seen.stored, [id(0x123)]);
    assert_eq!(seen.node_id, Some(id(0x123)));
    // query, set, query (verify), query: exactly these bytes went over the wire.
    let mut want = Vec::new();
    for r in [
        UartRequest::Query,
        UartRequest::SetId(id(0x123)),
        UartRequest::Query,
        UartRequest::Query,
    ] {
        want.extend(r.encode());
    }
    assert_eq!(seen.rx, want);
}

#[test]
fn renumbering_a_configured_board() {
    let board = Board::start(Some(id(0x111)), false);
    let mut s = session(&board.path);
    assert_eq!(s.query_id().unwrap(), id(0x111));
    s.set_id(id(0xffd)).unwrap();
    assert_eq!(board.seen().node_id, Some(id(0xffd)));
}

#[test]
fn a_reserved_id_sent_anyway_is_refused_by_the_board() {
    // The tool never sends one (see the CLI test); the board must refuse it all the same.
    let board = Board::start(Some(id(0x5)), false);
    let mut s = session(&board.path);
    let err = s
        .exchange(UartRequest::SetId(NodeId::BROADCAST))
        .unwrap_err();
    assert!(matches!(err, SerialError::Refused(_)), "{err}");
    assert_eq!(s.query_id().unwrap(), id(0x5));
    assert!(board.seen().stored.is_empty());
}

#[test]
fn a_failed_flash_write_is_an_error() {
    let board = Board::start(None, true);
    let mut s = session(&board.path);
    let err = s.set_id(id(0x42)).unwrap_err();
    assert!(
        matches!(err, SerialError::Refused(UartError::StoreFailed)),
        "{err}"
    );
    assert!(err.to_string().contains("flash"), "{err}");
    assert_eq!(board.seen().stored, [id(0x42)]);
}

#[test]
fn no_board_means_a_timeout_not_a_hang() {
    // A pty nobody serves: the request goes out, no answer comes back.
    let master = openpt(OpenptFlags::RDWR | OpenptFlags::NOCTTY).unwrap();
    grantpt(&master).unwrap();
    unlockpt(&master).unwrap();
    let path = PathBuf::from(ptsname(&master, Vec::new()).unwrap().into_string().unwrap());
    let mut s = Session::new(SerialPort::open(&path).unwrap(), Duration::from_millis(200));
    assert!(matches!(s.query_id(), Err(SerialError::Timeout(_))));
}

fn tool(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn cli_sets_ids_keeps_a_registry_and_refuses_bad_ones() {
    let board = Board::start(None, false);
    let port = board.path.to_str().unwrap();
    let registry =
        std::env::temp_dir().join(format!("ihex-provision-cli-{}.csv", std::process::id()));
    let _ = std::fs::remove_file(&registry);
    let reg = registry.to_str().unwrap();

    let (ok, out, err) = tool(&["serial", "--port", port, "--query"]);
    assert!(ok, "{err}");
    assert!(out.contains("unconfigured"), "{out}");

    let (ok, out, err) = tool(&["serial", "--port", port, "--id", "2a", "--registry", reg]);
    assert!(ok, "{err}");
    assert!(out.contains("node ID 2a stored"), "{out}");
    assert_eq!(board.seen().node_id, Some(id(0x2a)));
    assert!(std::fs::read_to_string(&registry).unwrap().contains("02a,"));

    let before = board.seen().rx.len();
    for (bad, what) in [
        ("fff", "reserved"),
        ("000", "reserved"),
        ("ffe", "reserved"),
        ("1000", "1 to 3 hex digits"),
        ("xyz", "hex"),
    ] {
        let (ok, _, err) = tool(&["serial", "--port", port, "--id", bad]);
        assert!(!ok && err.contains(what), "{bad}: {err}");
    }
    let (ok, _, err) = tool(&["serial", "--port", port, "--id", "02A", "--registry", reg]);
    assert!(!ok && err.contains("already assigned"), "{err}");
    // Refused IDs never reach the board.
    assert_eq!(board.seen().rx.len(), before);
    assert_eq!(board.seen().node_id, Some(id(0x2a)));
    std::fs::remove_file(&registry).unwrap();
}
