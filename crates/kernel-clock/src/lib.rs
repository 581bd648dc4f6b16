//! Whether the kernel says the system clock is synchronised. Linux keeps the state of its
//! clock discipline, which time daemons (chronyd, ntpd, systemd-timesyncd, phc2sys) set
//! while they keep the clock synchronised; `adjtimex(2)` reads it. Neither the standard
//! library nor nix wraps that call, so it is made here through libc, in the one
//! function of this crate that may use `unsafe` (ARCHITECTURE.md, "Unsafe code lives
//! in three places").

/// Whether the kernel says the system clock is synchronised: `adjtimex(2)` asked
/// without changing anything (modes 0) returns a clock state other than `TIME_ERROR`,
/// and the status it fills in has no `STA_UNSYNC`. A time daemon clears `STA_UNSYNC`
/// while it keeps the clock synchronised, and the kernel sets it again when its estimate
/// of the clock's error passes 16 s; `timedatectl` shows the same state as "System clock
/// synchronized". `false` when the call fails, and on systems other than Linux.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
pub fn synchronised() -> bool {
    // SAFETY: `timex` is a plain C struct for which all zeros is a valid value; with
    // `modes` 0 adjtimex only fills it in, and the pointer is to a live local.
    let mut tx: libc::timex = unsafe { std::mem::zeroed() };
    let state = unsafe { libc::adjtimex(&raw mut tx) };
    state >= 0 && state != libc::TIME_ERROR && tx.status & libc::STA_UNSYNC == 0
}

/// Whether the kernel says the system clock is synchronised: not known here, so `false`.
#[cfg(not(target_os = "linux"))]
pub fn synchronised() -> bool {
    false
}
