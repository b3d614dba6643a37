//! Galvo code mapping, free of registers so a host test runs it (`firmware/tests/board_model.rs`
//! includes this file through `#[path]`).
//!
//! The protocol speaks galvo codes `0..=galvo_max` per axis (the capabilities' `galvo_max`). The
//! board turns them into DAC codes for one of two output paths:
//!
//! - [`GalvoOutput::ExternalDac16`], the documented choice: a 16-bit dual SPI DAC (AD5689R, internal
//!   2.5 V reference, gain ×2: 0–5 V) followed by a difference amplifier per axis,
//!   `V_out = G·(V_dac − 2.5 V)` with `G` = 4 (±10 V galvo inputs) or 2 (±5 V). Code 0 is the
//!   negative end, 32768 is 0 V (mirror centred), 65535 the positive end. The DAC powers up at
//!   mid-scale (RSTSEL tied high), so the mirrors sit centred from power-on on.
//! - [`GalvoOutput::InternalDac12`], the fallback: the STM32's 12-bit DAC with its output buffer,
//!   which only swings about 0.2–3.1 V on a 3.3 V supply (not rail to rail). The full protocol
//!   range maps linearly onto that usable window instead of clipping at the rails.
//!
//! Either way the map can invert or swap axes, so a mirror mounted the other way round is fixed in
//! configuration, not wiring. No slam at boot and no ramp needed: the core's first write is the
//! centre ([`GalvoMap::centre`]), which is where the external DAC powers up (RSTSEL high: mid-scale),
//! so every write is one write and none waits (a blocking ramp used to stall the executor up to
//! 32 ms).

pub use subsurf_protocol::GalvoOutput;

/// Supply of the internal DAC, mV.
pub const VDDA_MV: u32 = 3_300;
/// Lowest output of the buffered internal DAC that is still linear, mV (datasheet: ~0.2 V).
pub const INTERNAL_MIN_MV: u32 = 200;
/// Highest output of the buffered internal DAC that is still linear, mV (datasheet: VDDA − 0.2 V).
pub const INTERNAL_MAX_MV: u32 = 3_100;
/// Largest internal DAC code.
pub const INTERNAL_FULL: u16 = 4095;
/// Largest external DAC code.
pub const EXTERNAL_FULL: u16 = 65_535;

/// Internal DAC code for an output voltage (mV), rounded.
pub const fn internal_code_for_mv(mv: u32) -> u16 {
    let code = (mv * INTERNAL_FULL as u32 + VDDA_MV / 2) / VDDA_MV;
    if code > INTERNAL_FULL as u32 {
        INTERNAL_FULL
    } else {
        code as u16
    }
}

/// How protocol codes become DAC codes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GalvoMap {
    /// Output path.
    pub output: GalvoOutput,
    /// Largest protocol code (announced in the capabilities).
    pub galvo_max: u16,
    /// Lowest and highest DAC code used, per axis: the protocol range maps linearly onto it.
    pub dac_lo: u16,
    /// See `dac_lo`.
    pub dac_hi: u16,
    /// Mirror X runs the other way.
    pub invert_x: bool,
    /// Mirror Y runs the other way.
    pub invert_y: bool,
    /// X and Y are wired to the other DAC channels.
    pub swap_xy: bool,
}

impl GalvoMap {
    /// The documented wiring for an output path: 16-bit full scale on the external DAC; the
    /// linear 0.2–3.1 V window on the internal one; announced as `galvo_max` = 65535 or 4095.
    pub const fn for_output(output: GalvoOutput) -> Self {
        match output {
            GalvoOutput::ExternalDac16 => Self {
                output,
                galvo_max: EXTERNAL_FULL,
                dac_lo: 0,
                dac_hi: EXTERNAL_FULL,
                invert_x: false,
                invert_y: false,
                swap_xy: false,
            },
            GalvoOutput::InternalDac12 => Self {
                output,
                galvo_max: INTERNAL_FULL,
                dac_lo: internal_code_for_mv(INTERNAL_MIN_MV),
                dac_hi: internal_code_for_mv(INTERNAL_MAX_MV),
                invert_x: false,
                invert_y: false,
                swap_xy: false,
            },
        }
    }

    fn axis(&self, code: u16, invert: bool) -> u16 {
        let code = u32::from(code.min(self.galvo_max));
        let code = if invert {
            u32::from(self.galvo_max) - code
        } else {
            code
        };
        let span = u32::from(self.dac_hi.saturating_sub(self.dac_lo));
        let max = u32::from(self.galvo_max.max(1));
        // Rounded to nearest; `code ≤ max` so the result stays within `dac_lo..=dac_hi`.
        let scaled = (code * span + max / 2) / max;
        u16::try_from(u32::from(self.dac_lo) + scaled).unwrap_or(self.dac_hi)
    }

    /// DAC codes for channels (1/A, 2/B) for a protocol point (codes above `galvo_max` clamp).
    pub fn dac_codes(&self, x: u16, y: u16) -> (u16, u16) {
        let (dx, dy) = (self.axis(x, self.invert_x), self.axis(y, self.invert_y));
        if self.swap_xy { (dy, dx) } else { (dx, dy) }
    }

    /// DAC codes of the centred mirrors.
    pub fn centre(&self) -> (u16, u16) {
        self.dac_codes(self.galvo_max.div_ceil(2), self.galvo_max.div_ceil(2))
    }
}

/// AD5689R command (datasheet command table): write to input register (held until an update).
const AD5689_WRITE_INPUT: u8 = 0b0001;
/// AD5689R command: update DAC register(s) from the input register(s).
const AD5689_UPDATE: u8 = 0b0010;
/// AD5689R address bits: DAC A.
const AD5689_DAC_A: u8 = 0b0001;
/// AD5689R address bits: DAC B.
const AD5689_DAC_B: u8 = 0b1000;
/// AD5689R address bits: both channels.
const AD5689_BOTH: u8 = 0b1001;

/// The three 24-bit SPI frames (MSB first, SPI mode 1, SYNC low per frame) that set both channels
/// of an AD5689R and update them together: A and B into their input registers, then one update
/// of both, so the mirror moves along a straight line rather than an L.
pub fn ad5689_frames(a: u16, b: u16) -> [[u8; 3]; 3] {
    let frame = |command: u8, address: u8, data: u16| {
        let [hi, lo] = data.to_be_bytes();
        [(command << 4) | address, hi, lo]
    };
    [
        frame(AD5689_WRITE_INPUT, AD5689_DAC_A, a),
        frame(AD5689_WRITE_INPUT, AD5689_DAC_B, b),
        frame(AD5689_UPDATE, AD5689_BOTH, 0),
    ]
}

/// Whether the STM32's internal DAC drives PA4/PA5 on this output path: only on its own. On the
/// external path the pins stay undriven (PA5 also carries the Nucleo's LED, and they may be wired
/// to something else).
pub const fn internal_dac_live(output: GalvoOutput) -> bool {
    matches!(output, GalvoOutput::InternalDac12)
}
