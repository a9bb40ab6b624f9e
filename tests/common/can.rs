//! For the tests that need SocketCAN (tests/can.rs, tests/canopen.rs): whether this machine
//! has it, and skipping where it has not, except where `RIGBRIDGE_REQUIRE_CAN=1` (the VM
//! scripts/test.sh starts) makes a missing bus a failure.

use rigbridge::transport::interface_up;

fn required() -> bool {
    std::env::var("RIGBRIDGE_REQUIRE_CAN").is_ok_and(|v| v == "1")
}

/// Prints why a test does not run here, or fails it where CAN is required.
pub fn skip(why: &str) {
    assert!(
        !required(),
        "RIGBRIDGE_REQUIRE_CAN=1, but {why}; scripts/test.sh runs this test inside a VM with vcan0"
    );
    println!("skipping: {why}; scripts/test.sh runs this test inside a VM with vcan0");
}

/// Whether this kernel has SocketCAN and `interface` is up; why not otherwise.
pub fn socketcan_here(interface: &str) -> Result<(), String> {
    // SAFETY: socket(2) with constant arguments; the descriptor is closed at once.
    let fd = unsafe { libc::socket(libc::PF_CAN, libc::SOCK_RAW, libc::CAN_RAW) };
    if fd < 0 {
        return Err(format!(
            "SocketCAN not available here ({})",
            std::io::Error::last_os_error()
        ));
    }
    // SAFETY: fd is the descriptor socket(2) just returned.
    unsafe { libc::close(fd) };
    match interface_up(interface) {
        Some(true) => Ok(()),
        Some(false) => Err(format!("{interface} is down")),
        None => Err(format!("no CAN interface {interface} here")),
    }
}
