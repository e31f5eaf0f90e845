//! A scripted MQTT broker for the connection's tests: one connection, CONNACK, then only what the
//! test sends it.

use tokio::{
    io::{AsyncReadExt, AsyncWriteExt},
    net::TcpListener,
    sync::mpsc,
};

/// What the test sends the client through the broker: bytes written as they are.
pub type Script = mpsc::UnboundedSender<Vec<u8>>;

/// Accepts one connection and its CONNECT with an accepted CONNACK, then writes whatever the test
/// sends on the returned channel and acknowledges nothing by itself. It hangs up after `reads`
/// reads of what the client wrote (`None`: once the client hangs up). Returns its port.
pub async fn broker(reads: Option<usize>) -> (u16, Script) {
    let (port, script, _) = broker_seeing(reads).await;
    (port, script)
}

/// [`broker`], also handing the test every read of what the client wrote after its CONNECT.
pub async fn broker_seeing(
    reads: Option<usize>,
) -> (u16, Script, mpsc::UnboundedReceiver<Vec<u8>>) {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let (tx, mut script) = mpsc::unbounded_channel::<Vec<u8>>();
    let (seen_tx, seen) = mpsc::unbounded_channel::<Vec<u8>>();
    tokio::spawn(async move {
        let (mut s, _) = listener.accept().await.unwrap();
        let mut buf = vec![0u8; 64 * 1024];
        let _ = s.read(&mut buf).await; // CONNECT
        s.write_all(&[0x20, 0x02, 0x00, 0x00]).await.unwrap(); // CONNACK accepted
        let mut left = reads.unwrap_or(usize::MAX);
        while left > 0 {
            tokio::select! {
                Some(bytes) = script.recv() => s.write_all(&bytes).await.unwrap(),
                n = s.read(&mut buf) => {
                    let Ok(n @ 1..) = n else { break };
                    let _ = seen_tx.send(buf[..n].to_vec());
                    left -= 1;
                }
            }
        }
    });
    (port, tx, seen)
}

/// A PUBACK of `pkid` as it goes on the wire.
pub fn puback(pkid: u16) -> Vec<u8> {
    let [hi, lo] = pkid.to_be_bytes();
    vec![0x40, 0x02, hi, lo]
}
