//! Setting and reading a sub-controller's node ID over its ST-Link virtual COM port (115200 8N1).
//!
//! The exchange is the protocol's 2-byte UART message (`ihex_proto::uart`): one request, one reply.
//! [`ReplyDecoder`] and [`check_reply`] are the sans-IO half (tested on their own); [`SerialPort`] is
//! a thin termios adapter (no libudev, so it builds for static musl); [`Session`] runs the exchange
//! with a bounded wait for every reply.

use std::{
    collections::VecDeque,
    fs::File,
    io::{self, Read, Write},
    path::{Path, PathBuf},
    time::{Duration, Instant},
};

use ihex_proto::{
    uart::{UartError, UartReply, UartRequest, BAUD, REPLY_ERR_MARKER, REPLY_ID_MARKER},
    NodeId,
};
use rustix::{
    event::{poll, PollFd, PollFlags, Timespec},
    fs::{Mode, OFlags},
    termios::{self, OptionalActions, QueueSelector},
};

/// Errors of the serial exchange.
#[derive(Debug, thiserror::Error)]
pub enum SerialError {
    /// Opening or configuring the port failed.
    #[error("cannot open serial port {path}: {source}")]
    Open {
        /// The device path.
        path: PathBuf,
        /// The OS error.
        source: io::Error,
    },
    /// Reading or writing failed.
    #[error("serial I/O on {path}: {source}")]
    Io {
        /// The device path.
        path: PathBuf,
        /// The OS error.
        source: io::Error,
    },
    /// No complete reply in time.
    #[error("no reply from the sub-controller within {0:?} (is the firmware running and this its ST-Link port?)")]
    Timeout(Duration),
    /// Two bytes that start like a reply but are none.
    #[error("garbled reply {0:02x?}")]
    Garbled([u8; 2]),
    /// The sub-controller refused the request.
    #[error("the sub-controller refused: {0}")]
    Refused(UartError),
    /// The sub-controller answered with another ID than the one asked for.
    #[error("the sub-controller reports ID {got} after being asked for {want}")]
    Mismatch {
        /// Requested ID.
        want: NodeId,
        /// ID it reported.
        got: NodeId,
    },
}

/// Finds replies in the received byte stream. Bytes that cannot start a reply (noise from a board
/// that was just reset, a half message from an earlier run) are skipped and counted.
#[derive(Clone, Copy, Default, Debug)]
pub struct ReplyDecoder {
    first: Option<u8>,
    skipped: usize,
}

impl ReplyDecoder {
    /// An idle decoder.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feeds one byte; a reply (or a garbled pair) once two bytes belong together.
    pub fn push(&mut self, byte: u8) -> Option<Result<UartReply, SerialError>> {
        match self.first.take() {
            None => {
                if matches!(byte >> 4, REPLY_ID_MARKER | REPLY_ERR_MARKER) {
                    self.first = Some(byte);
                } else {
                    self.skipped += 1;
                }
                None
            }
            Some(b0) => {
                let pair = [b0, byte];
                Some(UartReply::decode(pair).ok_or(SerialError::Garbled(pair)))
            }
        }
    }

    /// How many bytes were skipped as noise.
    pub fn skipped(&self) -> usize {
        self.skipped
    }
}

/// Checks a reply to `request`: a set must echo the requested ID; a query returns whatever is stored
/// ([`NodeId::UNCONFIGURED`] for a fresh board).
pub fn check_reply(request: UartRequest, reply: UartReply) -> Result<NodeId, SerialError> {
    match (request, reply) {
        (_, UartReply::Error(e)) => Err(SerialError::Refused(e)),
        (UartRequest::SetId(want), UartReply::Id(got)) if got != want => {
            Err(SerialError::Mismatch { want, got })
        }
        (_, UartReply::Id(got)) => Ok(got),
    }
}

/// A serial port in raw 115200 8N1 mode.
#[derive(Debug)]
pub struct SerialPort {
    file: File,
    path: PathBuf,
}

impl SerialPort {
    /// Opens `path` (no controlling terminal) and sets raw mode, 115200 baud, 8N1, no flow control.
    pub fn open(path: &Path) -> Result<Self, SerialError> {
        let open_err = |source: io::Error| SerialError::Open {
            path: path.into(),
            source,
        };
        let fd = rustix::fs::open(
            path,
            OFlags::RDWR | OFlags::NOCTTY | OFlags::CLOEXEC | OFlags::NONBLOCK,
            Mode::empty(),
        )
        .map_err(|e| open_err(e.into()))?;
        let mut t = termios::tcgetattr(&fd).map_err(|e| open_err(e.into()))?;
        t.make_raw();
        t.control_modes &= !(termios::ControlModes::CSTOPB
            | termios::ControlModes::PARENB
            | termios::ControlModes::CRTSCTS);
        t.control_modes |= termios::ControlModes::CLOCAL | termios::ControlModes::CREAD;
        t.input_modes &= !(termios::InputModes::IXON | termios::InputModes::IXOFF);
        t.set_speed(BAUD).map_err(|e| open_err(e.into()))?;
        termios::tcsetattr(&fd, OptionalActions::Now, &t).map_err(|e| open_err(e.into()))?;
        // Whatever the board printed before we opened the port is not a reply to us.
        let _ = termios::tcflush(&fd, QueueSelector::IFlush);
        Ok(SerialPort {
            file: File::from(fd),
            path: path.into(),
        })
    }

    fn io_err(&self, source: io::Error) -> SerialError {
        SerialError::Io {
            path: self.path.clone(),
            source,
        }
    }

    /// Writes all of `bytes`.
    pub fn write_all(&mut self, bytes: &[u8]) -> Result<(), SerialError> {
        let mut rest = bytes;
        while !rest.is_empty() {
            match self.file.write(rest) {
                Ok(n) => rest = &rest[n..],
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    self.wait(PollFlags::OUT, Duration::from_millis(100))?;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(self.io_err(e)),
            }
        }
        Ok(())
    }

    /// Reads what is available, waiting at most `timeout` for the first byte; `0` on timeout.
    pub fn read_timeout(
        &mut self,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, SerialError> {
        if !self.wait(PollFlags::IN, timeout)? {
            return Ok(0);
        }
        match self.file.read(buf) {
            Ok(n) => Ok(n),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                ) =>
            {
                Ok(0)
            }
            Err(e) => Err(self.io_err(e)),
        }
    }

    fn wait(&self, flags: PollFlags, timeout: Duration) -> Result<bool, SerialError> {
        let ts = Timespec::try_from(timeout).unwrap_or(Timespec {
            tv_sec: 1,
            tv_nsec: 0,
        });
        let mut fds = [PollFd::new(&self.file, flags)];
        match poll(&mut fds, Some(&ts)) {
            Ok(n) => {
                let revents = fds[0].revents();
                if n > 0
                    && revents.intersects(PollFlags::HUP | PollFlags::ERR)
                    && !revents.contains(flags)
                {
                    return Err(self.io_err(io::Error::new(
                        io::ErrorKind::BrokenPipe,
                        "the port hung up (board unplugged?)",
                    )));
                }
                Ok(n > 0)
            }
            Err(rustix::io::Errno::INTR) => Ok(false),
            Err(e) => Err(self.io_err(e.into())),
        }
    }
}

/// Request/reply exchanges over one open port.
///
/// Received bytes beyond the reply being waited for are kept, not dropped: a board whose flash write
/// fails answers a set with its ID *and then* a `StoreFailed` error (the core queues the error when the
/// adapter reports the failure), and that error must surface as the answer to the next request.
#[derive(Debug)]
pub struct Session {
    port: SerialPort,
    decoder: ReplyDecoder,
    pending: VecDeque<u8>,
    timeout: Duration,
}

impl Session {
    /// Wraps an open port; every reply is awaited at most `timeout`.
    pub fn new(port: SerialPort, timeout: Duration) -> Self {
        Session {
            port,
            decoder: ReplyDecoder::new(),
            pending: VecDeque::new(),
            timeout,
        }
    }

    /// Sends `request` and returns the checked reply (see [`check_reply`]).
    pub fn exchange(&mut self, request: UartRequest) -> Result<NodeId, SerialError> {
        self.port.write_all(&request.encode())?;
        let deadline = Instant::now() + self.timeout;
        let mut buf = [0u8; 64];
        loop {
            while let Some(b) = self.pending.pop_front() {
                if let Some(reply) = self.decoder.push(b) {
                    return check_reply(request, reply?);
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(SerialError::Timeout(self.timeout));
            }
            let n = self.port.read_timeout(&mut buf, left)?;
            self.pending.extend(&buf[..n]);
        }
    }

    /// Stores `id` on the board, then reads it back to confirm it is in force. The read-back also
    /// catches a `StoreFailed` error that trails the set reply.
    pub fn set_id(&mut self, id: NodeId) -> Result<NodeId, SerialError> {
        self.exchange(UartRequest::SetId(id))?;
        let now = self.exchange(UartRequest::Query)?;
        if now != id {
            return Err(SerialError::Mismatch { want: id, got: now });
        }
        Ok(now)
    }

    /// The ID the board reports ([`NodeId::UNCONFIGURED`] when it has none).
    pub fn query_id(&mut self) -> Result<NodeId, SerialError> {
        self.exchange(UartRequest::Query)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::id;

    fn feed(dec: &mut ReplyDecoder, bytes: &[u8]) -> Vec<Result<UartReply, String>> {
        bytes
            .iter()
            .filter_map(|&b| dec.push(b))
            .map(|r| r.map_err(|e| e.to_string()))
            .collect()
    }

    #[test]
    fn decodes_replies_and_skips_noise() {
        let mut dec = ReplyDecoder::new();
        let mut stream = vec![0x00, b'\n', 0x41];
        stream.extend(UartReply::Id(id(0x123)).encode());
        stream.extend(UartReply::Error(UartError::ReservedId).encode());
        let out = feed(&mut dec, &stream);
        assert_eq!(
            out,
            [
                Ok(UartReply::Id(id(0x123))),
                Ok(UartReply::Error(UartError::ReservedId))
            ]
        );
        assert_eq!(dec.skipped(), 3);
    }

    #[test]
    fn garbled_pair_is_an_error_not_a_panic() {
        let mut dec = ReplyDecoder::new();
        // Error marker with a non-zero low nibble, then an unknown error code.
        let out = feed(&mut dec, &[0xE1, 0x01, 0xE0, 0x77]);
        assert_eq!(out.len(), 2);
        assert!(
            out.iter()
                .all(|r| r.as_ref().unwrap_err().contains("garbled")),
            "{out:?}"
        );
    }

    #[test]
    fn set_reply_must_echo_the_id() {
        let req = UartRequest::SetId(id(0x123));
        assert_eq!(
            check_reply(req, UartReply::Id(id(0x123))).unwrap(),
            id(0x123)
        );
        let err = check_reply(req, UartReply::Id(id(0x124))).unwrap_err();
        assert!(matches!(err, SerialError::Mismatch { .. }), "{err}");
        let err = check_reply(req, UartReply::Error(UartError::StoreFailed)).unwrap_err();
        assert!(err.to_string().contains("flash"), "{err}");
        assert_eq!(
            check_reply(UartRequest::Query, UartReply::Id(NodeId::UNCONFIGURED)).unwrap(),
            NodeId::UNCONFIGURED
        );
    }
}
