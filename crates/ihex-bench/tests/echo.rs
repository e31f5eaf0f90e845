//! `ihex-bench echo`, the far end of the live run's process round trip, answers every write at
//! once (a buffered copy would make the round trip wait) and ends with its input.

use std::io::{Read, Write};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

#[test]
fn echo_answers_each_write_before_the_next() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_ihex-bench"))
        .arg("echo")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut to = child.stdin.take().unwrap();
    let mut from = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut buf = [0u8; 3];
        from.read_exact(&mut buf[..1]).unwrap();
        tx.send(buf[..1].to_vec()).unwrap();
        from.read_exact(&mut buf[1..]).unwrap();
        tx.send(buf[1..].to_vec()).unwrap();
    });
    to.write_all(b"a").unwrap();
    let first = rx.recv_timeout(Duration::from_secs(10));
    assert_eq!(
        first.as_deref(),
        Ok(&b"a"[..]),
        "the first byte, with the input still open"
    );
    to.write_all(b"bc").unwrap();
    let second = rx.recv_timeout(Duration::from_secs(10));
    assert_eq!(second.as_deref(), Ok(&b"bc"[..]));
    drop(to);
    assert!(child.wait().unwrap().success(), "ends with its input");
}
