//! The board binary's register-free layers on the host: galvo code mapping and the boot ramp
//! (`galvo_map.rs`), the hardware-timed exposure against a tick-exact one-pulse timer model
//! (`exposure.rs`), the profile's flash record log on an in-memory sector (`flash_record.rs`), and
//! the laser cut-off's register words (`safety.rs`).

#[path = "../src/bin/board/exposure.rs"]
#[allow(dead_code)]
mod exposure;
#[path = "../src/bin/board/flash_record.rs"]
#[allow(dead_code)]
mod flash_record;
#[path = "../src/bin/board/galvo_map.rs"]
#[allow(dead_code)]
mod galvo_map;
#[path = "../src/bin/board/safety.rs"]
#[allow(dead_code)]
mod safety;

use proptest::prelude::*;

mod galvo {
    use super::galvo_map::*;
    use super::*;

    /// Output voltage of the internal DAC for a code, mV.
    fn internal_mv(code: u16) -> u32 {
        (u32::from(code.min(INTERNAL_FULL)) * VDDA_MV + u32::from(INTERNAL_FULL) / 2)
            / u32::from(INTERNAL_FULL)
    }

    /// Galvo input voltage (mV) of the documented external path for a DAC code: AD5689R at gain
    /// ×2 with its 2.5 V reference (0–5 V), into `V_out = gain·(V_dac − 2.5 V)`.
    fn external_mv(code: u16, stage_gain: i32) -> i32 {
        let dac_uv = i64::from(code) * 5_000_000 / 65_536;
        let out_uv = i64::from(stage_gain) * (dac_uv - 2_500_000);
        i32::try_from(out_uv / 1_000).unwrap()
    }

    #[test]
    fn external_dac_is_bipolar_and_centred_at_0v() {
        let map = GalvoMap::for_output(GalvoOutput::ExternalSpi);
        assert!(map.is_valid());
        assert_eq!(map.galvo_max, 65_535);
        assert_eq!(map.centre(), (32_768, 32_768));
        // ±10 V stage (gain 4): code 0 → −10 V, centre → 0 V, full → +10 V − 1 LSB.
        assert_eq!(external_mv(0, 4), -10_000);
        assert_eq!(external_mv(32_768, 4), 0);
        assert_eq!(external_mv(65_535, 4), 9_999);
        // ±5 V stage (gain 2).
        assert_eq!(external_mv(0, 2), -5_000);
        assert_eq!(map.dac_codes(0, 65_535), (0, 65_535));
    }

    #[test]
    fn internal_dac_stays_in_its_linear_window() {
        let map = GalvoMap::for_output(GalvoOutput::InternalDac);
        assert!(map.is_valid());
        let (lo, hi) = map.dac_codes(0, 4095);
        // The buffered DAC swings 0.2–3.1 V, not 0–3.3 V: the ends map there, not to the rails.
        assert_eq!(internal_mv(lo), 200);
        assert_eq!(internal_mv(hi), 3_100);
        let (mid, _) = map.centre();
        assert!((internal_mv(mid) as i32 - 1_650).abs() <= 2);
        // Codes beyond galvo_max clamp instead of wrapping.
        assert_eq!(map.dac_codes(u16::MAX, 5_000), (hi, hi));
    }

    #[test]
    fn invert_and_swap_are_configuration() {
        let map = GalvoMap {
            invert_x: true,
            swap_xy: true,
            ..GalvoMap::for_output(GalvoOutput::ExternalSpi)
        };
        // X = 0 inverted → full scale, and it comes out on channel B.
        assert_eq!(map.dac_codes(0, 100), (100, 65_535));
    }

    #[test]
    fn ad5689_frames_match_the_datasheet() {
        // Write input register A (0001 0001), B (0001 1000), then update both (0010 1001).
        let f = ad5689_frames(0x1234, 0xabcd);
        assert_eq!(f[0], [0x11, 0x12, 0x34]);
        assert_eq!(f[1], [0x18, 0xab, 0xcd]);
        assert_eq!(f[2], [0x29, 0x00, 0x00]);
    }

    /// The boot sequence the board ran before: centre, then the core's first command (0, 0),
    /// as one jump. Through the slew limiter no write moves an axis by more than `max_step`.
    #[test]
    fn no_slam_at_boot() {
        let map = GalvoMap::for_output(GalvoOutput::ExternalSpi);
        let max_step = 2_048;
        let mut slew = Slew::new(map.centre(), max_step);
        let target = map.dac_codes(0, 0);
        let mut at = map.centre();
        let mut writes = 0;
        while let Some(next) = slew.next(target) {
            assert!(next.0.abs_diff(at.0) <= max_step && next.1.abs_diff(at.1) <= max_step);
            at = next;
            writes += 1;
            assert!(writes < 100, "ramp does not end");
        }
        assert_eq!(at, target);
        assert!(writes > 1, "jumped in one write");
        assert!(!slew.ramping());
        // After the ramp, ordinary commands go straight through (the core's settle model).
        assert_eq!(slew.next((65_535, 65_535)), Some((65_535, 65_535)));
        assert_eq!(slew.next((65_535, 65_535)), None);
    }

    proptest! {
        #[test]
        fn mapping_is_monotone_and_in_range(a in 0u16..=4095, b in 0u16..=4095, ext in any::<bool>()) {
            let output = if ext { GalvoOutput::ExternalSpi } else { GalvoOutput::InternalDac };
            let map = GalvoMap::for_output(output);
            let (lo, hi) = (a.min(b), a.max(b));
            let (x0, y0) = map.dac_codes(lo, lo);
            let (x1, y1) = map.dac_codes(hi, hi);
            prop_assert!(x0 <= x1 && y0 <= y1);
            prop_assert!(x0 >= map.dac_lo && x1 <= map.dac_hi);
        }
    }
}

mod timed_exposure {
    use super::exposure::*;
    use super::*;

    /// One-pulse timer: counts 0..=arr once at `tick_ns` and stops. The laser channel starts
    /// active (forced on before the start) and runs "inactive on match" at `laser_off_ccr`; the
    /// trigger runs "active on match" at `trigger_ccr` and its compare interrupt (`isr_ticks`
    /// late) switches it to "inactive on match" at `trigger_off_ccr`. Match modes keep their level
    /// after the timer stops. Returns the edges in ns: (laser off, trigger on, trigger off).
    fn run(plan: &Plan, isr_ticks: u32) -> (u64, u64, u64) {
        let mut laser = true;
        let mut laser_off = None;
        let mut trigger = (None, None);
        let mut trig_level = false;
        let mut trig_ccr = u32::from(plan.trigger_ccr);
        let mut trig_mode_on = true;
        let mut isr_at: Option<u32> = None;
        for cnt in 0..=u32::from(plan.arr) {
            let t = u64::from(cnt) * u64::from(plan.tick_ns);
            if cnt == u32::from(plan.laser_off_ccr) && laser {
                laser = false;
                laser_off = Some(t);
            }
            if cnt == trig_ccr && trig_mode_on != trig_level {
                trig_level = trig_mode_on;
                if trig_level {
                    trigger.0 = Some(t);
                    isr_at = Some(cnt + isr_ticks);
                } else {
                    trigger.1 = Some(t);
                }
            }
            if isr_at == Some(cnt) {
                isr_at = None;
                trig_mode_on = false;
                trig_ccr = u32::from(plan.trigger_off_ccr);
            }
        }
        assert!(!laser, "laser still on after the timer stopped");
        assert!(!trig_level, "trigger still active after the timer stopped");
        (
            laser_off.expect("laser off"),
            trigger.0.expect("trigger"),
            trigger.1.expect("trigger off"),
        )
    }

    /// The laser window covers the whole exposure, from the trigger edge plus the camera's
    /// latency to its end, and the trigger pulse is at least as long as asked.
    fn check(exposure_us: u32, trigger_us: u32, m: Margins) {
        let plan = plan(exposure_us, trigger_us, m).expect("plannable");
        // The compare interrupt runs a tick after the trigger edge (well within MIN_TRIGGER_US).
        let (off, trig, trig_off) = run(&plan, 1);
        let on = 0;
        let start = trig + u64::from(m.trigger_latency_us) * 1_000;
        let end = start + u64::from(exposure_us) * 1_000;
        assert!(
            on + u64::from(m.lead_us) * 1_000 <= trig + u64::from(plan.tick_ns),
            "lead"
        );
        assert!(
            off >= end + u64::from(m.tail_us) * 1_000,
            "laser off at {off} before {end}"
        );
        assert!(
            trig_off - trig >= u64::from(trigger_us) * 1_000,
            "trigger pulse short"
        );
        assert!(trig_off <= off);
        // And not wastefully long: at most two ticks and the margins beyond the exposure.
        let slack = off - on - u64::from(exposure_us) * 1_000;
        let margins = u64::from(m.lead_us + m.trigger_latency_us + m.tail_us) * 1_000;
        assert!(
            slack <= margins + 2 * u64::from(plan.tick_ns) + 1_000,
            "slack {slack}"
        );
        assert_eq!(plan.edges_us().2 * 1_000, off);
    }

    #[test]
    fn laser_window_covers_the_exposure_despite_trigger_latency() {
        check(20_000, 100, Margins::DEFAULT);
        // A slow camera (80 µs latency): the window stretches, the exposure stays covered.
        check(
            1_000,
            50,
            Margins {
                lead_us: 10,
                trigger_latency_us: 80,
                tail_us: 5,
            },
        );
    }

    #[test]
    fn long_exposures_use_a_coarser_tick_and_round_outwards() {
        check(2_000_000, 1_000, Margins::DEFAULT);
        let plan = plan(2_000_000, 1_000, Margins::DEFAULT).unwrap();
        assert!(plan.tick_ns > 1_000);
    }

    #[test]
    fn window_as_the_core_announces_it() {
        // Lead 50 µs, 100 µs trigger, laser off 20 050 µs after the edge (exposure + tail).
        let p = plan_window(50, 100, 20_050).unwrap();
        assert_eq!(p.tick_ns, 1_000);
        assert_eq!(p.edges_us(), (50, 150, 20_100));
        let (off, trig, trig_off) = run(&p, 2);
        assert_eq!((trig, trig_off, off), (50_000, 150_000, 20_100_000));
    }

    #[test]
    fn exposures_below_the_hardware_minimum_are_refused() {
        assert_eq!(
            plan(MIN_EXPOSURE_US - 1, MIN_TRIGGER_US, Margins::DEFAULT),
            Err(ExposureError::TooShort)
        );
        assert_eq!(plan(1, 1, Margins::DEFAULT), Err(ExposureError::TooShort));
        assert_eq!(
            plan(1_000, MIN_TRIGGER_US - 1, Margins::DEFAULT),
            Err(ExposureError::BadTrigger)
        );
        assert_eq!(
            plan(30_000_000, 100, Margins::DEFAULT),
            Err(ExposureError::TooLong)
        );
    }

    proptest! {
        #[test]
        fn any_exposure_is_covered(
            exposure in MIN_EXPOSURE_US..200_000,
            trigger in MIN_TRIGGER_US..500,
            lead in 0u32..200,
            latency in 0u32..200,
            tail in 0u32..200,
        ) {
            let m = Margins { lead_us: lead, trigger_latency_us: latency, tail_us: tail };
            check(exposure, trigger.min(exposure - 1), m);
        }
    }
}

mod profile_flash {
    use super::flash_record::*;
    use super::*;

    const SECTOR: usize = 4_096;

    fn write(sector: &mut [u8], payload: &[u8]) {
        let mut rec = [0u8; MAX_RECORD];
        let n = encode(payload, &mut rec).unwrap();
        let s = scan(sector);
        let at = match place(&s, n, sector.len()) {
            Ok(at) => at,
            Err(()) => {
                sector.fill(0xff);
                0
            }
        };
        // NOR flash: programming only clears bits.
        for (dst, src) in sector[at..at + n].iter_mut().zip(&rec[..n]) {
            *dst &= *src;
        }
    }

    #[test]
    fn blank_sector_has_no_profile_and_room() {
        let sector = vec![0xffu8; SECTOR];
        assert_eq!(latest_payload(&sector), None);
        assert_eq!(scan(&sector).free, Some(0));
    }

    #[test]
    fn newest_record_wins_and_wraps_by_erasing() {
        let mut sector = vec![0xffu8; SECTOR];
        for k in 0..500u32 {
            let payload = k.to_le_bytes();
            write(&mut sector, &payload);
            assert_eq!(latest_payload(&sector), Some(&payload[..]), "write {k}");
        }
    }

    #[test]
    fn torn_write_keeps_the_previous_record() {
        let mut sector = vec![0xffu8; SECTOR];
        write(&mut sector, b"first profile");
        let mut rec = [0u8; MAX_RECORD];
        let n = encode(b"second profile", &mut rec).unwrap();
        let at = scan(&sector).free.unwrap();
        // Power lost half-way through programming the second record.
        for (dst, src) in sector[at..at + n / 2].iter_mut().zip(&rec) {
            *dst &= *src;
        }
        assert_eq!(latest_payload(&sector), Some(&b"first profile"[..]));
        // The next write still lands and is read back.
        write(&mut sector, b"third");
        assert_eq!(latest_payload(&sector), Some(&b"third"[..]));
    }

    #[test]
    fn foreign_bytes_force_an_erase_not_a_misread() {
        let mut sector = vec![0xffu8; SECTOR];
        sector[..4].copy_from_slice(b"junk");
        assert_eq!(latest_payload(&sector), None);
        assert_eq!(scan(&sector).free, None);
        write(&mut sector, b"p");
        assert_eq!(latest_payload(&sector), Some(&b"p"[..]));
    }

    #[test]
    fn oversize_payload_is_refused() {
        let mut rec = [0u8; MAX_RECORD];
        assert_eq!(
            encode(&[0; MAX_PAYLOAD + 1], &mut rec),
            Err(RecordError::TooLarge)
        );
        assert_eq!(
            encode(&[0; 40], &mut [0u8; 8]),
            Err(RecordError::BufferTooSmall)
        );
    }

    proptest! {
        /// Any corruption of a stored record is caught by the CRC (never returned as a profile).
        #[test]
        fn corrupted_records_are_never_returned(payload in proptest::collection::vec(any::<u8>(), 1..200), flip in any::<usize>(), bit in 0u8..8) {
            let mut sector = vec![0xffu8; SECTOR];
            write(&mut sector, &payload);
            let n = HEADER_LEN + payload.len() + 4;
            sector[flip % n] ^= 1 << bit;
            prop_assert_ne!(latest_payload(&sector), Some(&payload[..]));
        }
    }
}

mod cut_off {
    use super::safety::*;

    #[test]
    fn unsafe_levels_cut_whichever_line_fired() {
        let pins = |estop_high, interlock_high| SafetyPins {
            estop_high,
            interlock_high,
        };
        assert_eq!(
            on_exti(pins(true, false)),
            Cut {
                lasers: true,
                stepper: true
            }
        );
        assert_eq!(
            on_exti(pins(false, true)),
            Cut {
                lasers: true,
                stepper: false
            }
        );
        assert_eq!(
            on_exti(pins(false, false)),
            Cut {
                lasers: false,
                stepper: false
            }
        );
    }

    /// The old cut-off always wrote the pin's reset bit (low): for an active-low laser driver that
    /// switched the laser ON. The inactive level follows the polarity.
    #[test]
    fn cut_off_drives_the_inactive_level_for_either_polarity() {
        assert_eq!(bsrr_inactive(8, false), 1 << 24); // BR8: low
        assert_eq!(bsrr_inactive(8, true), 1 << 8); // BS8: high = off for active-low
        assert_eq!(bsrr_inactive(9, false), 1 << 25);
    }

    #[test]
    fn cut_off_takes_the_pin_back_from_the_timer() {
        // PC6, PC8, PC9 in alternate function (timer-driven) → general-purpose output.
        let moder = moder_alternate(moder_alternate(moder_alternate(0, 6), 8), 9);
        let out = moder_output(moder_output(moder_output(moder, 6), 8), 9);
        assert_eq!(out, (0b01 << 12) | (0b01 << 16) | (0b01 << 18));
        assert_eq!(moder_output(u32::MAX, 3), !(0b10 << 6));
    }
}
