//! A throwaway QEMU microVM booted from a distribution kernel, for tests that need kernel features
//! the host lacks (SocketCAN).
//!
//! The initrd is two concatenated `newc` archives: a cached *base* (static busybox, the kernel
//! modules and their dependencies, host programs with their shared libraries, `/init`) and a
//! per-run *payload* (the programs to run at their host paths, a few repository files, `run.sh`).
//! `/init` loads the modules, runs the machine's boot script, runs the payload one program after the
//! other with output on the serial console, prints `@@ihex-vm exit <n> <code>` after each and powers
//! off. Nothing here is specific to x86_64: [`Vm`]'s fields name the QEMU binary, machine, kernel,
//! console and module tree, so an aarch64 machine is another constructor.

use std::collections::hash_map::DefaultHasher;
use std::fs;
use std::hash::{Hash, Hasher};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime};

use anyhow::{anyhow, bail, Context, Result};

use crate::cmd;
use crate::cpio::Cpio;

/// Marker prefix the VM prints on its console for the host to parse.
const MARK: &str = "@@ihex-vm";

/// Where the modules sit inside the VM (flat, loaded in list order).
const VM_MODULE_DIR: &str = "lib/modules/ihex";

/// One microVM configuration.
#[derive(Debug, Clone)]
pub struct Vm {
    /// Architecture name, used for the cache folder (`x86_64`, `aarch64`).
    pub arch: String,
    /// The QEMU system emulator.
    pub qemu: PathBuf,
    /// Machine, accelerator and CPU arguments (`-accel tcg`, `-M virt -cpu cortex-a72`...).
    pub machine_args: Vec<String>,
    /// Kernel image.
    pub kernel: PathBuf,
    /// The kernel's module tree (`.../lib/modules/<version>`).
    pub modules_dir: PathBuf,
    /// Serial console device of the guest (`ttyS0`, `ttyAMA0`).
    pub console: String,
    /// Kernel command-line arguments beyond the console and the quiet boot.
    pub kernel_args: Vec<String>,
    /// A statically linked busybox for the guest's architecture.
    pub busybox: PathBuf,
    /// Modules to load, by name; dependencies are added first.
    pub modules: Vec<String>,
    /// Network card for user-mode networking (guest 10.0.2.15, host 10.0.2.2); its driver's
    /// modules are loaded with [`Vm::modules`].
    pub net_device: Option<NetDevice>,
    /// Shell lines `/init` runs after loading the modules (create interfaces, export variables).
    pub boot_script: String,
    /// Host programs copied to the same paths with the shared libraries `ldd` lists.
    pub host_programs: Vec<PathBuf>,
    /// Guest memory; raised automatically when the initrd is large.
    pub memory_mb: u64,
    /// Virtual CPUs.
    pub smp: u32,
    /// A host CPU for the thread of vCPU 0 alone ([`pin_vcpu0`]); the other threads keep the
    /// CPUs QEMU was started with.
    pub pin_vcpu0: Option<usize>,
    /// A VM still running after this long is killed.
    pub timeout: Duration,
    /// Where base archives are cached.
    pub cache_dir: PathBuf,
    /// Strip debug info from payload programs (with `strip`, when installed) to keep the initrd
    /// small; panics still name file and line.
    pub strip: bool,
}

/// The guest's network card (the guest names it `eth0` either way).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum NetDevice {
    /// An emulated Intel e1000: every packet costs register accesses and interrupts, which TCG
    /// emulates slowly on the vCPU.
    E1000,
    /// A paravirtual virtio-net card: packets pass through shared rings, with few exits.
    Virtio,
}

impl NetDevice {
    fn qemu_model(self) -> &'static str {
        match self {
            NetDevice::E1000 => "e1000",
            NetDevice::Virtio => "virtio-net-pci",
        }
    }

    fn modules(self) -> &'static [&'static str] {
        match self {
            NetDevice::E1000 => &["e1000"],
            NetDevice::Virtio => &["virtio_pci", "virtio_net"],
        }
    }
}

/// A program to run in the VM.
#[derive(Debug, Clone)]
pub struct Program {
    /// Name in reports.
    pub name: String,
    /// Host path; the program is placed at the same path in the VM.
    pub path: PathBuf,
    /// Arguments.
    pub args: Vec<String>,
}

/// What one boot runs.
#[derive(Debug, Clone, Default)]
pub struct Payload {
    /// Run in order; a failing program does not stop the next.
    pub programs: Vec<Program>,
    /// Exported before the programs run.
    pub env: Vec<(String, String)>,
    /// Working directory of the programs (must be among `files`' folders to exist).
    pub cwd: Option<PathBuf>,
    /// Host files copied to the same paths (test fixtures, configs).
    pub files: Vec<PathBuf>,
}

/// Exit status of one program run in the VM.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Outcome {
    /// [`Program::name`].
    pub name: String,
    /// Its exit code as the guest shell saw it (128 + signal for a signal).
    pub code: i32,
}

/// The newest `/boot/vmlinuz-<v>` whose `/lib/modules/<v>` exists, or `IHEX_VM_KERNEL` and
/// `IHEX_VM_MODULES` when set.
pub fn host_kernel() -> Result<(PathBuf, PathBuf)> {
    if let (Some(k), Some(m)) = (
        std::env::var_os("IHEX_VM_KERNEL"),
        std::env::var_os("IHEX_VM_MODULES"),
    ) {
        return Ok((k.into(), m.into()));
    }
    let mut found = Vec::new();
    for entry in fs::read_dir("/boot").context("reading /boot")? {
        let name = entry?.file_name().to_string_lossy().into_owned();
        if let Some(version) = name.strip_prefix("vmlinuz-") {
            let modules = Path::new("/lib/modules").join(version);
            if modules.join("kernel/drivers/net/can/vcan.ko").exists()
                || modules.join("kernel/drivers/net/can").is_dir()
            {
                found.push((
                    version.to_string(),
                    PathBuf::from("/boot").join(&name),
                    modules,
                ));
            }
        }
    }
    // Version-aware enough: Debian's names differ in the ABI number, compare numerically-ish by length.
    found.sort_by(|a, b| (a.0.len(), &a.0).cmp(&(b.0.len(), &b.0)));
    found.pop().map(|(_, k, m)| (k, m)).ok_or_else(|| {
        anyhow!(
            "no kernel with CAN modules: need /boot/vmlinuz-<v> and /lib/modules/<v>/kernel/drivers/net/can \
             (Debian: apt-get install linux-image-amd64; or set IHEX_VM_KERNEL and IHEX_VM_MODULES)"
        )
    })
}

/// A statically linked busybox: `IHEX_VM_BUSYBOX`, or Debian's `busybox-static` at `/bin/busybox`.
pub fn static_busybox() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("IHEX_VM_BUSYBOX") {
        return Some(p.into());
    }
    let p = cmd::find("busybox")?;
    // A dynamically linked busybox would need its libraries in the VM; ldd says which it is.
    let ldd = Command::new("ldd")
        .arg(&p)
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .ok();
    let is_static = ldd
        .is_none_or(|o| !o.status.success() || !String::from_utf8_lossy(&o.stdout).contains("=>"));
    is_static.then_some(p)
}

/// Moves the thread of vCPU 0 of the QEMU process `pid` (started with `debug-threads=on`) to
/// host CPU `cpu` alone. QEMU's multi-threaded TCG runs each vCPU on a thread of its own, created
/// before the guest starts.
fn pin_vcpu0(pid: u32, cpu: usize) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        for task in fs::read_dir(format!("/proc/{pid}/task"))?.flatten() {
            let comm = fs::read_to_string(task.path().join("comm")).unwrap_or_default();
            if comm.trim_end() == "CPU 0/TCG" {
                let tid = task.file_name().to_string_lossy().into_owned();
                cmd::run(
                    Command::new("taskset")
                        .args(["-p", "-c", &cpu.to_string(), &tid])
                        .stdout(Stdio::null()),
                )
                .context("pinning vCPU 0 (taskset, util-linux)")?;
                println!("vm: vCPU 0 (thread {tid}) alone on host CPU {cpu}");
                return Ok(());
            }
        }
        if Instant::now() > deadline {
            bail!(
                "QEMU (pid {pid}) has no thread \"CPU 0/TCG\" after 10 s: single-threaded TCG? \
                 (`cargo xtask bench --no-pin` runs without pinning)"
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

impl Vm {
    /// An x86_64 TCG microVM from the host's kernel, busybox and QEMU (KVM does not work on the
    /// project's machines, see docs/testing.md, so TCG always).
    pub fn x86_64(cache_root: &Path) -> Result<Vm> {
        let (kernel, modules_dir) = host_kernel()?;
        let qemu = cmd::find("qemu-system-x86_64").ok_or_else(|| {
            anyhow!("qemu-system-x86_64 not found (Debian: apt-get install qemu-system-x86, or `cargo xtask setup`)")
        })?;
        let busybox = static_busybox().ok_or_else(|| {
            anyhow!("no statically linked busybox (Debian: apt-get install busybox-static, or set IHEX_VM_BUSYBOX)")
        })?;
        Ok(Vm {
            arch: "x86_64".into(),
            qemu,
            machine_args: ["-accel", "tcg", "-cpu", "max"].map(String::from).to_vec(),
            kernel,
            modules_dir,
            console: "ttyS0".into(),
            // With two vCPUs the kernel finds TCG's TSCs unsynchronized (they are one host clock,
            // read at slightly different moments) and falls back to the emulated HPET: every clock
            // read of every process becomes a system call and a device access, where the target
            // (a Raspberry Pi's arch timer) and any desktop read the clock in user space (vDSO).
            kernel_args: vec!["tsc=reliable".into()],
            busybox,
            modules: Vec::new(),
            net_device: Some(NetDevice::E1000),
            boot_script: String::new(),
            host_programs: Vec::new(),
            memory_mb: 1024,
            smp: 2,
            pin_vcpu0: None,
            timeout: Duration::from_secs(15 * 60),
            cache_dir: cache_root.join("x86_64"),
            strip: std::env::var_os("IHEX_VM_KEEP_DEBUG").is_none(),
        })
    }

    fn kernel_version(&self) -> String {
        self.modules_dir
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned()
    }

    /// Module files to load, dependencies first.
    fn module_files(&self) -> Result<Vec<PathBuf>> {
        let kver = self.kernel_version();
        // modules_dir is <base>/lib/modules/<kver>; modinfo wants <base>.
        let base = self
            .modules_dir
            .ancestors()
            .nth(3)
            .unwrap_or(Path::new("/"))
            .to_path_buf();
        let modinfo = |field: &str, name: &str| -> Result<String> {
            let out = cmd::output(
                Command::new("modinfo")
                    .arg("-b")
                    .arg(&base)
                    .args(["-k", &kver, "-F", field, name]),
            )
            .ok_or_else(|| {
                anyhow!(
                    "`modinfo -b {} -k {kver} {name}` failed: module missing?",
                    base.display()
                )
            })?;
            Ok(out.trim().to_string())
        };
        let mut order: Vec<(String, PathBuf)> = Vec::new();
        fn visit(
            name: &str,
            order: &mut Vec<(String, PathBuf)>,
            stack: &mut Vec<String>,
            modinfo: &dyn Fn(&str, &str) -> Result<String>,
        ) -> Result<()> {
            let name = name.replace('_', "-");
            if order.iter().any(|(n, _)| n.replace('_', "-") == name) || stack.contains(&name) {
                return Ok(());
            }
            stack.push(name.clone());
            let deps = modinfo("depends", &name)?;
            for dep in deps.split(',').map(str::trim).filter(|d| !d.is_empty()) {
                visit(dep, order, stack, modinfo)?;
            }
            let file = modinfo("filename", &name)?;
            if file.is_empty() || file == "(builtin)" {
                // Built into the kernel: nothing to load.
            } else {
                order.push((name.clone(), PathBuf::from(file)));
            }
            stack.pop();
            Ok(())
        }
        let net = self.net_device.map_or(&[][..], NetDevice::modules);
        for m in self
            .modules
            .iter()
            .map(String::as_str)
            .chain(net.iter().copied())
        {
            visit(m, &mut order, &mut Vec::new(), &modinfo)?;
        }
        Ok(order.into_iter().map(|(_, p)| p).collect())
    }

    fn init_script(&self) -> String {
        format!(
            r#"#!/bin/sh
/bin/busybox --install -s /bin
export PATH=/bin:/sbin:/usr/bin:/usr/sbin HOME=/root
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev 2>/dev/null
mkdir -p /dev/pts /dev/shm /tmp /run
# No tmpfs over /tmp: the rootfs is already in RAM and payload programs may live under /tmp.
chmod 1777 /tmp
mount -t tmpfs tmpfs /dev/shm
ip link set lo up
while read -r m; do
  insmod "/{VM_MODULE_DIR}/$m" || echo "{MARK} warning: insmod $m failed"
done < /etc/ihex/modules
if [ -e /sys/class/net/eth0 ]; then
  ip link set eth0 up
  ip addr add 10.0.2.15/24 dev eth0
  ip route add default via 10.0.2.2
fi
{boot}
echo "{MARK} ready"
if grep -q ihex.shell /proc/cmdline; then
  setsid cttyhack sh
elif [ -x /payload/run.sh ]; then
  /payload/run.sh
else
  echo "{MARK} error: /payload/run.sh missing (initramfs unpacking failed? more memory: --memory MIB)"
fi
echo "{MARK} done"
sync
poweroff -f
"#,
            boot = self.boot_script
        )
    }

    /// The cached base archive, built when missing.
    pub fn base(&self) -> Result<PathBuf> {
        let modules = self.module_files()?;
        let mut programs = Vec::new();
        for p in &self.host_programs {
            programs.push(p.clone());
            programs.extend(shared_libraries(p)?);
        }
        let init = self.init_script();
        let mut h = DefaultHasher::new();
        init.hash(&mut h);
        for f in modules.iter().chain(&programs).chain([&self.busybox]) {
            f.hash(&mut h);
            let meta = fs::metadata(f).with_context(|| format!("{}", f.display()))?;
            (
                meta.len(),
                meta.modified().unwrap_or(SystemTime::UNIX_EPOCH),
            )
                .hash(&mut h);
        }
        let path = self.cache_dir.join(format!(
            "base-{}-{:016x}.cpio",
            self.kernel_version(),
            h.finish()
        ));
        if path.exists() {
            return Ok(path);
        }
        fs::create_dir_all(&self.cache_dir)?;
        let tmp = path.with_extension(format!("tmp{}", std::process::id()));
        let mut c = Cpio::create(&tmp)?;
        for d in [
            "bin", "sbin", "usr/bin", "usr/sbin", "proc", "sys", "dev", "tmp", "run", "root",
            "etc/ihex",
        ] {
            c.dir(d)?;
        }
        c.char_dev("dev/console", 5, 1)?;
        c.char_dev("dev/null", 1, 3)?;
        c.file("bin/busybox", &self.busybox)?;
        c.symlink("bin/sh", "busybox")?;
        let mut list = String::new();
        for m in &modules {
            let name = module_name(m);
            c.bytes(&format!("{VM_MODULE_DIR}/{name}"), 0o644, &read_module(m)?)?;
            list.push_str(&name);
            list.push('\n');
        }
        c.bytes("etc/ihex/modules", 0o644, list.as_bytes())?;
        for p in &programs {
            c.file(&p.to_string_lossy(), p)?;
        }
        c.bytes("etc/passwd", 0o644, b"root:x:0:0:root:/root:/bin/sh\n")?;
        c.bytes("etc/group", 0o644, b"root:x:0:\n")?;
        c.bytes("etc/hosts", 0o644, b"127.0.0.1 localhost\n::1 localhost\n")?;
        c.bytes("init", 0o755, init.as_bytes())?;
        c.finish()?;
        fs::rename(&tmp, &path)?;
        // Older bases (another kernel, changed modules or init) are dead weight now.
        for entry in fs::read_dir(&self.cache_dir)?.flatten() {
            let p = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if p != path && name.starts_with("base-") && name.ends_with(".cpio") {
                let _ = fs::remove_file(p);
            }
        }
        println!("vm: built {} base initramfs {}", self.arch, path.display());
        Ok(path)
    }

    /// Boots once, runs every program of `payload` in turn (output streamed to stdout) and returns
    /// their exit codes. Fails when the VM hangs past [`Vm::timeout`] or stops before the end.
    pub fn run(&self, payload: &Payload) -> Result<Vec<Outcome>> {
        let initrd = self.initrd(Some(payload))?;
        let names: Vec<&str> = payload.programs.iter().map(|p| p.name.as_str()).collect();
        let result = self.boot(&initrd, &names, false);
        let _ = fs::remove_file(&initrd);
        let codes = result?;
        Ok(payload
            .programs
            .iter()
            .zip(codes)
            .map(|(p, code)| Outcome {
                name: p.name.clone(),
                code,
            })
            .collect())
    }

    /// Boots to an interactive shell on this terminal (`poweroff -f` or Ctrl-D leaves).
    pub fn shell(&self) -> Result<()> {
        let initrd = self.initrd(None)?;
        let result = self.boot(&initrd, &[], true);
        let _ = fs::remove_file(&initrd);
        result.map(|_| ())
    }

    fn initrd(&self, payload: Option<&Payload>) -> Result<PathBuf> {
        let path = self
            .cache_dir
            .join(format!("run-{}.cpio", std::process::id()));
        // A concurrent run with another configuration may prune our base between its check and
        // the copy: build it again once.
        let base = self.base()?;
        if fs::copy(&base, &path).is_err() {
            let base = self.base()?;
            fs::copy(&base, &path).with_context(|| format!("copying {}", base.display()))?;
        }
        if let Some(payload) = payload {
            let file = fs::OpenOptions::new().append(true).open(&path)?;
            let mut c = Cpio::new(std::io::BufWriter::with_capacity(1 << 20, file));
            c.assume_dirs([
                "bin", "sbin", "usr", "usr/bin", "usr/sbin", "tmp", "run", "root", "etc",
                "etc/ihex",
            ]);
            for f in &payload.files {
                c.file(&f.to_string_lossy(), f)?;
            }
            let strip = if self.strip { cmd::find("strip") } else { None };
            let stripped = self
                .cache_dir
                .join(format!("stripped-{}", std::process::id()));
            for (i, p) in payload.programs.iter().enumerate() {
                let src = match &strip {
                    Some(strip) => {
                        fs::create_dir_all(&stripped)?;
                        let out = stripped.join(i.to_string());
                        let ok = Command::new(strip)
                            .arg("--strip-debug")
                            .arg("-o")
                            .arg(&out)
                            .arg(&p.path)
                            .status()
                            .is_ok_and(|s| s.success());
                        if ok {
                            out
                        } else {
                            p.path.clone()
                        }
                    }
                    None => p.path.clone(),
                };
                c.file(&p.path.to_string_lossy(), &src)?;
            }
            let _ = fs::remove_dir_all(&stripped);
            c.bytes("payload/run.sh", 0o755, run_script(payload).as_bytes())?;
            c.finish()?;
        }
        Ok(path)
    }

    fn boot(&self, initrd: &Path, names: &[&str], interactive: bool) -> Result<Vec<i32>> {
        let expected = names.len();
        let size_mb = fs::metadata(initrd)?.len() >> 20;
        // The initrd is held in memory while the kernel unpacks it into a tmpfs that may use only
        // half of the RAM.
        let memory = self.memory_mb.max(size_mb * 3 + 512);
        let mut q = Command::new(&self.qemu);
        q.args(&self.machine_args)
            .args(["-m", &memory.to_string(), "-smp", &self.smp.to_string()])
            .arg("-kernel")
            .arg(&self.kernel)
            .arg("-initrd")
            .arg(initrd)
            .args([
                "-append",
                &format!(
                    "console={} quiet loglevel=3 panic=-1{}{}",
                    self.console,
                    self.kernel_args
                        .iter()
                        .map(|a| format!(" {a}"))
                        .collect::<String>(),
                    if interactive { " ihex.shell" } else { "" }
                ),
            ])
            .args(["-no-reboot", "-display", "none", "-monitor", "none"]);
        if self.pin_vcpu0.is_some() {
            // Names QEMU's threads ("CPU 0/TCG"), so that vCPU 0's can be found.
            q.args(["-name", "ihex-vm,debug-threads=on"]);
        }
        if let Some(dev) = &self.net_device {
            q.args([
                "-netdev",
                "user,id=n0",
                "-device",
                &format!("{},netdev=n0", dev.qemu_model()),
            ]);
        }
        if interactive {
            q.args(["-serial", "stdio"]);
            return cmd::run(&mut q).map(|()| Vec::new());
        }
        q.args(["-serial", "stdio"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped());
        println!("$ {}", cmd::display(&q));
        let start = Instant::now();
        let mut child = q
            .spawn()
            .with_context(|| format!("starting {}", self.qemu.display()))?;
        if let Some(cpu) = self.pin_vcpu0 {
            if let Err(e) = pin_vcpu0(child.id(), cpu) {
                let _ = child.kill();
                let _ = child.wait();
                return Err(e);
            }
        }
        let stdout = child.stdout.take().expect("piped");
        let (tx, rx) = mpsc::sync_channel(16);
        let reader = std::thread::spawn(move || console(stdout, std::io::stdout(), tx));
        let deadline = start + self.timeout;
        let mut codes: Vec<Option<i32>> = vec![None; expected];
        let mut booted = false;
        let mut running: Option<usize> = None;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(Event::Ready) => {
                    booted = true;
                    println!("vm: booted in {:.1} s", start.elapsed().as_secs_f64());
                }
                Ok(Event::Start(i)) => running = Some(i),
                Ok(Event::Exit(i, code)) => {
                    running = None;
                    if let Some(slot) = codes.get_mut(i) {
                        *slot = Some(code);
                    }
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    // Unblock the reader should it wait on a full channel.
                    drop(rx);
                    let _ = reader.join();
                    let done = codes.iter().filter(|c| c.is_some()).count();
                    let during = match running.and_then(|i| names.get(i)) {
                        Some(name) => format!("while running {name}"),
                        None if booted => "between programs".to_string(),
                        None => "before /init was ready".to_string(),
                    };
                    bail!(
                        "VM timed out after {} s {during} and was killed ({done} of {expected} programs \
                         finished); raise the limit with --vm-timeout SECS or IHEX_VM_TIMEOUT",
                        self.timeout.as_secs()
                    );
                }
            }
        }
        let status = child.wait()?;
        let _ = reader.join();
        println!(
            "vm: {} after {:.1} s",
            status,
            start.elapsed().as_secs_f64()
        );
        if !booted {
            bail!("VM stopped before /init was ready ({status}); see the console output above");
        }
        codes
            .into_iter()
            .enumerate()
            .map(|(i, c)| {
                c.ok_or_else(|| {
                    anyhow!(
                        "VM stopped before {} finished (kernel panic? initramfs too big for \
                         the memory? try --memory MIB); see the console output above",
                        names.get(i).unwrap_or(&"a program")
                    )
                })
            })
            .collect()
    }
}

enum Event {
    Ready,
    Start(usize),
    Exit(usize, i32),
}

/// Copies the console to `out` as it comes and reports the markers.
fn console(mut from: impl Read, mut out: impl Write, tx: mpsc::SyncSender<Event>) {
    let mut line = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        let n = match from.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        let chunk: Vec<u8> = buf[..n].iter().copied().filter(|&b| b != b'\r').collect();
        let _ = out.write_all(&chunk);
        let _ = out.flush();
        for b in chunk {
            if b != b'\n' {
                line.push(b);
                continue;
            }
            let text = String::from_utf8_lossy(&line);
            if let Some(rest) = text.trim().strip_prefix(MARK) {
                let words: Vec<&str> = rest.split_whitespace().collect();
                let event = match words.as_slice() {
                    ["ready"] => Some(Event::Ready),
                    ["start", i, ..] => i.parse().ok().map(Event::Start),
                    ["exit", i, code] => i
                        .parse()
                        .ok()
                        .zip(code.parse().ok())
                        .map(|(i, c)| Event::Exit(i, c)),
                    _ => None,
                };
                if let Some(e) = event {
                    let _ = tx.send(e);
                }
            }
            line.clear();
        }
    }
}

/// Single-quotes a word for `sh`.
fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

fn run_script(p: &Payload) -> String {
    let mut s = String::from("#!/bin/sh\n");
    for (k, v) in &p.env {
        s.push_str(&format!("export {k}={}\n", quote(v)));
    }
    if let Some(cwd) = &p.cwd {
        s.push_str(&format!(
            "mkdir -p {q} && cd {q}\n",
            q = quote(&cwd.to_string_lossy())
        ));
    }
    for (i, prog) in p.programs.iter().enumerate() {
        s.push_str(&format!(
            "echo \"{MARK} start {i} {}\"\n",
            prog.name.replace(['"', '$', '`', '\\'], "_")
        ));
        s.push_str(&quote(&prog.path.to_string_lossy()));
        for a in &prog.args {
            s.push(' ');
            s.push_str(&quote(a));
        }
        s.push_str(&format!("\necho \"{MARK} exit {i} $?\"\n"));
    }
    s
}

/// The libraries (and the dynamic loader) `ldd` lists for a program; empty for a static one.
pub fn shared_libraries(program: &Path) -> Result<Vec<PathBuf>> {
    let out = Command::new("ldd")
        .arg(program)
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .with_context(|| format!("running ldd {}", program.display()))?;
    if !out.status.success() {
        return Ok(Vec::new());
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut libs = Vec::new();
    for line in text.lines() {
        let path = match line.split_once("=>") {
            Some((_, right)) => right.split_whitespace().next(),
            None => line.split_whitespace().next(),
        };
        if let Some(p) = path.filter(|p| p.starts_with('/')) {
            libs.push(PathBuf::from(p));
        }
    }
    Ok(libs)
}

/// `can-raw.ko.xz` -> `can-raw.ko`.
fn module_name(path: &Path) -> String {
    let name = path.file_name().unwrap_or_default().to_string_lossy();
    for ext in [".xz", ".zst", ".gz"] {
        if let Some(stem) = name.strip_suffix(ext) {
            return stem.to_string();
        }
    }
    name.into_owned()
}

/// A module's bytes, decompressed on the host (busybox insmod may not decompress).
fn read_module(path: &Path) -> Result<Vec<u8>> {
    let name = path.to_string_lossy();
    let tool = if name.ends_with(".xz") {
        Some("xz")
    } else if name.ends_with(".zst") {
        Some("zstd")
    } else if name.ends_with(".gz") {
        Some("gzip")
    } else {
        None
    };
    match tool {
        None => fs::read(path).with_context(|| format!("reading {}", path.display())),
        Some(tool) => {
            let out = Command::new(tool)
                .arg("-dc")
                .arg(path)
                .output()
                .with_context(|| format!("running {tool} to decompress {}", path.display()))?;
            if !out.status.success() {
                bail!("{tool} -dc {} failed", path.display());
            }
            Ok(out.stdout)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_script_quotes_and_marks_every_program() {
        let p = Payload {
            programs: vec![
                Program {
                    name: "a".into(),
                    path: "/x/a b".into(),
                    args: vec!["it's".into()],
                },
                Program {
                    name: "b".into(),
                    path: "/x/b".into(),
                    args: vec![],
                },
            ],
            env: vec![("K".into(), "v w".into())],
            cwd: Some("/x".into()),
            files: vec![],
        };
        let s = run_script(&p);
        assert!(s.contains("export K='v w'\n"));
        assert!(s.contains("'/x/a b' 'it'\\''s'\n"));
        assert!(s.contains("@@ihex-vm exit 0 $?") && s.contains("@@ihex-vm exit 1 $?"));
        assert!(s.find("exit 0").unwrap() < s.find("'/x/b'").unwrap());
    }

    #[test]
    fn console_reports_markers_split_across_reads() {
        struct Chunks(Vec<&'static [u8]>);
        impl Read for Chunks {
            fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
                if self.0.is_empty() {
                    return Ok(0);
                }
                let c = self.0.remove(0);
                buf[..c.len()].copy_from_slice(c);
                Ok(c.len())
            }
        }
        let (tx, rx) = mpsc::sync_channel(16);
        let mut shown = Vec::new();
        console(
            Chunks(vec![
                b"boot\r\n@@ihex-vm re",
                b"ady\r\n@@ihex-vm start 1 some test\r\n@@ihex-vm exit 1 1",
                b"01\r\n",
            ]),
            &mut shown,
            tx,
        );
        assert_eq!(
            shown, b"boot\n@@ihex-vm ready\n@@ihex-vm start 1 some test\n@@ihex-vm exit 1 101\n",
            "console is shown without CRs"
        );
        let events: Vec<Event> = rx.iter().collect();
        assert!(matches!(
            events.as_slice(),
            [Event::Ready, Event::Start(1), Event::Exit(1, 101)]
        ));
    }

    #[test]
    fn compressed_module_names_lose_their_suffix() {
        assert_eq!(module_name(Path::new("/m/can-raw.ko.xz")), "can-raw.ko");
        assert_eq!(module_name(Path::new("/m/can.ko.zst")), "can.ko");
        assert_eq!(module_name(Path::new("/m/vcan.ko")), "vcan.ko");
    }
}
