//! The board binary's register-free layers on the host: galvo code mapping and the boot ramp
//! (`galvo_map.rs`), the hardware-timed exposure against a tick-exact one-pulse timer model
//! (`exposure.rs`), the profile's flash record log, its save and read-back on in-memory sectors
//! with a data cache (`flash_record.rs`), the laser cut-off's register words (`safety.rs`), and
//! the pins' connect and cut (`gate.rs`) on a model of GPIOC, the safety inputs and the
//! interrupts, which fire between any two register accesses of the shipped code.

#[path = "../src/bin/board/exposure.rs"]
#[allow(dead_code)]
mod exposure;
#[path = "../src/bin/board/flash_record.rs"]
#[allow(dead_code)]
mod flash_record;
#[path = "../src/bin/board/galvo_map.rs"]
#[allow(dead_code)]
mod galvo_map;
#[path = "../src/bin/board/gate.rs"]
#[allow(dead_code)]
mod gate;
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

    /// On a real bench, `tail_us = 0` with `trigger_us = exposure_us` (a level-triggered camera,
    /// no trigger latency) fell back to software edges; it is timed by the counters.
    #[test]
    fn a_trigger_as_long_as_the_window_is_timed_in_hardware() {
        let m = Margins {
            lead_us: 50,
            trigger_latency_us: 0,
            tail_us: 0,
        };
        assert!(plan(1_000, 1_000, m).is_ok());
        check(1_000, 1_000, m);
        check(20_000, 20_000, m);
        // Longer than the window after it stays refused.
        assert_eq!(
            plan_window(50, 1_001, 1_000, 1_000),
            Err(ExposureError::BadTrigger)
        );
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
    use subsurf_protocol::RigProfile;

    /// Two sectors in memory with NOR flash semantics (programming only clears bits), the
    /// flash's data cache (after an erase it keeps serving the erased bytes until reset), and
    /// optionally a bit that will not clear; saved through the board's own `flash_record::save`.
    struct Flash {
        sectors: [Vec<u8>; 2],
        erases: [u32; 2],
        /// What the data cache still serves for a sector erased under it.
        stale: [Option<Vec<u8>>; 2],
        /// (sector, byte, bit) stuck at 1.
        stuck: Option<(usize, usize, u8)>,
    }

    impl SectorFlash for Flash {
        fn sector(&self, i: usize) -> &[u8] {
            self.stale[i].as_deref().unwrap_or(&self.sectors[i])
        }
        fn erase(&mut self, i: usize) -> Result<(), subsurf_protocol::SaveError> {
            self.stale[i] = Some(self.sectors[i].clone());
            self.sectors[i].fill(0xff);
            self.erases[i] += 1;
            Ok(())
        }
        fn program(
            &mut self,
            i: usize,
            at: usize,
            bytes: &[u8],
        ) -> Result<(), subsurf_protocol::SaveError> {
            self.program(i, at, bytes);
            Ok(())
        }
        fn reset_data_cache(&mut self) {
            self.stale = [None, None];
        }
    }

    impl Flash {
        fn blank() -> Self {
            Self {
                sectors: [vec![0xff; SECTOR_LEN], vec![0xff; SECTOR_LEN]],
                erases: [0, 0],
                stale: [None, None],
                stuck: None,
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
            for (k, (d, s)) in self.sectors[sector][at..at + bytes.len()]
                .iter_mut()
                .zip(bytes)
                .enumerate()
            {
                *d &= *s;
                if let Some((ss, byte, bit)) = self.stuck
                    && ss == sector
                    && byte == at + k
                {
                    *d |= 1 << bit;
                }
            }
        }

        /// The board's save (`flash_record::save`, as `store.rs` calls it).
        fn save(&mut self, payload: &[u8]) -> Placement {
            save(self, payload).unwrap()
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

    /// What the board does with a profile the host sets, and reads back after a reset: its
    /// layout key and postcard bytes into a record, the newest valid record out; a record of
    /// another format version is skipped.
    #[test]
    fn rig_profile_survives_the_record_round_trip() {
        use subsurf_protocol::{GalvoOutput, RigProfile};
        let mut profile = RigProfile::DEFAULT;
        profile.laser.active_low = true;
        profile.motor.step_pulse_us = 8;
        profile.galvo.output = GalvoOutput::InternalDac12;
        let mut buf = [0u8; MAX_PAYLOAD];
        let bytes = encode_profile(&profile, &mut buf).unwrap();
        let mut f = Flash::blank();
        f.save(bytes);
        let back = decode_profile(f.latest().unwrap()).unwrap();
        assert_eq!(back, profile);
        // A newer firmware's record (version + 1, a higher sequence) is not misread as this
        // version's profile.
        let (p, mut rec) = f.plan(b"future");
        rec[4] = rec[4].wrapping_add(1);
        f.program(p.sector, p.at, &rec);
        assert_eq!(f.latest(), Some(bytes as &[u8]));
    }

    /// A record of another profile layout, or with bytes after the profile, is no profile, never
    /// a misread one (its bytes in the wrong fields, a polarity among them).
    #[test]
    fn another_layout_or_trailing_bytes_read_as_no_profile() {
        use subsurf_protocol::RigProfile;
        let profile = RigProfile::DEFAULT;
        let mut buf = [0u8; MAX_PAYLOAD];
        let bytes = encode_profile(&profile, &mut buf).unwrap().to_vec();
        assert_eq!(bytes[..4], RigProfile::LAYOUT.to_le_bytes());
        assert_eq!(decode_profile(&bytes), Some(profile));
        // The same bytes under another layout key (a firmware whose RigProfile differs).
        let mut other = bytes.clone();
        other[0] ^= 1;
        assert_eq!(decode_profile(&other), None);
        // Trailing bytes: postcard's `from_bytes` accepts them, the board does not.
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(postcard::from_bytes::<RigProfile>(&longer[4..]).is_ok());
        assert_eq!(decode_profile(&longer), None);
        // A record of the old format (version 2: postcard bytes with no key) is skipped whole.
        let mut f = Flash::blank();
        let old = postcard::to_slice(&profile, &mut buf).unwrap().to_vec();
        let (p, mut rec) = f.plan(&old);
        rec[4..6].copy_from_slice(&2u16.to_le_bytes());
        let body = HEADER_LEN + old.len();
        let crc = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(&rec[..body]);
        rec[body..body + 4].copy_from_slice(&crc.to_le_bytes());
        f.program(p.sector, p.at, &rec);
        assert_eq!(
            scan(&f.sectors[p.sector]).latest,
            None,
            "a version-2 record read"
        );
        assert_eq!(f.latest(), None);
        // The same record with this version's number would have been read (the CRC is right).
        rec[4..6].copy_from_slice(&RECORD_VERSION.to_le_bytes());
        let crc = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC).checksum(&rec[..body]);
        rec[body..body + 4].copy_from_slice(&crc.to_le_bytes());
        let mut g = Flash::blank();
        g.program(p.sector, p.at, &rec);
        assert_eq!(g.latest(), Some(&old[..]));
        assert_eq!(decode_profile(&old), None, "no key: not a profile");
        // Shorter than a key, or a valid key over an invalid profile.
        assert_eq!(decode_profile(&bytes[..3]), None);
        let mut bad = profile;
        bad.laser.channels = 0;
        let mut buf = [0u8; MAX_PAYLOAD];
        let bad = encode_profile(&bad, &mut buf).unwrap();
        assert_eq!(decode_profile(bad), None);
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

    fn profile(k: u32) -> RigProfile {
        let mut p = RigProfile::DEFAULT;
        p.motor.max_speed = 10_000 + k;
        assert!(p.validate().is_ok());
        p
    }

    /// A record that reads back otherwise than it was written (here a bit that will not clear
    /// in the new record's place) refuses the save: `Err(Verify)`, and the profile in flash
    /// is still the old one.
    #[test]
    fn a_read_back_mismatch_refuses_the_save() {
        let mut f = Flash::blank();
        assert_eq!(store_profile(&mut f, &profile(1)), Ok(()));
        assert_eq!(load_profile(&f), Some(profile(1)));
        // The next record goes right after the first; a bit of its payload sticks at 1.
        let next = f.plan(&[0u8; 40]).0;
        f.stuck = Some((next.sector, next.at + HEADER_LEN + 6, 0));
        assert_eq!(
            store_profile(&mut f, &profile(2)),
            Err(subsurf_protocol::SaveError::Verify)
        );
        assert_eq!(load_profile(&f), Some(profile(1)));
        // A profile flash already holds is acknowledged without a write.
        f.stuck = None;
        assert_eq!(store_profile(&mut f, &profile(1)), Ok(()));
    }

    /// Saves through several erases of sectors that held records: each save after an erase
    /// reads back the new profile, because the save resets the data cache after the erase (it
    /// would otherwise verify the erased sector's cached old records and refuse).
    #[test]
    fn every_save_after_an_erase_reads_back_through_a_reset_cache() {
        let mut f = Flash::blank();
        for k in 0..1_000u32 {
            let p = profile(k % 2);
            assert_eq!(store_profile(&mut f, &p), Ok(()), "save {k}");
            assert_eq!(load_profile(&f), Some(p), "save {k}");
        }
        assert!(
            f.erases[0] >= 1 && f.erases[1] >= 2,
            "{:?}: no erase of a sector that held records",
            f.erases
        );
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

    #[test]
    fn the_cut_off_is_one_moder_write_to_input_whatever_the_pin_did() {
        // PC6, PC8, PC9 in alternate function (timer-driven) or output → input, others kept.
        let af = |m, p| moder_with(m, p, PinMode::Alternate);
        // PC6 a general-purpose output (0b01), PC0 too.
        let moder = af(af((0b01 << 12) | 0b01, 8), 9);
        assert_eq!(park(park(park(moder, 6), 8), 9), 0b01);
        assert_eq!(park(u32::MAX, 3), !(0b11 << 6));
        assert_eq!(PARKED, PinMode::Input);
    }

    /// A laser enable line as the documented wiring makes it: the board's pin (MODER, OTYPER, the
    /// output data register, the timer channel's output in alternate-function mode) and the
    /// wiring's resistor, which pulls the line to the driver's off level when nothing drives it.
    /// A push-pull pin drives both levels; an open-drain pin only pulls low.
    #[derive(Clone, Copy)]
    struct Line {
        moder: u32,
        otype: OutputType,
        odr_high: bool,
        /// The timer channel's output level (after its polarity bit).
        timer_high: bool,
        /// How the laser driver is wired (its resistor holds the opposite level).
        wired_active_low: bool,
    }

    const PIN: u8 = 6;

    impl Line {
        fn at_reset(wired_active_low: bool) -> Self {
            Self {
                moder: 0,
                otype: OutputType::PushPull,
                odr_high: false,
                timer_high: false,
                wired_active_low,
            }
        }
        fn mode(&self) -> u32 {
            (self.moder >> (2 * PIN)) & 0b11
        }
        /// The line's level: the pin's output where it drives, else the resistor's.
        fn high(&self) -> bool {
            let resistor_high = self.wired_active_low;
            let out = match self.mode() {
                0b01 => Some(self.odr_high),
                0b10 => Some(self.timer_high),
                _ => None,
            };
            match (out, self.otype) {
                (None, _) => resistor_high,
                (Some(level), OutputType::PushPull) => level,
                (Some(false), OutputType::OpenDrain) => false,
                (Some(true), OutputType::OpenDrain) => resistor_high,
            }
        }
        /// Whether the driver emits.
        fn on(&self) -> bool {
            self.high() != self.wired_active_low
        }
    }

    /// What the board does to one laser pin over a boot and one timed window, per its stored
    /// polarity (`outputs.rs`, as `safety.rs` decides it), with every line level it goes through.
    /// Returns (line "on" outside the window, line "on" inside it).
    fn boot_and_window(stored_active_low: bool, wired_active_low: bool) -> (Vec<bool>, Vec<bool>) {
        let polarity = Polarity::from_active_low(stored_active_low);
        let mut line = Line::at_reset(wired_active_low);
        let mut outside = vec![line.on()];
        // Boot: the profile is read; the pins are parked and their output stage chosen.
        line.moder = park(line.moder, PIN);
        line.otype = output_type(polarity).expect("known polarity");
        outside.push(line.on());
        // The timer channel idles inactive (its polarity bit applied).
        line.timer_high = stored_active_low;
        // Arming and every connection read the parked line first.
        let idle_ok = idles_off(polarity, line.high());
        let mut inside = Vec::new();
        if idle_ok {
            // The window: forced active, connected, "inactive on match" at the end.
            line.timer_high = !stored_active_low;
            line.moder = moder_with(line.moder, PIN, PinMode::Alternate);
            inside.push(line.on());
            line.timer_high = stored_active_low;
            inside.push(line.on());
        }
        // The timers stopped: parked (as every fault path does, at any moment).
        line.moder = park(line.moder, PIN);
        outside.push(line.on());
        // A fault path in the middle of a window parks the same way: nothing to know.
        if idle_ok {
            line.timer_high = !stored_active_low;
            line.moder = moder_with(line.moder, PIN, PinMode::Alternate);
            inside.push(line.on());
            line.moder = park(line.moder, PIN);
            outside.push(line.on());
        }
        (outside, inside)
    }

    /// A stored polarity that is not the wiring's (as on a real bench) gives no light at all,
    /// neither at boot, nor in a window, nor at any fault; the right one gives light only inside
    /// its window.
    #[test]
    fn a_wrong_polarity_gives_no_light() {
        for stored in [false, true] {
            for wired in [false, true] {
                let (outside, inside) = boot_and_window(stored, wired);
                assert!(
                    outside.iter().all(|on| !on),
                    "stored active-low {stored}, wired {wired}: light outside a window {outside:?}"
                );
                if stored == wired {
                    assert_eq!(inside.first(), Some(&true), "no light in the window");
                } else {
                    assert!(
                        inside.iter().all(|on| !on),
                        "stored active-low {stored}, wired {wired}: light {inside:?}"
                    );
                }
            }
        }
    }

    /// The idle check is what stops the push-pull case: without it an "active high" profile on an
    /// active-low driver lights the laser at the window's end, when the timer drives low.
    #[test]
    fn without_the_idle_check_an_active_high_profile_lights_an_active_low_driver() {
        let mut line = Line::at_reset(true);
        assert!(!idles_off(Polarity::ActiveHigh, line.high()));
        line.otype = output_type(Polarity::ActiveHigh).unwrap();
        line.moder = moder_with(line.moder, PIN, PinMode::Alternate);
        line.timer_high = false;
        assert!(line.on());
        // Open-drain cannot drive the off level of an active-low line, so an "active low"
        // profile on an active-high driver stays dark even unchecked.
        let mut line = Line::at_reset(false);
        line.otype = output_type(Polarity::ActiveLow).unwrap();
        line.moder = moder_with(line.moder, PIN, PinMode::Alternate);
        for timer_high in [false, true] {
            line.timer_high = timer_high;
            assert!(!line.on());
        }
    }

    /// From reset until the profile is known, and at every fault after, a laser pin is never on,
    /// whichever polarity the driver is wired with, and none is known (at the board's first
    /// power-on, active-low lasers lit at every boot).
    #[test]
    fn laser_pins_are_off_from_reset_with_no_profile() {
        for wired_active_low in [false, true] {
            let mut line = Line::at_reset(wired_active_low);
            assert!(!line.on());
            line.moder = park(line.moder, PIN);
            assert!(!line.on());
            assert_eq!(output_type(Polarity::Unknown), None);
            assert!(!idles_off(Polarity::Unknown, line.high()));
        }
    }

    /// What the old cut-off did, in the same model: it drove the *stored* off level, push-pull.
    /// With the wrong polarity stored that is "on": the light a real bench showed.
    #[test]
    fn the_old_cut_off_lit_a_wrongly_stored_polarity() {
        let mut line = Line::at_reset(true);
        // Stored active high: "off" = drive low.
        line.odr_high = false;
        line.moder = 0b01 << (2 * PIN);
        assert!(line.on());
    }
}

/// EN follows the e-stop's fault, not its contact: released at a press, energised again only
/// once the core's `Fault::EmergencyStop` is cleared (`ClearFault`), never by the release alone.
#[test]
fn the_motor_is_energised_again_only_after_clear_fault() {
    use safety::enable_allowed;
    use subsurf_protocol::Fault;
    assert!(enable_allowed(true, false, None));
    assert!(
        !enable_allowed(false, false, None),
        "no profile: EN not driven"
    );
    assert!(
        !enable_allowed(true, true, Some(Fault::EmergencyStop)),
        "pressed"
    );
    assert!(
        !enable_allowed(true, false, Some(Fault::EmergencyStop)),
        "released but not cleared"
    );
    // Other faults keep the holding torque (the position is kept, the motion stopped).
    assert!(enable_allowed(true, false, Some(Fault::StepStall)));
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

/// The laser pins' connect against an e-stop edge or the deadline timer's window end landing
/// between any two of its register accesses: `gate.rs` as the board runs it, on a model of
/// GPIOC's MODER and IDR, GPIOB's safety pins, the latched flags, and the interrupt mask.
mod connect_race {
    use super::gate::*;
    use super::safety::*;

    /// What fires, and when: before register access number `at` (counted from 0 over the whole
    /// run) if interrupts are unmasked then, else as soon as they are unmasked again.
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    enum Event {
        /// The e-stop opens: PB5 reads high and its EXTI line's rising edge is pending.
        EstopEdge,
        /// The light's deadline timer (TIM5) reaches its update.
        WindowEnd,
    }

    #[derive(Debug)]
    struct Model {
        moder: u32,
        idr: u32,
        estop_high: bool,
        interlock_high: bool,
        latched: Latched,
        masked: u32,
        accesses: usize,
        fire: Option<(usize, Event)>,
        pending: Option<Event>,
        fired: Option<Event>,
        exposure_timers_running: bool,
        steps_running: bool,
    }

    impl Model {
        /// Lasers wired active high (each resistor pulls its line low: idles off), all parked,
        /// inputs safe.
        fn armed(fire: Option<(usize, Event)>) -> Self {
            Self {
                moder: 0,
                idr: 0,
                estop_high: false,
                interlock_high: false,
                latched: Latched::default(),
                masked: 0,
                accesses: 0,
                fire,
                pending: None,
                fired: None,
                exposure_timers_running: true,
                steps_running: true,
            }
        }

        /// One register access: the scheduled interrupt comes first if its time has come.
        fn access(&mut self) {
            if let Some((at, event)) = self.fire
                && self.accesses >= at
            {
                self.fire = None;
                self.pending = Some(event);
            }
            self.accesses += 1;
            self.deliver();
        }

        fn deliver(&mut self) {
            if self.masked == 0
                && let Some(event) = self.pending.take()
            {
                self.fired = Some(event);
                // The handler's own accesses do not count as scheduled points.
                let fire = self.fire.take();
                match event {
                    Event::EstopEdge => {
                        self.estop_high = true;
                        on_safety_interrupt(
                            self,
                            SafetyEdges {
                                estop: true,
                                interlock: false,
                            },
                        );
                    }
                    Event::WindowEnd => on_lights_out(self),
                }
                self.fire = fire;
            }
        }

        /// Whether laser channel `i`'s pin is connected to its timer (driven: on).
        fn lit(&self, i: usize) -> bool {
            connected(self.moder, LASER_PIN_NUMBERS[i])
        }
    }

    impl LightRegs for Model {
        fn moder(&mut self) -> u32 {
            self.access();
            self.moder
        }
        fn set_moder(&mut self, moder: u32) {
            self.access();
            self.moder = moder;
        }
        fn idr(&mut self) -> u32 {
            self.access();
            self.idr
        }
        fn safety_pins(&mut self) -> SafetyPins {
            self.access();
            SafetyPins {
                estop_high: self.estop_high,
                interlock_high: self.interlock_high,
            }
        }
        fn latched(&mut self) -> Latched {
            self.access();
            self.latched
        }
        fn latch(&mut self, edges: SafetyEdges) {
            self.latched.edges.estop |= edges.estop;
            self.latched.edges.interlock |= edges.interlock;
        }
        fn cut_light(&mut self) {
            self.latched.lights_out = true;
        }
        fn stop_exposure_timers(&mut self) {
            self.exposure_timers_running = false;
        }
        fn stop_steps(&mut self) {
            self.steps_running = false;
        }
        fn masked<R>(&mut self, f: impl FnOnce(&mut Self) -> R) -> R {
            self.masked += 1;
            let r = f(self);
            self.masked -= 1;
            self.deliver();
            r
        }
    }

    /// The rig task's sequence for `laser on` (channels R and B) once its own check passed: the
    /// connect of `outputs.rs`, through the seam.
    fn switch_on(m: &mut Model) -> Connected {
        connect(m, 0b101, false, Polarity::ActiveHigh)
    }

    /// Accesses the connect makes with nothing firing.
    fn accesses_of_a_connect() -> usize {
        let mut m = Model::armed(None);
        let done = switch_on(&mut m);
        assert_eq!(done.lasers, 0b101, "the connect did not connect: {done:?}");
        assert!(m.lit(0) && m.lit(2) && !m.lit(1));
        m.accesses
    }

    /// An e-stop edge at every point of the connect (before its first access through after its
    /// last): the laser ends dark every time, and the stepper stopped.
    #[test]
    fn an_estop_edge_anywhere_in_the_connect_leaves_the_laser_dark() {
        let n = accesses_of_a_connect();
        for at in 0..=n {
            let mut m = Model::armed(Some((at, Event::EstopEdge)));
            let done = switch_on(&mut m);
            if m.fired.is_none() {
                // Scheduled after the last access: the edge comes after the call.
                m.pending = Some(Event::EstopEdge);
                m.deliver();
            }
            assert_eq!(m.fired, Some(Event::EstopEdge));
            for i in 0..3 {
                assert!(
                    !m.lit(i),
                    "e-stop edge before access {at} of {n}: laser {i} lit (MODER {:#010x}, {done:?})",
                    m.moder
                );
            }
            // And the next connect is refused while the edge is latched.
            let again = switch_on(&mut m);
            assert!(again.refused && !m.lit(0) && !m.lit(2));
        }
    }

    /// The same for the deadline timer's window end.
    #[test]
    fn a_window_end_anywhere_in_the_connect_leaves_the_laser_dark() {
        let n = accesses_of_a_connect();
        for at in 0..=n {
            let mut m = Model::armed(Some((at, Event::WindowEnd)));
            let _ = switch_on(&mut m);
            if m.fired.is_none() {
                m.pending = Some(Event::WindowEnd);
                m.deliver();
            }
            assert!(
                !m.lit(0) && !m.lit(2),
                "window end before access {at} of {n}: lit (MODER {:#010x})",
                m.moder
            );
            assert!(!m.exposure_timers_running);
            assert!(switch_on(&mut m).refused);
        }
    }

    /// An e-stop that is open (or was pressed and bounced back, its edge latched) at the connect
    /// refuses it, though the caller's own earlier check passed: re-read inside.
    #[test]
    fn the_connect_re_reads_the_inputs_and_the_latched_edges() {
        let mut m = Model::armed(None);
        m.estop_high = true;
        assert!(switch_on(&mut m).refused);
        let mut m = Model::armed(None);
        m.latched.edges.estop = true;
        assert!(switch_on(&mut m).refused);
        let mut m = Model::armed(None);
        m.interlock_high = true;
        assert!(switch_on(&mut m).refused);
        assert_eq!(m.moder, 0);
        // A line that idles at the level the profile calls on (a pull-up under "active high")
        // is not driven; the others are.
        let mut m = Model::armed(None);
        m.idr = 1 << LASER_PIN_NUMBERS[2];
        let done = switch_on(&mut m);
        assert_eq!(done.lasers, 0b001);
        assert!(m.lit(0) && !m.lit(2));
    }

    /// Every fault path's park takes the four pins, nothing else.
    #[test]
    fn park_all_parks_exactly_the_light_pins() {
        let mut m = Model::armed(None);
        m.moder = u32::MAX;
        park_all(&mut m);
        let light = [6u32, 7, 8, 9]
            .iter()
            .fold(0u32, |acc, &p| acc | (0b11 << (2 * p)));
        assert_eq!(m.moder, !light);
        assert_eq!(parked_all(u32::MAX), !light);
    }
}
