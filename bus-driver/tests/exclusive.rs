//! A serial bus is held by one process at a time, and a refused second opener leaves the holder's
//! hold as it was (hazard C1 in docs/hazards.md).

#![allow(clippy::unwrap_used, clippy::expect_used)]
#![allow(
    unsafe_code,
    reason = "TIOCGEXCL, read-only, to see the tty's exclusive flag (nix has no wrapper)"
)]

use bus_driver::transport::TransportError;
use bus_driver::SerialTransport;
use std::os::fd::AsRawFd;
use std::path::PathBuf;

/// A pseudo-terminal's slave path; the master is kept open so the line stays up.
fn line() -> (std::os::fd::OwnedFd, PathBuf) {
    let pty = nix::pty::openpty(None, None).unwrap();
    let path = nix::unistd::ttyname(&pty.slave).unwrap();
    (pty.master, path)
}

/// The tty's exclusive flag (TIOCEXCL), read through a descriptor of its own.
fn exclusive(path: &PathBuf) -> bool {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
        .open(path)
        .unwrap();
    let mut flag: nix::libc::c_int = 0;
    // SAFETY: TIOCGEXCL writes one int through the pointer, valid for the call, on an open fd.
    let r = unsafe { nix::libc::ioctl(file.as_raw_fd(), nix::libc::TIOCGEXCL, &mut flag) };
    assert_eq!(r, 0, "TIOCGEXCL");
    flag != 0
}

#[test]
fn a_second_opener_is_refused_and_the_holder_keeps_its_port_exclusive() {
    let (_master, path) = line();
    let held = SerialTransport::open(&path, 1_000_000).unwrap();
    assert!(exclusive(&path));
    for _ in 0..3 {
        match SerialTransport::open(&path, 1_000_000) {
            Err(TransportError::Busy { device }) => assert_eq!(device, path),
            Err(other) => panic!("refused for the wrong reason: {other}"),
            Ok(_) => panic!("a second opener got the bus"),
        }
        // Refused without touching the holder's flag (serialport's own refusal, as root,
        // cleared it on its way out).
        assert!(exclusive(&path), "the holder's port is no longer exclusive");
    }
    drop(held);
    assert!(!exclusive(&path));
    SerialTransport::open(&path, 1_000_000).expect("free again once the holder is gone");
}
