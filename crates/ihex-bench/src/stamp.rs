//! Kernel timestamps for the latency probes: when a probe's MQTT packet entered this machine's
//! network stack or left it (a packet socket, `AF_PACKET`, with `SO_TIMESTAMPNS`), to set beside
//! when its frame was on the bus (a CAN socket's own `SO_TIMESTAMPNS`). The difference is what the
//! measured process added — its wake-up, its work and its write — without the benchmark's own
//! MQTT client and wake-ups, which the end-to-end series carry.

use std::io::IoSliceMut;
use std::os::fd::{AsFd, AsRawFd, OwnedFd};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result};
use nix::errno::Errno;
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::socket::{
    self, sockopt, AddressFamily, ControlMessageOwned, LinkAddr, MsgFlags, SockFlag, SockProtocol,
    SockType,
};
use nix::sys::time::TimeSpec;

/// `PACKET_OUTGOING` (linux/if_packet.h): a packet this machine sent.
const PACKET_OUTGOING: u8 = 4;
const ETH_P_IP: u16 = 0x0800;
const ETH_P_IPV6: u16 = 0x86dd;
const IPPROTO_TCP: u8 = 6;

/// Which way a probe's packet goes, seen from here.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Way {
    /// From the broker to a process here (a command on its way to the gateway).
    FromBroker,
    /// From a process here to the broker (an event the gateway publishes).
    ToBroker,
}

/// A packet socket on every interface, reading the broker's TCP traffic with receive timestamps.
pub(crate) struct Tap {
    fd: OwnedFd,
    broker_port: u16,
    buf: Vec<u8>,
}

impl Tap {
    /// Opens the tap for the broker listening on `broker_port` (needs `CAP_NET_RAW`).
    pub(crate) fn open(broker_port: u16) -> Result<Tap> {
        let fd = socket::socket(
            AddressFamily::Packet,
            SockType::Datagram,
            SockFlag::SOCK_NONBLOCK | SockFlag::SOCK_CLOEXEC,
            SockProtocol::EthAll,
        )
        .context("opening a packet socket (AF_PACKET) for the probes' kernel timestamps")?;
        socket::setsockopt(&fd, sockopt::ReceiveTimestampns, &true)
            .context("asking the packet socket for receive timestamps (SO_TIMESTAMPNS)")?;
        Ok(Tap {
            fd,
            broker_port,
            buf: vec![0; 1 << 16],
        })
    }

    /// Forgets every packet read so far.
    pub(crate) fn drain(&mut self) -> Result<()> {
        while self.next(Duration::ZERO)?.is_some() {}
        Ok(())
    }

    /// The kernel time of the first packet within `timeout` that goes `way` and carries `needle`
    /// in its TCP payload (`None`: no such packet, or the kernel gave it no timestamp).
    pub(crate) fn find(
        &mut self,
        way: Way,
        needle: &[u8],
        timeout: Duration,
    ) -> Result<Option<SystemTime>> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Some((outgoing, at, len)) = self.next(left)? else {
                return Ok(None);
            };
            let Some(seg) = tcp(&self.buf[..len]) else {
                continue;
            };
            let ours = match way {
                Way::FromBroker => !outgoing && seg.src == self.broker_port,
                Way::ToBroker => outgoing && seg.dst == self.broker_port,
            };
            if ours && contains(seg.payload, needle) {
                return Ok(at);
            }
        }
    }

    /// The next IP packet within `timeout`: whether this machine sent it, its timestamp and its
    /// length in `buf` (from the IP header on).
    fn next(&mut self, timeout: Duration) -> Result<Option<(bool, Option<SystemTime>, usize)>> {
        let deadline = Instant::now() + timeout;
        loop {
            let mut iov = [IoSliceMut::new(&mut self.buf)];
            let mut cmsg = nix::cmsg_space!(TimeSpec);
            let r = socket::recvmsg::<LinkAddr>(
                self.fd.as_raw_fd(),
                &mut iov,
                Some(&mut cmsg),
                MsgFlags::MSG_DONTWAIT,
            );
            match r {
                Ok(m) => {
                    let Some(addr) = m.address else { continue };
                    let proto = u16::from_be(addr.protocol());
                    if proto != ETH_P_IP && proto != ETH_P_IPV6 {
                        continue;
                    }
                    let at = m.cmsgs().ok().and_then(|mut c| {
                        c.find_map(|c| match c {
                            ControlMessageOwned::ScmTimestampns(t) => Some(system_time(t)),
                            _ => None,
                        })
                    });
                    return Ok(Some((addr.pkttype() == PACKET_OUTGOING, at, m.bytes)));
                }
                Err(Errno::EAGAIN) => {}
                Err(Errno::EINTR) => continue,
                Err(e) => return Err(e).context("reading the packet socket"),
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            let ms = u16::try_from(left.as_millis().max(1)).unwrap_or(u16::MAX);
            let mut fds = [PollFd::new(self.fd.as_fd(), PollFlags::POLLIN)];
            match poll(&mut fds, PollTimeout::from(ms)) {
                Ok(_) | Err(Errno::EINTR) => {}
                Err(e) => return Err(e).context("waiting on the packet socket"),
            }
        }
    }
}

/// `later - earlier` in µs (negative when the clock says otherwise).
pub(crate) fn micros_between(earlier: SystemTime, later: SystemTime) -> f64 {
    match later.duration_since(earlier) {
        Ok(d) => d.as_secs_f64() * 1e6,
        Err(e) => -e.duration().as_secs_f64() * 1e6,
    }
}

fn system_time(t: TimeSpec) -> SystemTime {
    UNIX_EPOCH
        + Duration::new(
            u64::try_from(t.tv_sec()).unwrap_or(0),
            u32::try_from(t.tv_nsec()).unwrap_or(0),
        )
}

/// A TCP segment's ports and payload.
#[derive(Debug, PartialEq, Eq)]
struct Segment<'a> {
    src: u16,
    dst: u16,
    payload: &'a [u8],
}

/// The TCP segment in the IPv4 or IPv6 packet `ip` (`None`: another protocol, IPv6 extension
/// headers, or cut short).
fn tcp(ip: &[u8]) -> Option<Segment<'_>> {
    let be16 = |b: &[u8], at: usize| Some(u16::from_be_bytes([*b.get(at)?, *b.get(at + 1)?]));
    let (proto, rest) = match ip.first()? >> 4 {
        4 => {
            let ihl = usize::from(ip[0] & 0x0f) * 4;
            // A segmentation-offloaded packet may say 0 here: then the packet is what was read.
            let total = match usize::from(be16(ip, 2)?) {
                0 => ip.len(),
                n => n.min(ip.len()),
            };
            (*ip.get(9)?, ip.get(ihl..total)?)
        }
        6 => {
            let end = (40 + usize::from(be16(ip, 4)?)).min(ip.len());
            (*ip.get(6)?, ip.get(40..end)?)
        }
        _ => return None,
    };
    if proto != IPPROTO_TCP {
        return None;
    }
    let offset = usize::from(rest.get(12)? >> 4) * 4;
    Some(Segment {
        src: be16(rest, 0)?,
        dst: be16(rest, 2)?,
        payload: rest.get(offset..)?,
    })
}

fn contains(haystack: &[u8], needle: &[u8]) -> bool {
    !needle.is_empty() && haystack.windows(needle.len()).any(|w| w == needle)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A TCP header (20 bytes, no options) from `src` to `dst`, then `payload`.
    fn tcp_bytes(src: u16, dst: u16, payload: &[u8]) -> Vec<u8> {
        let mut t = vec![0u8; 20];
        t[0..2].copy_from_slice(&src.to_be_bytes());
        t[2..4].copy_from_slice(&dst.to_be_bytes());
        t[12] = 5 << 4;
        t.extend_from_slice(payload);
        t
    }

    fn ipv4(proto: u8, body: &[u8], trailer: usize) -> Vec<u8> {
        let mut p = vec![0u8; 20];
        p[0] = 0x45;
        p[2..4].copy_from_slice(&((20 + body.len()) as u16).to_be_bytes());
        p[9] = proto;
        p.extend_from_slice(body);
        // Ethernet padding after the IP packet is not payload.
        p.extend(std::iter::repeat_n(0xee, trailer));
        p
    }

    #[test]
    fn an_ipv4_segment_gives_its_ports_and_payload_without_the_padding() {
        let p = ipv4(IPPROTO_TCP, &tcp_bytes(1883, 40000, b"hello"), 6);
        assert_eq!(
            tcp(&p),
            Some(Segment {
                src: 1883,
                dst: 40000,
                payload: b"hello"
            })
        );
    }

    #[test]
    fn an_ipv6_segment_gives_its_ports_and_payload() {
        let body = tcp_bytes(40000, 1883, b"{\"event\"}");
        let mut p = vec![0u8; 40];
        p[0] = 0x60;
        p[4..6].copy_from_slice(&(body.len() as u16).to_be_bytes());
        p[6] = IPPROTO_TCP;
        p.extend_from_slice(&body);
        let s = tcp(&p).unwrap();
        assert_eq!(
            (s.src, s.dst, s.payload),
            (40000, 1883, &b"{\"event\"}"[..])
        );
    }

    #[test]
    fn other_protocols_and_short_packets_are_not_segments() {
        assert_eq!(tcp(&ipv4(17, &tcp_bytes(1, 2, b"x"), 0)), None);
        let p = ipv4(IPPROTO_TCP, &tcp_bytes(1, 2, b"x"), 0);
        assert_eq!(tcp(&p[..30]), None);
        assert_eq!(tcp(&[]), None);
        assert_eq!(tcp(&[0x15; 40]), None);
    }

    #[test]
    fn a_needle_is_found_anywhere_and_never_when_empty() {
        assert!(contains(b"ab{\"cmd\":\"led\"}cd", b"{\"cmd\":\"led\"}"));
        assert!(!contains(b"abc", b"abd"));
        assert!(!contains(b"abc", b""));
    }

    /// The tap on this machine's loopback: a "broker" and a client, each way's packet found and
    /// stamped between the moments before and after it was sent.
    #[test]
    fn the_tap_finds_and_stamps_both_ways_on_loopback() {
        use std::io::{Read, Write};
        let broker = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let mut tap = match Tap::open(broker.local_addr().unwrap().port()) {
            Ok(t) => t,
            // Packet sockets need CAP_NET_RAW; the benchmark runs as root in its VM.
            Err(e) if format!("{e:#}").contains("EPERM") => {
                eprintln!("skipped: {e:#}");
                return;
            }
            Err(e) => panic!("{e:#}"),
        };
        let mut client = std::net::TcpStream::connect(broker.local_addr().unwrap()).unwrap();
        let (mut served, _) = broker.accept().unwrap();
        std::thread::sleep(Duration::from_millis(50));
        tap.drain().unwrap();

        let before = SystemTime::now();
        client.write_all(b"publish-to-broker-17").unwrap();
        let after = SystemTime::now();
        let at = tap
            .find(Way::ToBroker, b"to-broker-17", Duration::from_secs(2))
            .unwrap()
            .expect("the client's packet, stamped");
        assert!(before <= at && at <= after, "{before:?} {at:?} {after:?}");
        let mut buf = [0u8; 64];
        let _ = served.read(&mut buf).unwrap();

        // The same bytes the other way are not taken for this way's packet.
        let before = SystemTime::now();
        served.write_all(b"deliver-from-broker-18").unwrap();
        let after = SystemTime::now();
        assert_eq!(
            tap.find(Way::ToBroker, b"from-broker-18", Duration::from_millis(200))
                .unwrap(),
            None
        );
        tap.drain().unwrap();
        served.write_all(b"deliver-from-broker-19").unwrap();
        let at = tap
            .find(Way::FromBroker, b"from-broker-19", Duration::from_secs(2))
            .unwrap()
            .expect("the broker's packet, stamped");
        assert!(before <= at, "{before:?} {at:?}");
        assert!(
            at >= after,
            "the second packet was sent after the first one's `after`"
        );
    }

    #[test]
    fn time_between_is_signed() {
        let t = UNIX_EPOCH + Duration::from_secs(10);
        let later = t + Duration::from_micros(1500);
        assert_eq!(micros_between(t, later), 1500.0);
        assert_eq!(micros_between(later, t), -1500.0);
    }
}
