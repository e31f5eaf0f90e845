//! Bit lengths of the extended data frames every iHEX message travels in, with and without
//! worst-case bit stuffing: what a bus-share budget (the firmware sender's cap) and the
//! benchmark's frame-rate limits count.
//!
//! An extended data frame with `n` data bytes is, field by field: SOF 1, base ID 11, SRR 1, IDE 1,
//! extended ID 18, RTR 1, r1 + r0 2, DLC 4, data 8n, CRC 15, CRC delimiter 1, ACK slot 1, ACK
//! delimiter 1, EOF 7 — 64 + 8n bits — plus the 3-bit interframe space before the next frame can
//! start: **67 + 8n** bits. Stuffing covers SOF through the CRC (54 + 8n bits); after the first
//! five equal bits every further four can force one stuff bit, so the worst case adds
//! **floor((54 + 8n − 1) / 4)** bits. 8 data bytes: 131 bits plain, 160 worst case.

/// Bits from SOF to the end of the CRC sequence (the stuffed region) of an extended frame.
pub const fn stuffed_region_bits(data_len: u8) -> u32 {
    54 + 8 * data_len as u32
}

/// Bits of an extended data frame including the 3-bit interframe space, without stuff bits.
pub const fn frame_bits(data_len: u8) -> u32 {
    67 + 8 * data_len as u32
}

/// The most stuff bits an extended frame with `data_len` bytes can carry.
pub const fn worst_stuff_bits(data_len: u8) -> u32 {
    (stuffed_region_bits(data_len) - 1) / 4
}

/// Bits of an extended data frame with worst-case stuffing, interframe space included: the
/// most bus time one frame can take.
pub const fn frame_bits_worst(data_len: u8) -> u32 {
    frame_bits(data_len) + worst_stuff_bits(data_len)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eight_and_zero_byte_frames() {
        assert_eq!(frame_bits(8), 131);
        assert_eq!(worst_stuff_bits(8), 29);
        assert_eq!(frame_bits_worst(8), 160);
        assert_eq!(frame_bits(0), 67);
        assert_eq!(frame_bits_worst(0), 80);
    }
}
