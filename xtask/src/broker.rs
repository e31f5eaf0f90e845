//! A Mosquitto broker on the host's loopback for the SocketCAN stage (the VM reaches it at
//! 10.0.2.2), on a free port, stopped on drop.

use std::fs;
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use crate::cmd;

/// A running host broker.
pub struct HostBroker {
    child: Child,
    dir: PathBuf,
    /// Where it listens (127.0.0.1:port).
    pub addr: SocketAddr,
}

impl HostBroker {
    /// Starts mosquitto on a free loopback port; `None` (with a note) when it is not installed.
    pub fn start() -> Result<Option<HostBroker>> {
        let Some(bin) = cmd::find("mosquitto") else {
            println!("xtask: mosquitto not installed: no host broker (IHEX_TEST_MQTT unset)");
            return Ok(None);
        };
        let port = TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
            .local_addr()?
            .port();
        let addr = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
        let dir = std::env::temp_dir().join(format!("ihex-xtask-mosquitto-{}", std::process::id()));
        fs::create_dir_all(&dir)?;
        let conf = dir.join("mosquitto.conf");
        fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\n\
                 log_dest stderr\nlog_type error\nlog_type warning\n"
            ),
        )?;
        let child = Command::new(&bin)
            .arg("-c")
            .arg(&conf)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        let mut broker = HostBroker { child, dir, addr };
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(status) = broker.child.try_wait()? {
                bail!("host mosquitto exited ({status}) before listening on {addr}");
            }
            if TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_ok() {
                println!("xtask: host mosquitto listening on {addr}");
                return Ok(Some(broker));
            }
            if Instant::now() > deadline {
                bail!("host mosquitto did not listen on {addr} within 10 s");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for HostBroker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = fs::remove_dir_all(&self.dir);
    }
}
