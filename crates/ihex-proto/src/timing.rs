//! bxCAN bit timing: prescaler and segment lengths from a peripheral clock and a bitrate.

/// One bit split into time quanta: `1 (sync) + bs1 + bs2`, sampled after `1 + bs1`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct BitTiming {
    /// Clock divider, 1–1024.
    pub prescaler: u16,
    /// Time segment 1 (propagation + phase 1), 1–16 quanta.
    pub bs1: u8,
    /// Time segment 2 (phase 2), 1–8 quanta.
    pub bs2: u8,
    /// Resynchronisation jump width, 1–4 quanta.
    pub sjw: u8,
}

/// Why no timing fits.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TimingError {
    /// Bitrate or clock is zero.
    Zero,
    /// No prescaler and quanta count (8–25 quanta per bit) divide the clock exactly into the bitrate.
    NoExactTiming,
}

impl core::fmt::Display for TimingError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            TimingError::Zero => "clock and bitrate must be non-zero",
            TimingError::NoExactTiming => {
                "no bxCAN prescaler/segment split gives this bitrate exactly from this clock"
            }
        })
    }
}

impl core::error::Error for TimingError {}

impl BitTiming {
    /// Target sample point, per mille (CiA recommends 87.5 % up to 800 kbit/s).
    pub const TARGET_SAMPLE_POINT_PERMILLE: u32 = 875;

    /// The exact timing whose sample point is nearest 87.5 % (ties: more quanta per bit), SJW 1.
    ///
    /// 36 MHz → 500 kbit/s gives prescaler 9 and 1 + 6 + 1 quanta, the seed's table.
    pub const fn compute(pclk_hz: u32, bitrate: u32) -> Result<BitTiming, TimingError> {
        if pclk_hz == 0 || bitrate == 0 {
            return Err(TimingError::Zero);
        }
        let mut best: Option<(BitTiming, u32)> = None;
        // 8 quanta minimum keeps enough resolution for the sample point; 25 is the hardware maximum.
        let mut tq = 25u32;
        while tq >= 8 {
            let per_bit = bitrate as u64 * tq as u64;
            if (pclk_hz as u64).is_multiple_of(per_bit) {
                let prescaler = (pclk_hz as u64 / per_bit) as u32;
                if prescaler >= 1 && prescaler <= 1024 {
                    // Samples after 1 + bs1 quanta; round to the nearest quantum, then clamp to the ranges.
                    let mut before = (tq * Self::TARGET_SAMPLE_POINT_PERMILLE + 500) / 1000;
                    if before > 17 {
                        before = 17;
                    }
                    if tq - before > 8 {
                        before = tq - 8;
                    }
                    if before >= tq {
                        before = tq - 1;
                    }
                    let bs1 = before - 1;
                    let bs2 = tq - before;
                    if bs1 >= 1 && bs1 <= 16 && bs2 >= 1 && bs2 <= 8 {
                        let sp = before * 1000 / tq;
                        let err = sp.abs_diff(Self::TARGET_SAMPLE_POINT_PERMILLE);
                        let t = BitTiming {
                            prescaler: prescaler as u16,
                            bs1: bs1 as u8,
                            bs2: bs2 as u8,
                            sjw: 1,
                        };
                        let better = match best {
                            None => true,
                            Some((_, e)) => err < e,
                        };
                        if better {
                            best = Some((t, err));
                        }
                    }
                }
            }
            tq -= 1;
        }
        match best {
            Some((t, _)) => Ok(t),
            None => Err(TimingError::NoExactTiming),
        }
    }

    /// Quanta per bit.
    pub const fn quanta(&self) -> u32 {
        1 + self.bs1 as u32 + self.bs2 as u32
    }

    /// Sample point in per mille of the bit.
    pub const fn sample_point_permille(&self) -> u32 {
        (1 + self.bs1 as u32) * 1000 / self.quanta()
    }

    /// True when every field is in the range bxCAN can hold (prescaler 1–1024, BS1 1–16, BS2 1–8,
    /// SJW 1–4 and no longer than either segment). [`BitTiming::compute`] only returns valid timings.
    pub const fn is_valid(&self) -> bool {
        self.prescaler >= 1
            && self.prescaler <= 1024
            && self.bs1 >= 1
            && self.bs1 <= 16
            && self.bs2 >= 1
            && self.bs2 <= 8
            && self.sjw >= 1
            && self.sjw <= 4
            && self.sjw <= self.bs1
            && self.sjw <= self.bs2
    }

    /// The bitrate this timing gives from `pclk_hz` (0 for a zero prescaler rather than a panic).
    pub const fn bitrate(&self, pclk_hz: u32) -> u32 {
        match pclk_hz.checked_div(self.prescaler as u32 * self.quanta()) {
            Some(rate) => rate,
            None => 0,
        }
    }

    /// The value of bxCAN's `CAN_BTR` register timing fields (BRP, TS1, TS2, SJW; mode bits clear).
    ///
    /// Each field is masked to its register width, so an invalid timing (see
    /// [`BitTiming::is_valid`]) gives a wrong value but never a panic or a bit in a neighbouring field.
    pub const fn btr(&self) -> u32 {
        ((self.sjw.saturating_sub(1) as u32 & 0x3) << 24)
            | ((self.bs2.saturating_sub(1) as u32 & 0x7) << 20)
            | ((self.bs1.saturating_sub(1) as u32 & 0xF) << 16)
            | (self.prescaler.saturating_sub(1) as u32 & 0x3FF)
    }
}
