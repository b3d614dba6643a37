//! The board's step timer bookkeeping (`src/bin/board/pulse_train.rs`) against a tick-exact model
//! of TIM2 (84 MHz, PWM mode 2, preloaded ARR/CCR, update interrupt with latency), fed by the
//! core's own planner (`subsurf_firmware::planner`) exactly as the rig task feeds it: woken at the
//! planner's refill times, late by a random latency, handing over the compressed segments for the
//! next 10 ms.
//!
//! What it proves without hardware: up to 50 kHz every STEP rising edge lands exactly (0 ticks) on
//! the planned segment's step time, which is within the planner's stated error of the profile's
//! ideal time (never late, at most `MAX_STEP_ERROR_US` early); DIR is settled before every edge;
//! every pulse is as wide as configured; the pulse count equals the step count; the interrupt
//! runs once per period and the feeding task a few hundred times a second, not once per step; the
//! timer stops after the last step; a feeder late by more than the planning horizon (the timer ran
//! dry mid-motion) and a reversal that leaves DIR too little set-up time are reported as stalls.

#[path = "../src/bin/board/pulse_train.rs"]
#[allow(dead_code)]
mod pulse_train;

use proptest::prelude::*;
use pulse_train::*;
use subsurf_firmware::hal::StepSegment;
use subsurf_firmware::planner::StepPlanner;
use subsurf_firmware::profile::Profile;
use subsurf_firmware::stepcompress::MAX_STEP_ERROR_US;

const T: u64 = TICKS_PER_US as u64;

/// TIM2 as the board configures it.
#[derive(Default)]
struct Tim {
    cen: bool,
    cnt: u32,
    arr: u32,
    ccr: u32,
    arr_pre: u32,
    ccr_pre: u32,
    uif: bool,
    out: bool,
    dir: bool,
    /// Update events counted by the board's TIM4 (clocked by TIM2's update TRGO): free-running
    /// across starts, as on the chip, and counting the start's own update generation too (the
    /// baseline must not care whether the chip does).
    updates: u16,
}

/// The model as the interrupt sees it.
struct Regs<'a>(&'a mut Tim);

impl StepTimer for Regs<'_> {
    fn take_update(&mut self) -> bool {
        std::mem::take(&mut self.0.uif)
    }
    fn set_dir(&mut self, forward: bool) {
        self.0.dir = forward;
    }
    fn preload(&mut self, p: Preload) {
        (self.0.arr_pre, self.0.ccr_pre) = (p.arr, p.ccr);
    }
    fn stop(&mut self) {
        self.0.cen = false;
        self.0.out = false;
    }
    fn updates(&mut self) -> u16 {
        self.0.updates
    }
}

impl StartTimer for Regs<'_> {
    fn load(&mut self, dir: bool, first: Preload, next: Preload) {
        let t = &mut *self.0;
        t.dir = dir;
        (t.arr, t.ccr) = (first.arr, first.ccr);
        (t.arr_pre, t.ccr_pre) = (next.arr, next.ccr);
        t.cnt = 0;
        t.out = false;
        // The update generation (UG) loads the preloads and may clock TIM4 once.
        t.updates = t.updates.wrapping_add(1);
    }
    fn run(&mut self) {
        self.0.cen = true;
    }
}

#[derive(Debug, Default)]
struct Run {
    /// (tick, DIR level) of every STEP rising edge.
    edges: Vec<(u64, bool)>,
    /// High time of every pulse, ticks.
    widths: Vec<u64>,
    /// Every step of every segment queued, with its direction, in order (ticks).
    planned: Vec<(u64, bool)>,
    /// Steps counted by the interrupt.
    counted: u64,
    /// Interrupts run.
    interrupts: u64,
    /// Tick at which the timer stopped for good.
    stopped_at: Option<u64>,
    /// Steps that could not be placed on schedule.
    stalls: u32,
    /// Interrupts that came after the following update event (the train stopped).
    overruns: u32,
    /// Times the feeding task woke with something to queue.
    wakes: u64,
    /// Segments queued.
    segments: u64,
    /// When each motion started, µs.
    starts: Vec<u64>,
    /// Tick of every update event (counter wrap).
    wraps: Vec<u64>,
    /// Tick at which every interrupt ran.
    isr_runs: Vec<u64>,
}

/// One motion: the profile's steps from `start_us` (or when the one before has ended, if that
/// is later), in one direction.
struct MotionSpec {
    start_us: u64,
    steps: u32,
    speed: u32,
    accel: u32,
    forward: bool,
}

/// Run `motions` (one after the other, each starting when the last one's steps are out) through
/// the planner and the train. The task wakes at the planner's refill times plus `latency(wake)`
/// µs; the interrupt runs `isr_latency(tick)` ticks after its event.
fn simulate(
    motions: &[MotionSpec],
    pulse_us: u32,
    dir_setup_us: u32,
    latency: &dyn Fn(u64) -> u64,
    isr_latency: &dyn Fn(u64) -> u64,
) -> Run {
    let mut train = PulseTrain::new();
    assert!(train.set_timing(pulse_us, dir_setup_us));
    let mut planner = StepPlanner::new(TICKS_PER_US, MIN_PERIOD_US.max(2 * pulse_us));
    let mut tim = Tim::default();
    let mut run = Run::default();
    let mut isr_at: Option<u64> = None;
    let mut rose_at = 0u64;
    let mut motion = 0usize;
    // Profile index of the next ideal step of the current motion.
    let mut next_index = 1u32;
    let mut wake_at = motions.first().map_or(0, |m| m.start_us) * T;
    run.starts.extend(motions.first().map(|m| m.start_us));
    let end = motions.last().map_or(0, |m| m.start_us) * T + 60_000_000 * T;
    let mut t = 0u64;
    while t < end {
        // Hardware: the next event (a wrap, a rising edge), the interrupt, or the task.
        let mut next = end;
        if tim.cen {
            next = next.min(t + u64::from(tim.arr - tim.cnt.min(tim.arr)) + 1);
            if !tim.out && tim.ccr > tim.cnt && tim.ccr <= tim.arr {
                next = next.min(t + u64::from(tim.ccr - tim.cnt));
            }
        }
        if let Some(at) = isr_at {
            next = next.min(at);
        }
        if motion < motions.len() {
            next = next.min(wake_at);
        }
        if next >= end {
            break;
        }
        if tim.cen {
            let dt = u32::try_from(next - t).unwrap();
            if tim.cnt + dt > tim.arr {
                // The wrap (update event) at `next`.
                tim.cnt = 0;
                tim.arr = tim.arr_pre;
                tim.ccr = tim.ccr_pre;
                tim.uif = true;
                tim.updates = tim.updates.wrapping_add(1);
                run.wraps.push(next);
                // A pending interrupt stays pending (the NVIC holds one, UIF stays set): a later
                // wrap does not move it, so a late interrupt runs exactly as late as asked.
                if isr_at.is_none() {
                    isr_at = Some(next + isr_latency(next));
                }
            } else {
                tim.cnt += dt;
            }
            let out = tim.cnt >= tim.ccr;
            if out && !tim.out {
                run.edges.push((next, tim.dir));
                rose_at = next;
            }
            if !out && tim.out {
                run.widths.push(next - rose_at);
            }
            tim.out = out;
        }
        t = next;
        if isr_at.is_some_and(|at| at <= t) {
            isr_at = None;
            run.interrupts += 1;
            run.isr_runs.push(t);
            if let Some(u) = on_interrupt(&mut train, &mut Regs(&mut tim)) {
                run.overruns += train.take_overruns();
                run.counted += u64::from(u.stepped);
                if u.preload.is_none() {
                    run.stopped_at = Some(t);
                }
            }
        }
        // The rig task: count what is out, plan ahead, queue.
        if motion < motions.len() && t >= wake_at {
            let now_us = t / T;
            planner.take_due(now_us);
            let m = &motions[motion];
            let start = run.starts[motion];
            let profile = Profile::new(m.steps, m.speed, m.accel).unwrap();
            let mut queued = 0u64;
            let mut ideal = || {
                (next_index <= m.steps).then(|| {
                    let at = start + profile.step_time_us(next_index);
                    next_index += 1;
                    at
                })
            };
            let mut queue = |s: StepSegment| {
                for j in 0..s.count {
                    run.planned.push((s.step_at(j), s.forward));
                }
                queued += 1;
                // The board's own queue-and-start (`pulse_train::queue`).
                let was_running = train.running();
                let ok = queue(&mut train, &mut Regs(&mut tim), &s, t);
                if !was_running && train.running() {
                    run.stopped_at = None;
                }
                ok
            };
            planner.refill(now_us, m.forward, &mut ideal, &mut queue);
            run.stalls += train.take_stalls();
            run.segments += queued;
            run.wakes += u64::from(queued > 0);
            let all_planned = next_index > m.steps && planner.refill_at().is_none();
            if all_planned {
                // The next motion starts once this one's last step is out.
                motion += 1;
                next_index = 1;
                planner.clear_pending();
                let last = planner.last_due().unwrap_or(now_us);
                if let Some(n) = motions.get(motion) {
                    let start = n.start_us.max(last);
                    run.starts.push(start);
                    wake_at = start * T;
                }
            } else {
                let at = planner.refill_at().unwrap_or(now_us + 1).max(now_us + 1);
                wake_at = (at + latency(run.wakes)) * T;
            }
        }
    }
    run
}

/// The profile's ideal step times (ticks) for `motions` started at `starts`, in order.
fn ideal(motions: &[MotionSpec], starts: &[u64]) -> Vec<(u64, bool)> {
    motions
        .iter()
        .zip(starts)
        .flat_map(|(m, &start)| {
            let p = Profile::new(m.steps, m.speed, m.accel).unwrap();
            (1..=m.steps).map(move |k| ((start + p.step_time_us(k)) * T, m.forward))
        })
        .collect()
}

fn assert_exact(motions: &[MotionSpec], run: &Run, pulse_us: u32) {
    let ideal = ideal(motions, &run.starts);
    assert_eq!(run.stalls, 0, "stalled");
    assert_eq!(run.edges.len(), ideal.len(), "pulse count");
    assert_eq!(run.planned.len(), ideal.len(), "planned steps");
    assert_eq!(run.counted, ideal.len() as u64, "counted steps");
    assert!(run.stopped_at.is_some(), "timer left running");
    let err = MAX_STEP_ERROR_US * T;
    for (k, (((edge, dir), (plan, _)), (want, forward))) in
        run.edges.iter().zip(&run.planned).zip(&ideal).enumerate()
    {
        assert_eq!(
            edge, plan,
            "step {k}: edge at {edge}, planned {plan} (jitter)"
        );
        // Within the planner's error of the ideal time (+1 µs of the task's clock when a
        // motion's first segment starts the idle timer).
        assert!(
            *edge <= want + T && edge + err >= *want,
            "step {k}: edge at {edge}, ideal {want}"
        );
        assert_eq!(dir, forward, "step {k}: DIR not settled before the edge");
    }
    assert!(
        run.widths.iter().all(|&w| w == u64::from(pulse_us) * T),
        "pulse widths {:?}",
        &run.widths[..run.widths.len().min(10)]
    );
    // The interrupt runs once per period: every step, plus a blank whenever the queue ran out
    // (at a motion's end, or between the slow first steps of a ramp, each its own restart).
    assert!(run.interrupts <= 2 * run.counted + 2);
}

#[test]
fn forty_khz_move_is_exact_with_the_task_waking_every_few_ms() {
    // 12 000 steps cruising at 40 kHz; the task wakes at the planner's refill times, up to 2 ms
    // late on top; the interrupt up to 4 µs late.
    let motions = [MotionSpec {
        start_us: 5_000,
        steps: 12_000,
        speed: 40_000,
        accel: 400_000,
        forward: true,
    }];
    let run = simulate(
        &motions,
        DEFAULT_PULSE_US,
        5,
        &|k| (k * 7_919) % 2_000,
        &|t| (t % 5) * T,
    );
    assert_exact(&motions, &run, DEFAULT_PULSE_US);
    // The executor wakes about every 5 ms (0.4 s of motion), not once per step, and hands over a
    // segment or two each time.
    assert!(run.wakes < 200, "{} wakes for 12 000 steps", run.wakes);
    assert!(run.segments < 300, "{} segments", run.segments);
}

#[test]
fn fifty_khz_with_wide_opto_pulses() {
    // 8 µs pulses (slow opto-isolated inputs) still leave 50 kHz: the gap floor is 16 µs.
    let motions = [MotionSpec {
        start_us: 2_000,
        steps: 6_000,
        speed: 50_000,
        accel: 500_000,
        forward: false,
    }];
    let run = simulate(&motions, 8, 5, &|k| (k * 31) % 1_500, &|t| (t % 4) * T);
    assert_exact(&motions, &run, 8);
}

#[test]
fn moves_back_and_forth_keep_direction_and_dir_set_up() {
    let motions = [
        MotionSpec {
            start_us: 1_000,
            steps: 500,
            speed: 40_000,
            accel: 400_000,
            forward: true,
        },
        MotionSpec {
            start_us: 0,
            steps: 500,
            speed: 10_000,
            accel: 100_000,
            forward: false,
        },
        MotionSpec {
            start_us: 0,
            steps: 50,
            speed: 200,
            accel: 400,
            forward: true,
        },
    ];
    let run = simulate(&motions, DEFAULT_PULSE_US, 100, &|_| 37, &|_| 2 * T);
    assert_exact(&motions, &run, DEFAULT_PULSE_US);
}

/// An interrupt later than one period, as on a real bench. TIM2 preloads its period, so the
/// period after the missed update repeats the stale preload: a pulse nobody counts, and the
/// position (counted by time) is off without a word. The hardware's own update count (TIM4 on
/// TIM2's update) exposes it, and the train stops at once (Klipper's "Timer too close").
#[test]
fn an_interrupt_later_than_one_period_stops_the_train_and_is_reported() {
    let motions = [MotionSpec {
        start_us: 2_000,
        steps: 3_000,
        speed: 40_000,
        accel: 400_000,
        forward: true,
    }];
    // Up to 4 µs late (less than the 25 µs period at 40 kHz): no overrun, every step exact.
    let run = simulate(&motions, DEFAULT_PULSE_US, 5, &|_| 100, &|t| (t % 5) * T);
    assert_eq!(run.overruns, 0);
    assert_exact(&motions, &run, DEFAULT_PULSE_US);
    // Once, 60 µs late (more than two periods at cruise), 50 ms into the move: the train stops
    // on that interrupt and reports it; no step is emitted after it.
    let late_at = 52_000 * T;
    let once = std::cell::Cell::new(false);
    let isr_latency = |t: u64| {
        if t >= late_at && !once.replace(true) {
            60 * T
        } else {
            T
        }
    };
    let run = simulate(&motions, DEFAULT_PULSE_US, 5, &|_| 100, &isr_latency);
    // The model delivered it as late as asked.
    let late_wrap = *run.wraps.iter().find(|&&w| w >= late_at).unwrap();
    assert!(
        run.isr_runs.contains(&(late_wrap + 60 * T)),
        "the interrupt of the wrap at {late_wrap} did not run 60 µs later"
    );
    assert_eq!(run.overruns, 1, "the late interrupt was not reported");
    let stopped = run.stopped_at.expect("the timer stopped");
    assert!(
        stopped >= late_at && stopped <= late_at + 100 * T,
        "stopped at {stopped}, late at {late_at}"
    );
    assert!(run.edges.iter().all(|&(t, _)| t <= stopped));
    assert!(run.edges.len() < 3_000);
    // The same lateness without the check is silent: the hardware emitted more pulses than the
    // interrupt counted.
    let emitted_before_stop = run.edges.len() as u64;
    assert!(
        emitted_before_stop > run.counted,
        "{emitted_before_stop} pulses, {} counted: nothing was lost",
        run.counted
    );
}

/// The first interrupt after a start, late by more than the period after it: the first period
/// ran on, the timer wrapped again on the preloads the interrupt never refreshed. It is checked
/// against the baseline the start took, so it faults like any other late interrupt; without the
/// baseline it only took the count and the replayed period went unseen.
#[test]
fn a_late_first_interrupt_after_a_start_faults() {
    let motions = [
        MotionSpec {
            start_us: 2_000,
            steps: 400,
            speed: 40_000,
            accel: 400_000,
            forward: true,
        },
        // A second start (the train idle in between): its first interrupt is late too.
        MotionSpec {
            start_us: 200_000,
            steps: 400,
            speed: 40_000,
            accel: 400_000,
            forward: false,
        },
    ];
    // On time: every step exact, no overrun, at both starts.
    let run = simulate(&motions, DEFAULT_PULSE_US, 5, &|_| 100, &|_| T);
    assert_eq!(run.overruns, 0);
    assert_exact(&motions, &run, DEFAULT_PULSE_US);
    for (k, start_us) in [(0usize, 2_000u64), (1, 200_000)] {
        // The first wrap at or after this motion's start is the first period's end; its
        // interrupt comes 2 ms late (the second period, the first step's interval, is 0.93 ms).
        let start = start_us * T;
        let hit = std::cell::Cell::new(false);
        let isr_latency = |t: u64| {
            if t >= start && !hit.replace(true) {
                2_000 * T
            } else {
                T
            }
        };
        let run = simulate(&motions, DEFAULT_PULSE_US, 5, &|_| 100, &isr_latency);
        let first_wrap = *run.wraps.iter().find(|&&w| w >= start).unwrap();
        assert!(
            run.isr_runs.contains(&(first_wrap + 2_000 * T)),
            "motion {k}: the first interrupt did not run 2 ms after its wrap"
        );
        assert!(
            run.wraps
                .iter()
                .filter(|&&w| w > first_wrap && w < first_wrap + 2_000 * T)
                .count()
                >= 1,
            "motion {k}: no second wrap before the late interrupt"
        );
        assert_eq!(
            run.overruns, 1,
            "motion {k}: the late first interrupt was not reported"
        );
    }
}

#[test]
fn feeder_late_by_more_than_the_horizon_is_a_stall() {
    // At 40 kHz the task misses one wake by 30 ms: the timer runs dry mid-motion. The train
    // reports it rather than moving the motor off schedule silently.
    let motions = [MotionSpec {
        start_us: 0,
        steps: 8_000,
        speed: 40_000,
        accel: 400_000,
        forward: true,
    }];
    let run = simulate(
        &motions,
        DEFAULT_PULSE_US,
        5,
        &|k| if k == 20 { 30_000 } else { 10 },
        &|_| T,
    );
    assert!(run.stalls > 0, "a dry timer mid-motion went unreported");
}

/// A reversal queued with less than the DIR set-up before its step is a stall, not a step the
/// driver may take in the old direction.
#[test]
fn a_reversal_without_dir_set_up_is_a_stall() {
    let mut train = PulseTrain::new();
    assert!(train.set_timing(5, 100));
    let seg = |first_at, forward| StepSegment {
        first_at,
        interval: 100 * TICKS_PER_US,
        add: 0,
        count: 3,
        forward,
    };
    assert!(matches!(
        train.push(&seg(1_000 * T, true), 0),
        Push::Start { .. }
    ));
    // Same direction right after: fine.
    assert_eq!(train.push(&seg(1_250 * T, true), 500 * T), Push::Queued);
    assert_eq!(train.take_stalls(), 0);
    // Reversal 50 µs after the last step: DIR needs 100 µs (+ the pulse and the interrupt).
    assert_eq!(train.push(&seg(1_500 * T, false), 500 * T), Push::Queued);
    assert_eq!(train.take_stalls(), 1);
    // Reversal with room: fine.
    assert_eq!(train.push(&seg(2_000 * T, true), 500 * T), Push::Queued);
    assert_eq!(train.take_stalls(), 0);
}

/// A flush at any tick (home switch found, emergency halt) accounts for every queued step: each
/// was either emitted as a full pulse before the flush or reported as discarded, never both, and
/// no pulse comes after it.
#[test]
fn flush_accounts_for_every_step() {
    let seg = StepSegment {
        first_at: 3_000 * T,
        interval: 25 * TICKS_PER_US,
        add: 0,
        count: 3_000,
        forward: true,
    };
    let rise0 = seg.first_at;
    for flush_at in [
        2_000 * T,
        rise0 - 4,
        rise0,
        rise0 + 3,
        20_000 * T,
        40_000 * T + 7,
        60_003 * T,
        77_777 * T,
    ] {
        let mut train = PulseTrain::new();
        let mut tim = Tim::default();
        assert!(queue(&mut train, &mut Regs(&mut tim), &seg, 0));
        assert!(tim.cen);
        let (mut edges, mut isr_at) = (0u64, None);
        let mut t = 0u64;
        let dropped = loop {
            let mut next = flush_at;
            if tim.cen {
                next = next.min(t + u64::from(tim.arr - tim.cnt) + 1);
                if !tim.out && tim.ccr > tim.cnt && tim.ccr <= tim.arr {
                    next = next.min(t + u64::from(tim.ccr - tim.cnt));
                }
            }
            if let Some(at) = isr_at {
                next = next.min(at);
            }
            if tim.cen {
                let dt = u32::try_from(next - t).unwrap();
                if tim.cnt + dt > tim.arr {
                    tim.cnt = 0;
                    (tim.arr, tim.ccr) = (tim.arr_pre, tim.ccr_pre);
                    tim.uif = true;
                    tim.updates = tim.updates.wrapping_add(1);
                    isr_at = Some(next + 2 * T);
                } else {
                    tim.cnt += dt;
                }
                let out = tim.cnt >= tim.ccr;
                edges += u64::from(out && !tim.out);
                tim.out = out;
            }
            t = next;
            if isr_at.is_some_and(|at| at <= t) {
                isr_at = None;
                on_interrupt(&mut train, &mut Regs(&mut tim));
            }
            if t >= flush_at {
                tim.cen = false;
                break u64::from(train.flush(tim.cnt));
            }
        };
        assert_eq!(edges + dropped, 3_000, "flush at {flush_at}");
        assert!(flush_at < rise0 || edges > 0);
        assert!(!train.running());
    }
}

#[test]
fn timing_is_clamped_and_fixed_while_running() {
    let mut train = PulseTrain::new();
    assert!(train.set_timing(1, 0));
    assert_eq!(train.pulse_ticks(), PULSE_US_RANGE.start() * TICKS_PER_US);
    let seg = StepSegment {
        first_at: 500 * T,
        interval: 0,
        add: 0,
        count: 1,
        forward: true,
    };
    assert!(matches!(train.push(&seg, 0), Push::Start { .. }));
    assert!(!train.set_timing(10, 0), "changed mid-motion");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Any profile (slow starts, up to 50 kHz cruise, a reversal) is reproduced exactly as
    /// planned, whatever the task's lateness (below the planning horizon) and the interrupt's.
    #[test]
    fn fast_profiles_are_exact(
        steps in 2u32..1_500,
        speed in 2_000u32..=50_000,
        accel in 20_000u32..=800_000,
        back in 1u32..300,
        seed in 0u64..1_000,
    ) {
        let motions = [
            MotionSpec { start_us: 1_000, steps, speed, accel, forward: seed % 2 == 0 },
            MotionSpec { start_us: 0, steps: back, speed, accel, forward: seed % 2 == 1 },
        ];
        let run = simulate(
            &motions,
            DEFAULT_PULSE_US,
            5,
            &|k| (k * 2_654_435_761 + seed) % 3_000,
            &|t| ((t ^ seed) % 5) * T,
        );
        assert_exact(&motions, &run, DEFAULT_PULSE_US);
    }
}
