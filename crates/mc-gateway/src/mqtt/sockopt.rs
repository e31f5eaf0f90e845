//! The socket options the MQTT connection sets that neither std nor tokio offer: the one place of
//! the crate allowed `unsafe` (`#![deny(unsafe_code)]` everywhere else), each block a plain
//! `setsockopt`/`getsockopt` of one `c_int`.

use std::{io, os::fd::RawFd};

/// Sets the receive low-water mark (`SO_RCVLOWAT`) of socket `fd`: the kernel reports it readable
/// once `bytes` have arrived (or the connection ended). `fd` must be a socket the caller owns; a
/// closed or foreign descriptor is the kernel's error, not undefined behaviour.
pub fn set_rcvlowat(fd: RawFd, bytes: u16) -> io::Result<()> {
    let value = libc::c_int::from(bytes);
    // SAFETY: `setsockopt` reads exactly `size_of::<c_int>()` bytes from the pointer, which points
    // to `value`, a live `c_int` on this stack frame; the call does not keep the pointer. An
    // invalid `fd` is reported as EBADF/ENOTSOCK, no memory is touched for it.
    let r = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVLOWAT,
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

/// The receive low-water mark of socket `fd`, as the kernel has it (tests check what was set).
#[cfg(test)]
pub fn rcvlowat(fd: RawFd) -> io::Result<libc::c_int> {
    let mut value: libc::c_int = 0;
    let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
    // SAFETY: `getsockopt` writes at most `len` bytes (the size of `value`, a live `c_int` on this
    // stack frame) and stores the written length in `len`, also live; neither pointer is kept.
    let r = unsafe {
        libc::getsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_RCVLOWAT,
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
