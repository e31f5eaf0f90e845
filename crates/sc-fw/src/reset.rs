//! Why the chip started, from the RCC reset flags (read once, then cleared for the next reset).

use embassy_stm32::pac::RCC;
use ihex_proto::ResetReason;

/// Reads and clears the reset flags. A panic resets through `SYSRESETREQ`, so it reads as `Software`.
pub fn take_reset_reason() -> ResetReason {
    let csr = RCC.csr().read();
    // A power-on reset also raises PINRSTF, so POR is tested first.
    let reason = if csr.porrstf() {
        ResetReason::PowerOn
    } else if csr.iwdgrstf() {
        ResetReason::Watchdog
    } else if csr.sftrstf() {
        ResetReason::Software
    } else if csr.pinrstf() {
        ResetReason::Pin
    } else {
        ResetReason::Other(0xFF)
    };
    RCC.csr().modify(|w| w.set_rmvf(true));
    reason
}
