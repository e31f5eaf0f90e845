//! The system calls neither std nor tokio offer: the MQTT connection's socket options (each a plain
//! `setsockopt`/`getsockopt` of one `c_int`: the receive low-water mark, delayed ACKs, Nagle), the
//! CAN socket's registration with tokio's reactor and its batched read (`recvmmsg`), and the
//! doctor's free-space query (`statvfs`). The one place of the crate allowed `unsafe`
//! (`#![deny(unsafe_code)]` everywhere else).

use std::{io, os::fd::RawFd};

/// Sets the receive low-water mark (`SO_RCVLOWAT`) of socket `fd`: the kernel reports it readable
/// once `bytes` have arrived (or the connection ended). `fd` must be a socket the caller owns; a
/// closed or foreign descriptor is the kernel's error, not undefined behaviour.
pub fn set_rcvlowat(fd: RawFd, bytes: u16) -> io::Result<()> {
    set_int(fd, libc::SOL_SOCKET, libc::SO_RCVLOWAT, bytes.into())
}

/// The receive low-water mark of socket `fd`, as the kernel has it (tests check what was set).
#[cfg(test)]
pub fn rcvlowat(fd: RawFd) -> io::Result<libc::c_int> {
    get_int(fd, libc::SOL_SOCKET, libc::SO_RCVLOWAT)
}

/// Puts TCP socket `fd` into delayed-ACK mode (`TCP_QUICKACK` 0, Linux's "pingpong" mode): a read
/// that empties the socket no longer sends a bare ACK at once for a small pushed segment; the ACK
/// goes with the next data written (or when the delayed-ACK timer fires, which also ends the mode).
/// `fd` must be a socket of this process; a closed or foreign descriptor is the kernel's error.
pub fn delay_acks(fd: RawFd) -> io::Result<()> {
    set_int(fd, libc::IPPROTO_TCP, libc::TCP_QUICKACK, 0)
}

/// Whether TCP socket `fd` acknowledges at once (`TCP_QUICKACK` as the kernel has it: false in
/// delayed-ACK mode; tests check what was set).
#[cfg(test)]
pub fn quickack(fd: RawFd) -> io::Result<bool> {
    get_int(fd, libc::IPPROTO_TCP, libc::TCP_QUICKACK).map(|v| v != 0)
}

/// Turns Nagle's algorithm off (`TCP_NODELAY`) on TCP socket `fd`; on a listening socket, every
/// connection it accepts from then on inherits the setting (Linux). `fd` must be a socket of this
/// process; a closed or foreign descriptor is the kernel's error, not undefined behaviour.
#[cfg(feature = "demo")]
pub fn set_nodelay(fd: RawFd) -> io::Result<()> {
    set_int(fd, libc::IPPROTO_TCP, libc::TCP_NODELAY, 1)
}

/// Whether Nagle's algorithm is off (`TCP_NODELAY`) on TCP socket `fd` (tests check what was set).
#[cfg(all(test, feature = "demo"))]
pub fn nodelay(fd: RawFd) -> io::Result<bool> {
    get_int(fd, libc::IPPROTO_TCP, libc::TCP_NODELAY).map(|v| v != 0)
}

/// Registers a CAN socket with tokio's reactor (the current runtime's).
pub fn register_can(
    sock: socketcan::CanSocket,
) -> io::Result<tokio::io::unix::AsyncFd<socketcan::CanSocket>> {
    // SAFETY: `CanSocket` owns its descriptor (an `OwnedFd`): it stays open and the same while the
    // socket lives, which the `AsyncFd` owns from here until it is dropped, and `as_raw_fd` always
    // returns it.
    unsafe { tokio::io::unix::AsyncFd::register(sock) }.map_err(|e| e.into_parts().1)
}

/// Frames one [`recv_can_frames`] call reads at most.
pub const CAN_BATCH: usize = 32;

/// Reads the classic CAN frames waiting on raw CAN socket `fd`, up to `frames.len()` (at most
/// [`CAN_BATCH`]), in one `recvmmsg` call that does not wait: how many frames were kept, at the
/// front of `frames`, and whether the call filled every place (then more may be waiting).
/// `WouldBlock` when none was waiting. A datagram that is not one `can_frame` (the socket is not
/// set up for CAN FD) is dropped. `fd` must be a socket of this process; a closed or foreign
/// descriptor is the kernel's error.
pub fn recv_can_frames(fd: RawFd, frames: &mut [libc::can_frame]) -> io::Result<(usize, bool)> {
    const MTU: usize = std::mem::size_of::<libc::can_frame>();
    let n = frames.len().min(CAN_BATCH);
    // SAFETY: all-zero is a valid `iovec` and `mmsghdr` (null pointers, zero lengths).
    let mut iov: [libc::iovec; CAN_BATCH] = unsafe { std::mem::zeroed() };
    let mut msgs: [libc::mmsghdr; CAN_BATCH] = unsafe { std::mem::zeroed() };
    for ((v, m), f) in iov.iter_mut().zip(msgs.iter_mut()).zip(frames.iter_mut()) {
        v.iov_base = (f as *mut libc::can_frame).cast();
        v.iov_len = MTU;
        m.msg_hdr.msg_iov = v;
        m.msg_hdr.msg_iovlen = 1;
    }
    // SAFETY: the first `n` headers each point to one live iovec, which points to one live
    // `can_frame` of `frames` (exclusively borrowed) and gives its exact size: the kernel writes at
    // most that many bytes there and the message lengths into `msgs`, all of which outlive the
    // call; no name or control buffers are given. Nothing keeps the pointers after it returns.
    let r = unsafe {
        libc::recvmmsg(
            fd,
            msgs.as_mut_ptr(),
            n as _,
            libc::MSG_DONTWAIT as _,
            std::ptr::null_mut(),
        )
    };
    if r < 0 {
        return Err(io::Error::last_os_error());
    }
    let mut kept = 0;
    for i in 0..r as usize {
        if msgs[i].msg_len as usize == MTU && msgs[i].msg_hdr.msg_flags & libc::MSG_TRUNC == 0 {
            frames[kept] = frames[i];
            kept += 1;
        }
    }
    Ok((kept, r as usize == n))
}

/// `setsockopt` of one `c_int`.
fn set_int(fd: RawFd, level: libc::c_int, name: libc::c_int, value: libc::c_int) -> io::Result<()> {
    // SAFETY: `setsockopt` reads exactly `size_of::<c_int>()` bytes from the pointer, which points
    // to `value`, a live `c_int` on this stack frame; the call does not keep the pointer. An
    // invalid `fd` is reported as EBADF/ENOTSOCK, no memory is touched for it.
    let r = unsafe {
        libc::setsockopt(
            fd,
            level,
            name,
            (&value as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if r == 0 {
        Ok(())
    } else {
        Err(io::Error::last_os_error())
    }
}

/// `getsockopt` of one `c_int`.
#[cfg(test)]
fn get_int(fd: RawFd, level: libc::c_int, name: libc::c_int) -> io::Result<libc::c_int> {
    let mut value: libc::c_int = 0;
    let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: `getsockopt` writes at most `len` bytes (the size of `value`, a live `c_int` on this
    // stack frame) and stores the written length in `len`, also live; neither pointer is kept.
    let r = unsafe {
        libc::getsockopt(
            fd,
            level,
            name,
            (&mut value as *mut libc::c_int).cast(),
            &mut len,
        )
    };
    if r == 0 {
        Ok(value)
    } else {
        Err(io::Error::last_os_error())
    }
}

/// Free space for an unprivileged user and total size, in bytes, of the file system holding `p`.
pub fn statvfs(p: &std::path::Path) -> std::io::Result<(u64, u64)> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(p.as_os_str().as_bytes())
        .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
    let mut s: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a NUL-terminated path and `s` a properly sized, writable statvfs.
    if unsafe { libc::statvfs(c.as_ptr(), &mut s) } != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let frsize = s.f_frsize as u64;
    Ok((s.f_bavail as u64 * frsize, s.f_blocks as u64 * frsize))
}

#[cfg(test)]
mod tests {
    use std::os::{fd::AsRawFd, unix::net::UnixDatagram};

    use super::*;

    /// Any datagram socket takes `recvmmsg` (the host running the tests has no CAN): frames in
    /// order, a batch at a time, a datagram of another size dropped, then `WouldBlock`.
    #[test]
    fn can_frames_are_read_a_batch_at_a_time_and_odd_datagrams_dropped() {
        let (tx, rx) = UnixDatagram::pair().unwrap();
        for i in 0..6u8 {
            let mut f = [0u8; 16];
            f[0] = i;
            f[4] = 1;
            f[8] = 0xa0 | i;
            tx.send(&f).unwrap();
        }
        tx.send(&[1, 2, 3]).unwrap();
        let mut frames = [socketcan::frame::can_frame_default(); 4];
        assert_eq!(
            recv_can_frames(rx.as_raw_fd(), &mut frames).unwrap(),
            (4, true)
        );
        let got: Vec<(u32, u8)> = frames.iter().map(|f| (f.can_id, f.data[0])).collect();
        assert_eq!(got, [(0, 0xa0), (1, 0xa1), (2, 0xa2), (3, 0xa3)]);
        assert_eq!(
            recv_can_frames(rx.as_raw_fd(), &mut frames).unwrap(),
            (2, false)
        );
        assert_eq!((frames[0].can_id, frames[1].data[0]), (4, 0xa5));
        let e = recv_can_frames(rx.as_raw_fd(), &mut frames).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::WouldBlock);
    }
}
