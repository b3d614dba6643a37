//! The board's step generator bookkeeping (`src/bin/board/pulse_train.rs`) against a tick-exact
//! model of TIM2 (PWM mode 2, preloaded ARR/CCR, update interrupt with latency) fed the core's own
//! trapezoidal profiles by a task that wakes once per batch ([`batch_wake`]), late by a random
//! latency, and pushes every step that came due meanwhile.
//!
//! What it proves without hardware: up to 50 kHz every STEP rising edge lands exactly (0 ticks of
//! jitter) at the core's scheduled time plus the constant pipeline delay, with the feeding task
//! waking once per batch of steps, not once per step (segments expanded by the interrupt); DIR is
//! settled before every edge; every pulse is as wide as configured; the pulse count equals the
//! step count; the timer stops after the last step; and a feeder late by more than the pipeline
//! (the timer ran dry mid-motion) is reported as a stall. (The real timer adds only its crystal's
//! error; the model is tick-exact.)

#[path = "../src/bin/board/pulse_train.rs"]
#[allow(dead_code)]
mod pulse_train;

use proptest::prelude::*;
use pulse_train::*;
use subsurf_firmware::profile::Profile;

const PIPELINE: u64 = 1_000;

/// TIM2 as the board configures it, one tick per µs.
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
}

#[derive(Debug)]
struct Run {
    /// (tick, DIR level) of every STEP rising edge.
    edges: Vec<(u64, bool)>,
    /// High time of every pulse, ticks.
    widths: Vec<u64>,
    /// Steps counted by the interrupt.
    counted: u64,
    /// Tick at which the timer stopped for good.
    stopped_at: Option<u64>,
    /// Steps that could not be placed on schedule.
    stalls: u32,
    /// Times the feeding task woke with steps to push.
    wakes: u64,
    /// Most segments queued at once.
    max_queued: usize,
}

/// Steps as (scheduled time µs, forward). The task wakes per [`batch_wake`] plus `latency(wake)`
/// and pushes every step scheduled by then (target = scheduled + pipeline); the update interrupt
/// runs `isr_latency(t)` ticks after its event.
fn simulate(
    steps: &[(u64, bool)],
    pulse_ticks: u32,
    latency: &dyn Fn(u64) -> u64,
    isr_latency: &dyn Fn(u64) -> u64,
) -> Run {
    let mut train = PulseTrain::new();
    assert!(train.set_pulse_ticks(pulse_ticks));
    let mut tim = Tim::default();
    let mut run = Run {
        edges: Vec::new(),
        widths: Vec::new(),
        counted: 0,
        stopped_at: None,
        stalls: 0,
        wakes: 0,
        max_queued: 0,
    };
    let mut next = 0usize;
    let mut last_wake;
    let mut wake_at = steps.first().map_or(0, |s| s.0) + latency(0);
    let mut isr_at: Option<u64> = None;
    let mut rose_at = 0u64;
    let end = steps.last().map_or(0, |s| s.0) + PIPELINE * 4 + 100_000;
    let mut t = 0u64;
    while t < end {
        // Hardware: count, wrap at ARR (update event loads the preloads), drive the output.
        if tim.cen {
            if tim.cnt >= tim.arr {
                tim.cnt = 0;
                tim.arr = tim.arr_pre;
                tim.ccr = tim.ccr_pre;
                tim.uif = true;
                isr_at = Some(t + isr_latency(t));
            } else {
                tim.cnt += 1;
            }
            let out = tim.cnt >= tim.ccr;
            if out && !tim.out {
                run.edges.push((t, tim.dir));
                rose_at = t;
            }
            if !out && tim.out {
                run.widths.push(t - rose_at);
            }
            tim.out = out;
        }
        // The update interrupt.
        if isr_at.is_some_and(|at| at <= t) {
            isr_at = None;
            tim.uif = false;
            let u = train.on_update();
            run.counted += u64::from(u.stepped);
            if let Some(d) = u.dir {
                tim.dir = d;
            }
            match u.preload {
                Some(p) => {
                    tim.arr_pre = p.arr;
                    tim.ccr_pre = p.ccr;
                }
                None => {
                    tim.cen = false;
                    tim.out = false;
                    run.stopped_at = Some(t);
                }
            }
        }
        // The rig task: a wake pushes every step whose scheduled time has come.
        if next < steps.len() && t >= wake_at {
            run.wakes += 1;
            last_wake = t;
            while next < steps.len() && steps[next].0 <= t {
                let (at, forward) = steps[next];
                match train.push(at + PIPELINE, forward, t, tim.cnt, tim.uif) {
                    Push::Queued | Push::Full => {}
                    Push::Patch(p) => {
                        tim.arr_pre = p.arr;
                        tim.ccr_pre = p.ccr;
                    }
                    Push::Start { dir, first, next } => {
                        tim.dir = dir;
                        tim.arr = first.arr;
                        tim.ccr = first.ccr;
                        tim.arr_pre = next.arr;
                        tim.ccr_pre = next.ccr;
                        tim.cnt = 0;
                        tim.out = false;
                        tim.cen = true;
                        run.stopped_at = None;
                    }
                }
                next += 1;
            }
            run.max_queued = run.max_queued.max(train.queued_segments());
            run.stalls += train.take_stalls();
            if let Some(&(due, _)) = steps.get(next) {
                wake_at = batch_wake(due, true, last_wake) + latency(run.wakes);
            }
        }
        t += 1;
    }
    run
}

/// The core's schedule for one move starting at `start`.
fn schedule(start: u64, steps: u32, speed: u32, accel: u32, forward: bool) -> Vec<(u64, bool)> {
    let profile = Profile::new(steps, speed, accel).expect("valid profile");
    (1..=steps)
        .map(|k| (start + profile.step_time_us(k), forward))
        .collect()
}

fn assert_exact(steps: &[(u64, bool)], run: &Run, pulse_ticks: u32) {
    assert_eq!(run.stalls, 0, "stalled");
    assert_eq!(run.edges.len(), steps.len(), "pulse count");
    assert_eq!(run.counted, steps.len() as u64, "counted steps");
    assert!(run.stopped_at.is_some(), "timer left running");
    for (k, ((edge, dir), (at, forward))) in run.edges.iter().zip(steps).enumerate() {
        assert_eq!(
            *edge,
            at + PIPELINE,
            "step {k}: edge at {edge}, scheduled {at} + pipeline (jitter)"
        );
        assert_eq!(dir, forward, "step {k}: DIR not settled before the edge");
    }
    assert!(
        run.widths.iter().all(|&w| w == u64::from(pulse_ticks)),
        "pulse widths {:?}",
        &run.widths[..run.widths.len().min(10)]
    );
}

#[test]
fn forty_khz_move_is_exact_with_one_wake_per_batch() {
    // 12 000 steps cruising at 40 kHz; the task wakes every 400 µs, up to 500 µs late on top,
    // the interrupt up to 4 ticks late.
    let steps = schedule(5_000, 12_000, 40_000, 400_000, true);
    let run = simulate(&steps, DEFAULT_PULSE_TICKS, &|k| (k * 7919) % 500, &|t| {
        t % 5
    });
    assert_exact(&steps, &run, DEFAULT_PULSE_TICKS);
    // One executor wake per ~20 steps, not one per step.
    assert!(
        run.wakes * 10 < steps.len() as u64,
        "{} wakes for {} steps",
        run.wakes,
        steps.len()
    );
    assert!(run.max_queued < QUEUE_LEN, "queue full");
}

#[test]
fn fifty_khz_with_wide_opto_pulses() {
    // 8 µs pulses (slow opto-isolated inputs) still leave 50 kHz: the interval floor is 16 µs.
    let steps = schedule(2_000, 6_000, 50_000, 500_000, false);
    let run = simulate(&steps, 8, &|k| (k * 31) % 300, &|t| t % 4);
    assert_exact(&steps, &run, 8);
}

#[test]
fn default_pulse_is_at_least_five_us() {
    const { assert!(DEFAULT_PULSE_TICKS >= 5) };
    let steps = schedule(0, 200, 20_000, 200_000, true);
    let run = simulate(&steps, DEFAULT_PULSE_TICKS, &|_| 50, &|_| 1);
    assert_exact(&steps, &run, DEFAULT_PULSE_TICKS);
    assert_eq!(run.widths.len(), 200);
}

#[test]
fn moves_back_and_forth_keep_direction_per_step() {
    let mut steps = schedule(1_000, 500, 40_000, 400_000, true);
    let restart = steps.last().unwrap().0 + 50_000;
    steps.extend(schedule(restart, 500, 10_000, 100_000, false));
    let run = simulate(&steps, DEFAULT_PULSE_TICKS, &|_| 37, &|_| 2);
    assert_exact(&steps, &run, DEFAULT_PULSE_TICKS);
}

#[test]
fn slow_steps_from_idle_land_on_schedule_too() {
    // 200 steps/s: the timer stops between steps; each restart takes the rest of the pipeline
    // lead, so the task's varying lateness does not show in the pulses.
    let steps = schedule(0, 50, 200, 400, true);
    let run = simulate(&steps, DEFAULT_PULSE_TICKS, &|k| (k * 13) % 50, &|_| 1);
    assert_exact(&steps, &run, DEFAULT_PULSE_TICKS);
}

#[test]
fn feeder_late_by_more_than_the_pipeline_is_a_stall() {
    // At 40 kHz the task misses one wake by 3 ms: the timer runs dry mid-motion. The steps still
    // come out (none lost), but late, and the train reports it rather than staying silent.
    let steps = schedule(0, 4_000, 40_000, 400_000, true);
    let run = simulate(
        &steps,
        DEFAULT_PULSE_TICKS,
        &|k| if k == 30 { 3_000 } else { 10 },
        &|_| 1,
    );
    assert_eq!(run.edges.len(), steps.len(), "no step lost");
    assert!(run.stalls > 0, "a dry timer mid-motion went unreported");
    let late = run
        .edges
        .iter()
        .zip(&steps)
        .filter(|((edge, _), (at, _))| *edge != at + PIPELINE)
        .count();
    assert!(late > 0);
}

#[test]
fn segments_merge_only_exact_progressions() {
    let mut train = PulseTrain::new();
    // Pushed with an update pending, so no step replaces the preloaded blank period. The first
    // queued step comes after that blank (its interval is shorter), so it opens its own segment.
    let _ = train.push(1_000, true, 0, 0, false);
    assert_eq!(train.push(1_025, true, 10, 5, true), Push::Queued);
    assert_eq!(train.push(1_050, true, 10, 5, true), Push::Queued);
    let base = train.queued_segments();
    // Steps 25 apart: one new segment, then they merge.
    for k in 1..=4u64 {
        assert_eq!(train.push(1_050 + 25 * k, true, 10, 5, true), Push::Queued);
    }
    assert_eq!(train.queued_segments(), base + 1);
    // 26 breaks the progression; 27 continues it (add = 1); a reversal opens another.
    assert_eq!(train.push(1_150 + 26, true, 10, 5, true), Push::Queued);
    assert_eq!(train.queued_segments(), base + 2);
    assert_eq!(train.push(1_176 + 27, true, 10, 5, true), Push::Queued);
    assert_eq!(
        train.queued_segments(),
        base + 2,
        "26, 27: add = 1 continues"
    );
    assert_eq!(train.push(1_203 + 40, false, 10, 5, true), Push::Queued);
    assert_eq!(train.queued_segments(), base + 3);
    assert_eq!(train.take_stalls(), 0);
}

#[test]
fn pulse_width_is_clamped_and_fixed_while_running() {
    let mut train = PulseTrain::new();
    assert!(train.set_pulse_ticks(1));
    assert_eq!(train.pulse_ticks(), *PULSE_TICKS_RANGE.start());
    let _ = train.push(500, true, 0, 0, false);
    assert!(!train.set_pulse_ticks(10), "changed mid-motion");
    assert_eq!(min_interval(5), MIN_PERIOD_TICKS);
    assert_eq!(min_interval(20), 40);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]

    /// Any profile (slow starts, up to 50 kHz cruise, reversals between moves) is reproduced with
    /// zero jitter, whatever the task's lateness (batch + latency below the pipeline) and the
    /// interrupt latency.
    #[test]
    fn fast_profiles_are_exact(
        steps in 2u32..1_500,
        speed in 2_000u32..=50_000,
        accel in 20_000u32..=800_000,
        seed in 0u64..1_000,
    ) {
        let schedule = schedule(1_000, steps, speed, accel, seed % 2 == 0);
        let run = simulate(
            &schedule,
            DEFAULT_PULSE_TICKS,
            &|k| (k * 2_654_435_761 + seed) % 550,
            &|t| (t ^ seed) % 5,
        );
        assert_exact(&schedule, &run, DEFAULT_PULSE_TICKS);
    }
}
