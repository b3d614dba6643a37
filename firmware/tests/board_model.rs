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
        let map = GalvoMap::for_output(GalvoOutput::ExternalDac16);
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
        let map = GalvoMap::for_output(GalvoOutput::InternalDac12);
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
            ..GalvoMap::for_output(GalvoOutput::ExternalDac16)
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

    /// Finding 10: the first galvo command used to be ramped in 1 ms steps, blocking the
    /// executor up to 32 ms (a move's steps starved meanwhile). No ramp is needed: the core's
    /// first write is the centre, which is exactly where the AD5689R powers up (RSTSEL high:
    /// mid-scale, 0x8000), so no write ever jumps from an unknown level; every command is one
    /// write.
    #[test]
    fn the_first_write_is_the_power_on_centre_so_nothing_ramps() {
        let map = GalvoMap::for_output(GalvoOutput::ExternalDac16);
        let c = GalvoOutput::ExternalDac16.center();
        assert_eq!(map.dac_codes(c, c), (0x8000, 0x8000));
        assert_eq!(map.centre(), (0x8000, 0x8000));
        let internal = GalvoMap::for_output(GalvoOutput::InternalDac12);
        let c = GalvoOutput::InternalDac12.center();
        assert_eq!(internal.dac_codes(c, c), internal.centre());
    }

    /// Finding 8: the internal DAC drove PA4/PA5 even on the external-DAC path.
    #[test]
    fn the_internal_dac_is_live_only_on_its_own_path() {
        assert!(!internal_dac_live(GalvoOutput::ExternalDac16));
        assert!(internal_dac_live(GalvoOutput::InternalDac12));
    }

    proptest! {
        #[test]
        fn mapping_is_monotone_and_in_range(a in 0u16..=4095, b in 0u16..=4095, ext in any::<bool>()) {
            let output = if ext { GalvoOutput::ExternalDac16 } else { GalvoOutput::InternalDac12 };
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

    /// Margins around one exposure, µs: the laser on `lead_us` before the trigger edge and off
    /// `trigger_latency_us + exposure + tail_us` after it.
    #[derive(Clone, Copy)]
    struct Margins {
        lead_us: u32,
        trigger_latency_us: u32,
        tail_us: u32,
    }

    impl Margins {
        const DEFAULT: Self = Self {
            lead_us: 50,
            trigger_latency_us: 20,
            tail_us: 30,
        };
    }

    fn plan(exposure_us: u32, trigger_us: u32, m: Margins) -> Result<Plan, ExposureError> {
        let after = u64::from(m.trigger_latency_us + exposure_us + m.tail_us);
        plan_window(u64::from(m.lead_us), trigger_us, exposure_us, after)
    }

    /// The two one-pulse timers, tick by tick, with no interrupt at all: TIM8's laser channel
    /// starts active (forced on before the start) and runs "inactive on match" at its compare;
    /// TIM3's trigger channel runs PWM mode 2 (active while the counter is at or above its
    /// compare). Each counter counts `0..=arr` once, then one-pulse mode stops it at 0, where a
    /// match mode keeps its level and PWM mode 2 reads inactive. Returns the edges in ns:
    /// (laser off, trigger on, trigger off), and checks both outputs are off once both stopped.
    fn run(plan: &Plan) -> (u64, u64, u64) {
        let mut laser_off = None;
        for cnt in 0..=u32::from(plan.laser.arr) {
            if cnt == u32::from(plan.laser.ccr) {
                laser_off = Some(plan.laser.at_ns(cnt));
                break;
            }
        }
        let (mut rise, mut fall) = (None, None);
        let mut level = false;
        for cnt in 0..=u32::from(plan.trigger.arr) + 1 {
            // After `arr` the counter wraps to 0 and stops.
            let c = if cnt > u32::from(plan.trigger.arr) {
                0
            } else {
                cnt
            };
            let out = c >= u32::from(plan.trigger.ccr);
            if out && !level {
                rise = Some(plan.trigger.at_ns(cnt));
            }
            if !out && level {
                fall = Some(plan.trigger.at_ns(cnt));
            }
            level = out;
        }
        assert!(!level, "trigger still active after its timer stopped");
        (
            laser_off.expect("laser off"),
            rise.expect("trigger"),
            fall.expect("trigger off"),
        )
    }

    /// The laser window covers the whole exposure, from the trigger edge plus the camera's
    /// latency to its end, and the trigger pulse is at least as long as asked, ended by its
    /// counter.
    fn check(exposure_us: u32, trigger_us: u32, m: Margins) {
        let plan = plan(exposure_us, trigger_us, m).expect("plannable");
        let (off, trig, trig_off) = run(&plan);
        let start = trig + u64::from(m.trigger_latency_us) * 1_000;
        let end = start + u64::from(exposure_us) * 1_000;
        assert!(
            u64::from(m.lead_us) * 1_000 <= trig + u64::from(plan.trigger.tick_ns),
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
        // And not wastefully long: at most two ticks of each timer beyond the margins.
        let slack = off - u64::from(exposure_us) * 1_000;
        let margins = u64::from(m.lead_us + m.trigger_latency_us + m.tail_us) * 1_000;
        let ticks = 2 * u64::from(plan.laser.tick_ns + plan.trigger.tick_ns);
        assert!(slack <= margins + ticks + 1_000, "slack {slack}");
        assert_eq!(plan.edges_ns(), (trig, trig_off, off));
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

    /// Finding 6: the trigger's falling edge needed the compare interrupt within the pulse, or
    /// it stayed high until the next capture. Now both trigger edges are TIM3's own, even for a
    /// 1 µs pulse (the old floor was 10 µs), and no interrupt runs at all.
    #[test]
    fn the_trigger_falls_by_its_counter_even_for_a_one_microsecond_pulse() {
        check(100, 1, Margins::DEFAULT);
        let p = plan(100, 1, Margins::DEFAULT).unwrap();
        let (_, rise, fall) = run(&p);
        assert_eq!(fall - rise, 1_000);
    }

    #[test]
    fn long_exposures_use_a_coarser_tick_and_round_outwards() {
        check(2_000_000, 1_000, Margins::DEFAULT);
        let plan = plan(2_000_000, 1_000, Margins::DEFAULT).unwrap();
        assert!(plan.laser.tick_ns > 1_000);
    }

    #[test]
    fn window_as_the_core_announces_it() {
        // Lead 50 µs, 100 µs trigger, laser off 20 050 µs after the edge (exposure + tail).
        let p = plan_window(50, 100, 20_000, 20_050).unwrap();
        assert_eq!(p.trigger.tick_ns, 1_000);
        assert_eq!(p.edges_ns(), (50_000, 150_000, 20_100_000));
        assert_eq!(run(&p), (20_100_000, 50_000, 150_000));
    }

    /// The core's scheduled laser-off leaves a running timer to end the window on its count; an
    /// earlier off (abort, heartbeat loss), a safety cut, or a finished timer cuts at once.
    #[test]
    fn scheduled_end_is_the_timer_s_abort_is_immediate() {
        let off = Some(20_000);
        assert_eq!(
            on_set_lasers(off, 20_000, true, true, 0),
            LaserCall::LeaveToTimer
        );
        assert_eq!(
            on_set_lasers(off, 19_999, true, true, 0),
            LaserCall::Apply(0)
        );
        assert_eq!(
            on_set_lasers(off, 20_000, true, false, 0),
            LaserCall::Apply(0)
        );
        assert_eq!(
            on_set_lasers(off, 20_000, false, true, 0),
            LaserCall::Apply(0)
        );
        assert_eq!(
            on_set_lasers(None, 20_000, true, true, 0),
            LaserCall::Apply(0)
        );
        // Light only with the safety pins permitting it.
        assert_eq!(
            on_set_lasers(None, 0, false, false, 0b1),
            LaserCall::Apply(0)
        );
        assert_eq!(
            on_set_lasers(None, 0, false, true, 0b1),
            LaserCall::Apply(1)
        );
    }

    /// Finding 6: heartbeat loss and the laser's limits were handled only by the executor (the
    /// watchdog, 500 ms later, the only backstop). TIM5 now fires a little after the core's own
    /// deadline, whatever the executor does; a deadline long past fires at once.
    #[test]
    fn the_light_s_deadline_timer_follows_the_core_s_deadline() {
        assert_eq!(lights_out_timer(None, 5), LightsOutTimer::Stop);
        assert_eq!(
            lights_out_timer(Some(2_000_000), 1_000_000),
            LightsOutTimer::FireIn {
                ticks: 1_000_000 + LIGHTS_OUT_GRACE_US as u32,
                lift: true
            }
        );
        // Long past (the executor was stuck): at once, and the cut stays.
        assert_eq!(
            lights_out_timer(Some(1_000), 9_000_000),
            LightsOutTimer::FireIn {
                ticks: 1,
                lift: false
            }
        );
        // Far ahead: clamped to the 32-bit counter.
        assert!(matches!(
            lights_out_timer(Some(u64::MAX), 0),
            LightsOutTimer::FireIn { ticks, .. } if ticks == u32::MAX - 1
        ));
    }

    #[test]
    fn exposures_below_the_hardware_minimum_are_refused() {
        assert_eq!(
            plan(MIN_EXPOSURE_US - 1, 1, Margins::DEFAULT),
            Err(ExposureError::TooShort)
        );
        assert_eq!(plan(1, 1, Margins::DEFAULT), Err(ExposureError::TooShort));
        assert_eq!(
            plan(1_000, 0, Margins::DEFAULT),
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
            exposure in MIN_EXPOSURE_US + 1..200_000,
            trigger in 1u32..500,
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

    /// Two sectors in memory and what the board does with them: `save` as `store.rs` does,
    /// counting erases; NOR flash semantics (programming only clears bits).
    struct Flash {
        sectors: [Vec<u8>; 2],
        erases: [u32; 2],
    }

    impl Flash {
        fn blank() -> Self {
            Self {
                sectors: [vec![0xff; SECTOR_LEN], vec![0xff; SECTOR_LEN]],
                erases: [0, 0],
            }
        }

        fn scans(&self) -> [Scan; 2] {
            [scan(&self.sectors[0]), scan(&self.sectors[1])]
        }

        fn latest(&self) -> Option<&[u8]> {
            latest_payload([&self.sectors[0], &self.sectors[1]])
        }

        /// Plan and encode a save; `None` if the sector to write must be erased.
        fn plan(&self, payload: &[u8]) -> (Placement, Vec<u8>) {
            let p = place(&self.scans(), record_len(payload.len()), SECTOR_LEN);
            let mut rec = [0u8; MAX_RECORD];
            let n = encode(payload, p.seq, &mut rec).unwrap();
            (p, rec[..n].to_vec())
        }

        fn program(&mut self, sector: usize, at: usize, bytes: &[u8]) {
            for (d, s) in self.sectors[sector][at..at + bytes.len()]
                .iter_mut()
                .zip(bytes)
            {
                *d &= *s;
            }
        }

        fn save(&mut self, payload: &[u8]) -> Placement {
            let (p, rec) = self.plan(payload);
            if p.erase {
                self.sectors[p.sector].fill(0xff);
                self.erases[p.sector] += 1;
            }
            self.program(p.sector, p.at, &rec);
            p
        }
    }

    #[test]
    fn blank_sectors_have_no_profile_and_room() {
        let f = Flash::blank();
        assert_eq!(f.latest(), None);
        let p = f.plan(b"x").0;
        assert_eq!((p.sector, p.at, p.seq), (0, 0, 1));
    }

    #[test]
    fn newest_record_wins_and_erases_are_rare_and_never_of_the_newest() {
        let mut f = Flash::blank();
        // A 256-byte payload: the largest record.
        for k in 0..1_000u32 {
            let mut payload = [0u8; MAX_PAYLOAD];
            payload[..4].copy_from_slice(&k.to_le_bytes());
            let newest_before = newest(&f.scans()).map(|(s, _)| s);
            let p = f.save(&payload);
            if p.erase {
                assert_ne!(
                    Some(p.sector),
                    newest_before,
                    "write {k} erased the newest record"
                );
            }
            assert_eq!(f.latest(), Some(&payload[..]), "write {k}");
        }
        // One erase per sector's worth of records, not per save.
        let erases = f.erases[0] + f.erases[1];
        assert!(
            erases <= 1_000 / (RECORDS_PER_SECTOR as u32 - 1),
            "{erases} erases for 1000 saves"
        );
    }

    #[test]
    fn a_reset_during_an_erase_keeps_the_newest_profile() {
        let mut f = Flash::blank();
        f.save(b"old");
        // Fill sector 0 so the next save erases sector 1; the erase is cut half-way (junk left).
        while !f.plan(b"newest").0.erase {
            f.save(b"newest");
        }
        let (p, _) = f.plan(b"next");
        assert_eq!(p.sector, 1);
        f.sectors[1][..64].fill(0x5a);
        assert_eq!(f.latest(), Some(&b"newest"[..]));
        // The save after the reset erases it again and lands.
        let p = f.save(b"next");
        assert!(p.erase && p.sector == 1);
        assert_eq!(f.latest(), Some(&b"next"[..]));
    }

    #[test]
    fn torn_write_keeps_the_previous_record() {
        let mut f = Flash::blank();
        f.save(b"first profile");
        let (p, rec) = f.plan(b"second profile");
        // Power lost half-way through programming the second record.
        f.program(p.sector, p.at, &rec[..rec.len() / 2]);
        assert_eq!(f.latest(), Some(&b"first profile"[..]));
        // The next write still lands (in the other sector: the torn one has no clean room) and
        // is read back.
        f.save(b"third");
        assert_eq!(f.latest(), Some(&b"third"[..]));
    }

    #[test]
    fn foreign_bytes_force_an_erase_not_a_misread() {
        let mut f = Flash::blank();
        f.sectors[0][..4].copy_from_slice(b"junk");
        f.sectors[1][..4].copy_from_slice(b"junk");
        assert_eq!(f.latest(), None);
        let p = f.save(b"p");
        assert!(p.erase);
        assert_eq!(f.latest(), Some(&b"p"[..]));
    }

    /// What the board does with a profile the host sets, and reads back after a reset: postcard
    /// into a record, the newest valid record out; a record of another format version is skipped.
    #[test]
    fn rig_profile_survives_the_record_round_trip() {
        use subsurf_protocol::{GalvoOutput, RigProfile};
        let mut profile = RigProfile::DEFAULT;
        profile.laser.active_low = true;
        profile.motor.step_pulse_us = 8;
        profile.galvo.output = GalvoOutput::InternalDac12;
        let mut buf = [0u8; MAX_PAYLOAD];
        let bytes = postcard::to_slice(&profile, &mut buf).unwrap();
        let mut f = Flash::blank();
        f.save(bytes);
        let back: RigProfile = postcard::from_bytes(f.latest().unwrap()).unwrap();
        assert_eq!(back, profile);
        assert!(back.validate().is_ok());
        // A newer firmware's record (version + 1, a higher sequence) is not misread as this
        // version's profile.
        let (p, mut rec) = f.plan(b"future");
        rec[4] = rec[4].wrapping_add(1);
        f.program(p.sector, p.at, &rec);
        assert_eq!(f.latest(), Some(bytes as &[u8]));
    }

    #[test]
    fn oversize_payload_is_refused() {
        let mut rec = [0u8; MAX_RECORD];
        assert_eq!(
            encode(&[0; MAX_PAYLOAD + 1], 1, &mut rec),
            Err(RecordError::TooLarge)
        );
        assert_eq!(
            encode(&[0; 40], 1, &mut [0u8; 8]),
            Err(RecordError::BufferTooSmall)
        );
    }

    /// Finding 2: a save blocked every interrupt for a 128 KiB sector's erase (up to 2 s) under a
    /// 500 ms watchdog, so the chip reset mid-erase, every time. Now a 16 KiB sector (≤ 500 ms)
    /// with the watchdog stretched to outlast it even on the fastest LSI.
    #[test]
    fn the_watchdog_outlasts_the_worst_erase() {
        // The board's regular watchdog: 500 ms at 32 kHz, only 340 ms on a 47 kHz LSI: even the
        // small sector's 500 ms erase would outlast it.
        let regular_ms = 500 * 32_000 / LSI_MAX_HZ;
        assert!(regular_ms < SECTOR_ERASE_MAX_MS);
        let (pr, rlr) = erase_watchdog().expect("the watchdog can wait that long");
        let shortest_ms = u64::from(rlr) * (4u64 << pr) * 1_000 / u64::from(LSI_MAX_HZ);
        assert!(shortest_ms >= u64::from(ERASE_WATCHDOG_MS));
        assert!(u64::from(worst_case_blocking_ms()) < shortest_ms);
        assert!(
            worst_case_blocking_ms() <= 510,
            "{}",
            worst_case_blocking_ms()
        );
        assert_eq!(SECTOR_LEN, 16 * 1024);
        // Beyond what the watchdog can count, no setting.
        assert_eq!(watchdog_setting(60_000), None);
    }

    proptest! {
        /// Any corruption of a stored record is caught by the CRC (never returned as a profile).
        #[test]
        fn corrupted_records_are_never_returned(payload in proptest::collection::vec(any::<u8>(), 1..200), flip in any::<usize>(), bit in 0u8..8) {
            let mut f = Flash::blank();
            f.save(&payload);
            let n = HEADER_LEN + payload.len() + 4;
            f.sectors[0][flip % n] ^= 1 << bit;
            prop_assert_ne!(f.latest(), Some(&payload[..]));
        }
    }
}

mod cut_off {
    use super::safety::*;

    fn pins(estop_high: bool, interlock_high: bool) -> SafetyPins {
        SafetyPins {
            estop_high,
            interlock_high,
        }
    }

    #[test]
    fn unsafe_levels_cut_whichever_line_fired() {
        let none = SafetyEdges::default();
        assert_eq!(
            on_exti(none, pins(true, false)),
            Cut {
                lasers: true,
                stepper: true
            }
        );
        assert_eq!(
            on_exti(none, pins(false, true)),
            Cut {
                lasers: true,
                stepper: false
            }
        );
        assert_eq!(
            on_exti(none, pins(false, false)),
            Cut {
                lasers: false,
                stepper: false
            }
        );
    }

    /// Finding 10: the interrupt acted on the level it sampled, so a press (or an opening)
    /// shorter than its latency, already released when it sampled, cut nothing. The latched edge
    /// cuts.
    #[test]
    fn a_short_press_cuts_by_its_latched_edge() {
        let released = pins(false, false);
        let press = SafetyEdges {
            estop: true,
            interlock: false,
        };
        assert_eq!(
            on_exti(press, released),
            Cut {
                lasers: true,
                stepper: true
            }
        );
        let opening = SafetyEdges {
            estop: false,
            interlock: true,
        };
        assert_eq!(
            on_exti(opening, released),
            Cut {
                lasers: true,
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
        let af = |m, p| moder_with(m, p, PinMode::Alternate);
        let out = |m, p| moder_with(m, p, PinMode::Output);
        let moder = af(af(af(0, 6), 8), 9);
        assert_eq!(
            out(out(out(moder, 6), 8), 9),
            (0b01 << 12) | (0b01 << 16) | (0b01 << 18)
        );
        assert_eq!(out(u32::MAX, 3), !(0b10 << 6));
        assert_eq!(moder_with(u32::MAX, 3, PinMode::Input), !(0b11 << 6));
    }

    /// A GPIO pin and what a laser driver wired to it sees: driven by ODR in output mode,
    /// high-impedance as an input (the wiring's resistor then pulls it to the driver's off level),
    /// the timer's level in alternate-function mode (here: the timer's idle output, inactive).
    struct Pin {
        moder: u32,
        odr_high: bool,
    }

    const PIN: u8 = 6;

    impl Pin {
        fn at_reset() -> Self {
            Self {
                moder: 0,
                odr_high: false,
            }
        }
        fn bsrr(&mut self, word: u32) {
            if word & (1 << PIN) != 0 {
                self.odr_high = true;
            }
            if word & (1 << (PIN + 16)) != 0 {
                self.odr_high = false;
            }
        }
        /// Whether the driver (active low or high) sees "on".
        fn on(&self, wired_active_low: bool) -> bool {
            match (self.moder >> (2 * PIN)) & 0b11 {
                // Input: the external resistor holds the off level.
                0b00 => false,
                0b01 => self.odr_high != wired_active_low,
                _ => false,
            }
        }
        fn apply(&mut self, park: Park, wired_active_low: bool, steps: &mut Vec<bool>) {
            if let Some(word) = park.bsrr {
                self.bsrr(word);
                steps.push(self.on(wired_active_low));
            }
            self.moder = moder_with(self.moder, PIN, park.mode);
            steps.push(self.on(wired_active_low));
        }
    }

    /// Finding 1: from reset until the profile is known, and at every fault after, a laser pin is
    /// never on, whichever polarity the driver is wired with: high-impedance while unknown, then
    /// parked at the known profile's inactive level (data register before mode).
    #[test]
    fn laser_pins_are_off_from_reset_for_either_polarity() {
        for wired_active_low in [false, true] {
            let mut pin = Pin::at_reset();
            let mut seen = vec![pin.on(wired_active_low)];
            // Boot with nothing stored: parked (a fault path, or `configure` never called).
            pin.apply(park(PIN, Polarity::Unknown), wired_active_low, &mut seen);
            // The stored (right) profile is read: parked at its inactive level.
            pin.apply(
                park(PIN, Polarity::from_active_low(wired_active_low)),
                wired_active_low,
                &mut seen,
            );
            // A fault path parks again.
            pin.apply(
                park(PIN, Polarity::from_active_low(wired_active_low)),
                wired_active_low,
                &mut seen,
            );
            assert!(
                seen.iter().all(|on| !on),
                "wired active-{}: {seen:?}",
                if wired_active_low { "low" } else { "high" }
            );
        }
    }

    /// What the old boot did, in the same model: parked at the *default* polarity (active high:
    /// drive low) before the stored profile was read. For an active-low driver that is "on" until
    /// the profile is applied: light at every boot.
    #[test]
    fn the_old_boot_order_lit_active_low_lasers() {
        let mut pin = Pin::at_reset();
        let mut seen = Vec::new();
        pin.apply(park(PIN, Polarity::ActiveHigh), true, &mut seen);
        assert!(seen.iter().any(|&on| on), "{seen:?}");
    }
}

/// Finding 10: embassy's EXTI handler masked every line it found pending until a task waited on
/// it again; an exposure-active edge between the board's handler and embassy's masked line 6 for
/// the rest of the boot. The board now binds its own handler alone on every EXTI vector it uses.
#[test]
fn no_exti_vector_runs_embassy_s_masking_handler() {
    let main = include_str!("../src/bin/board/main.rs");
    assert!(
        !main.contains("exti::InterruptHandler"),
        "embassy's EXTI handler is bound again"
    );
    for vector in ["EXTI4", "EXTI9_5", "EXTI15_10"] {
        assert!(
            main.contains(&format!("{vector} => inputs::Exti<")),
            "{vector} is not the board's handler"
        );
    }
}
