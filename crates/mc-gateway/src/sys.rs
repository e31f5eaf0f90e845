//! The system calls neither std nor tokio offer: the MQTT connection's socket options (each a plain
//! `setsockopt`/`getsockopt` of one `c_int`) and the doctor's free-space query (`statvfs`). The one
//! place of the crate allowed `unsafe` (`#![deny(unsafe_code)]` everywhere else).

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
