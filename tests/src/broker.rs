//! A throwaway Mosquitto broker per test, on a free loopback port, killed when dropped.
//!
//! [`Mosquitto::start`] spawns the system's `mosquitto` with a generated config that needs no other
//! files, so it runs natively and inside the test microVM alike (the harness copies the binary and
//! its libraries into the VM). [`Mosquitto::start_with`] adds what a [`Setup`] says: TLS,
//! passwords, access control, bridges, and the files they need. It is the one broker launcher of
//! the tests (the benchmark's live harness starts its own, tuned for measurement: docs/benchmarks.md).

use std::fs;
use std::io;
use std::net::{Ipv4Addr, SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// Environment variable naming the mosquitto binary to use (default: `mosquitto` on `PATH`, then
/// `/usr/sbin/mosquitto`).
pub const BIN_ENV: &str = "IHEX_MOSQUITTO";

/// How long a started broker may take to accept connections (before [`crate::time::scaled`]).
const READY_TIMEOUT: Duration = Duration::from_secs(10);

static INSTANCE: AtomicUsize = AtomicUsize::new(0);

/// Why a broker could not be started.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No mosquitto binary was found.
    #[error(
        "mosquitto not found (looked at ${BIN_ENV}, PATH, /usr/sbin, /usr/local/sbin): \
         install it (`apt-get install mosquitto`) or run `cargo xtask setup`"
    )]
    NotFound,
    /// A file or process operation failed.
    #[error("{action}: {source}")]
    Io {
        /// What was being done.
        action: String,
        /// The underlying error.
        source: io::Error,
    },
    /// The broker exited before it accepted connections.
    #[error("mosquitto exited ({status}) before listening on {addr}; its log:\n{log}")]
    Exited {
        /// Where it should have listened.
        addr: SocketAddr,
        /// Its exit status.
        status: ExitStatus,
        /// What it wrote to stderr.
        log: String,
    },
    /// The broker did not accept connections in time.
    #[error("mosquitto did not accept connections on {addr} within {after:?}; its log:\n{log}")]
    NotReady {
        /// Where it should have listened.
        addr: SocketAddr,
        /// How long we waited.
        after: Duration,
        /// What it wrote to stderr.
        log: String,
    },
}

fn io_err(action: impl Into<String>) -> impl FnOnce(io::Error) -> Error {
    let action = action.into();
    move |source| Error::Io { action, source }
}

/// The mosquitto binary this process would run.
pub fn binary() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(BIN_ENV) {
        return Some(PathBuf::from(p));
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin".into(), "/usr/local/sbin".into()])
        .map(|dir| dir.join("mosquitto"))
        .find(|p| p.is_file())
}

/// A Mosquitto password file (`user:hash` lines) for these users, hashed by `mosquitto_passwd -U`
/// (found beside the mosquitto binary or on `PATH`), for [`Setup::files`] and `password_file`.
pub fn password_file(users: &[(&str, &str)]) -> Result<Vec<u8>, Error> {
    let tool = binary()
        .and_then(|b| {
            // Debian: /usr/sbin/mosquitto and /usr/bin/mosquitto_passwd.
            let near = b.parent()?.join("mosquitto_passwd");
            let usr_bin = b.parent()?.parent()?.join("bin/mosquitto_passwd");
            [near, usr_bin].into_iter().find(|p| p.is_file())
        })
        .or_else(|| {
            let path = std::env::var_os("PATH").unwrap_or_default();
            std::env::split_paths(&path)
                .map(|d| d.join("mosquitto_passwd"))
                .find(|p| p.is_file())
        })
        .ok_or(Error::NotFound)?;
    let path = std::env::temp_dir().join(format!(
        "ihex-passwd-{}-{}",
        std::process::id(),
        INSTANCE.fetch_add(1, Ordering::Relaxed)
    ));
    let plain: String = users.iter().map(|(u, p)| format!("{u}:{p}\n")).collect();
    fs::write(&path, plain).map_err(io_err(format!("writing {}", path.display())))?;
    let status = Command::new(&tool)
        .arg("-U")
        .arg(&path)
        .stdin(Stdio::null())
        .status()
        .map_err(io_err(format!("running {}", tool.display())));
    let hashed = fs::read(&path).map_err(io_err(format!("reading {}", path.display())));
    let _ = fs::remove_file(&path);
    match status? {
        s if s.success() => hashed,
        s => Err(Error::Io {
            action: format!("{} -U", tool.display()),
            source: io::Error::other(format!("exited with {s}")),
        }),
    }
}

/// `conf` (a Mosquitto configuration file's text) with the value of every line whose first word
/// is one of `values`' keys replaced. Fails when a key is on no line, so a test running a
/// documented file notices when the file changes under it.
pub fn rewrite(conf: &str, values: &[(&str, &str)]) -> Result<String, String> {
    let mut used = vec![false; values.len()];
    let mut out = String::new();
    for line in conf.lines() {
        let key = line.split_whitespace().next().unwrap_or_default();
        match values.iter().position(|(k, _)| *k == key) {
            Some(i) if !line.trim_start().starts_with('#') => {
                used[i] = true;
                out.push_str(&format!("{key} {}\n", values[i].1));
            }
            _ => {
                out.push_str(line);
                out.push('\n');
            }
        }
    }
    let missing: Vec<&str> = values
        .iter()
        .zip(&used)
        .filter(|(_, u)| !**u)
        .map(|((k, _), _)| *k)
        .collect();
    if missing.is_empty() {
        Ok(out)
    } else {
        Err(format!(
            "no line for {} in the configuration",
            missing.join(", ")
        ))
    }
}

/// A running mosquitto process listening on `127.0.0.1:<port>`; killed on drop.
#[derive(Debug)]
pub struct Mosquitto {
    bin: PathBuf,
    dir: PathBuf,
    addr: SocketAddr,
    child: Option<Child>,
}

/// What a broker needs beyond the plain anonymous listener of [`Mosquitto::start`]: TLS, passwords,
/// access control, bridges. Every text may name the broker's own folder as `{dir}` (where
/// [`Setup::files`] are written) and its port as `{port}`.
#[derive(Clone, Debug)]
pub struct Setup {
    /// Whether clients without a user name are accepted (`allow_anonymous`).
    pub anonymous: bool,
    /// Global lines (`password_file {dir}/passwd`, `acl_file {dir}/acl`, ...).
    pub global: String,
    /// Lines of the listener on `127.0.0.1:{port}` (`cafile`, `certfile`, `keyfile`, ...).
    pub listener: String,
    /// Bridge sections (`connection NAME` ...); they come last in the file, as Mosquitto wants.
    pub bridges: String,
    /// Files written into the broker's folder before it starts: (name, contents).
    pub files: Vec<(String, Vec<u8>)>,
    /// `log_type` lines (default `error`, `warning`); add `notice` or `all` to see more in
    /// [`Mosquitto::log`].
    pub log_types: Vec<String>,
    /// A complete configuration (a repository file run through [`rewrite`]) instead of the
    /// generated listener, `anonymous`, `global`, `listener` and `bridges`; the harness only adds
    /// what it needs to run the broker here (`user root`, no persistence, logging to stderr).
    pub conf: Option<String>,
}

impl Default for Setup {
    fn default() -> Setup {
        Setup {
            anonymous: true,
            global: String::new(),
            listener: String::new(),
            bridges: String::new(),
            files: Vec::new(),
            log_types: vec!["error".into(), "warning".into()],
            conf: None,
        }
    }
}

impl Mosquitto {
    /// Starts a broker on a free loopback port and waits until it accepts TCP connections.
    pub fn start() -> Result<Mosquitto, Error> {
        Mosquitto::start_with(&Setup::default())
    }

    /// Starts a broker configured by `setup` on a free loopback port and waits until it accepts
    /// TCP connections (for a TLS listener: until the port accepts; the handshake is the test's).
    pub fn start_with(setup: &Setup) -> Result<Mosquitto, Error> {
        let bin = binary().ok_or(Error::NotFound)?;
        let port = free_port()?;
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let dir = std::env::temp_dir().join(format!(
            "ihex-mosquitto-{}-{}",
            std::process::id(),
            INSTANCE.fetch_add(1, Ordering::Relaxed)
        ));
        fs::create_dir_all(&dir).map_err(io_err(format!("creating {}", dir.display())))?;
        for (name, contents) in &setup.files {
            let path = dir.join(name);
            fs::write(&path, contents).map_err(io_err(format!("writing {}", path.display())))?;
        }
        let fill = |text: &str| {
            text.replace("{dir}", &dir.to_string_lossy())
                .replace("{port}", &port.to_string())
        };
        // `user root` keeps a root-run broker from switching to a `mosquitto` account, which the
        // test VM does not have; for non-root runs mosquitto ignores it.
        let mut conf = String::from("persistence false\nuser root\nlog_dest stderr\n");
        for t in &setup.log_types {
            conf.push_str(&format!("log_type {t}\n"));
        }
        match &setup.conf {
            Some(text) => conf.push_str(&fill(text)),
            None => {
                conf.push_str(&format!(
                    "per_listener_settings false\nallow_anonymous {}\n",
                    setup.anonymous
                ));
                conf.push_str(&fill(&setup.global));
                conf.push_str(&format!("\nlistener {port} 127.0.0.1\n"));
                conf.push_str(&fill(&setup.listener));
                conf.push('\n');
                conf.push_str(&fill(&setup.bridges));
            }
        }
        conf.push('\n');
        let conf_path = dir.join("mosquitto.conf");
        fs::write(&conf_path, conf).map_err(io_err(format!("writing {}", conf_path.display())))?;
        let mut broker = Mosquitto {
            bin,
            dir,
            addr,
            child: None,
        };
        broker.spawn()?;
        Ok(broker)
    }

    /// Where clients connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The broker's folder ([`Setup::files`] are there).
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// What the broker has logged (stderr) since it was last started or restarted.
    pub fn log(&self) -> String {
        read_log(&self.log_path())
    }

    /// Kills the broker with SIGKILL (`kill -9`: no clean-up, clients see their connection drop).
    /// Idempotent.
    pub fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Stops the broker and starts a fresh one on the same port (sessions and retained messages
    /// are gone: persistence is off), waiting until it accepts connections again.
    pub fn restart(&mut self) -> Result<(), Error> {
        self.stop();
        self.spawn()
    }

    /// True while the broker process is alive.
    pub fn is_running(&mut self) -> bool {
        matches!(self.child.as_mut().map(|c| c.try_wait()), Some(Ok(None)))
    }

    fn log_path(&self) -> PathBuf {
        self.dir.join("mosquitto.log")
    }

    fn spawn(&mut self) -> Result<(), Error> {
        let log_path = self.log_path();
        let log = fs::File::create(&log_path)
            .map_err(io_err(format!("creating {}", log_path.display())))?;
        let child = Command::new(&self.bin)
            .arg("-c")
            .arg(self.dir.join("mosquitto.conf"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .map_err(io_err(format!("starting {}", self.bin.display())))?;
        self.child = Some(child);
        self.wait_ready()
    }

    fn wait_ready(&mut self) -> Result<(), Error> {
        let after = crate::time::scaled(READY_TIMEOUT);
        let deadline = Instant::now() + after;
        loop {
            let child = self.child.as_mut().expect("spawn sets the child");
            if let Ok(Some(status)) = child.try_wait() {
                self.child = None;
                return Err(Error::Exited {
                    addr: self.addr,
                    status,
                    log: read_log(&self.log_path()),
                });
            }
            if TcpStream::connect_timeout(&self.addr, Duration::from_millis(200)).is_ok() {
                return Ok(());
            }
            if Instant::now() >= deadline {
                self.stop();
                return Err(Error::NotReady {
                    addr: self.addr,
                    after,
                    log: read_log(&self.log_path()),
                });
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        self.stop();
        let _ = fs::remove_dir_all(&self.dir);
    }
}

fn read_log(path: &Path) -> String {
    fs::read_to_string(path).unwrap_or_else(|e| format!("(no log: {e})"))
}

fn free_port() -> Result<u16, Error> {
    crate::net::try_free_port().map_err(io_err("binding a free loopback port"))
}
