//! The board's step generator bookkeeping (`src/bin/board/pulse_train.rs`) against a tick-exact
//! model of TIM2 (PWM mode 2, preloaded ARR/CCR, update interrupt with latency) fed the core's own
//! trapezoidal profiles by a task that pushes each step late by a random latency.
//!
//! What it proves without hardware: up to 20 kHz every STEP rising edge lands exactly (0 ticks of
//! jitter) at the core's scheduled time plus one constant pipeline delay, however late (within the
//! pipeline) the task pushes the step; DIR is settled before every edge; the pulse count equals
//! the step count; and the timer stops after the last step. (The real timer adds only its crystal's
//! error; the model is tick-exact.)

#[path = "../src/bin/board/pulse_train.rs"]
#[allow(dead_code)]
mod pulse_train;

use proptest::prelude::*;
use pulse_train::*;
use subsurf_firmware::profile::Profile;

const PIPELINE: u32 = 1_000;

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

struct Run {
    /// (tick, DIR level) of every STEP rising edge.
    edges: Vec<(u64, bool)>,
    /// Steps counted by the interrupt.
    counted: u64,
    /// Tick at which the timer stopped for good.
    stopped_at: Option<u64>,
    /// Pushes that found the queue full.
    full: u64,
}

/// Steps as (scheduled time µs, forward); the task pushes each at `time + latency(k)`, the
/// update interrupt runs `isr_latency(k)` ticks after its event.
fn simulate(
    steps: &[(u64, bool)],
    latency: &dyn Fn(usize) -> u64,
    isr_latency: &dyn Fn(u64) -> u64,
) -> Run {
    let mut train = PulseTrain::new();
    let mut tim = Tim::default();
    let mut run = Run {
        edges: Vec::new(),
        counted: 0,
        stopped_at: None,
        full: 0,
    };
    let mut next = 0usize;
    let mut last_step_at = 0u64;
    let mut isr_at: Option<u64> = None;
    let end = steps.last().map_or(0, |s| s.0) + u64::from(PIPELINE) * 4 + 100_000;
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
        // The rig task: every step whose (late) push time has come.
        while next < steps.len() && steps[next].0 + latency(next) <= t {
            let (at, forward) = steps[next];
            let interval = interval_for(at, last_step_at, train.running(), PIPELINE, t - at);
            last_step_at = at;
            let step = QueuedStep { interval, forward };
            match train.push(step, tim.cnt, tim.uif) {
                Push::Queued => {}
                Push::Full => run.full += 1,
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

fn assert_exact(steps: &[(u64, bool)], run: &Run) {
    assert_eq!(run.full, 0, "queue overflowed");
    assert_eq!(run.edges.len(), steps.len(), "pulse count");
    assert_eq!(run.counted, steps.len() as u64, "counted steps");
    assert!(run.stopped_at.is_some(), "timer left running");
    let offset = run.edges[0].0 as i64 - steps[0].0 as i64;
    for (k, ((edge, dir), (at, forward))) in run.edges.iter().zip(steps).enumerate() {
        assert_eq!(
            *edge as i64 - *at as i64,
            offset,
            "step {k}: edge at {edge}, scheduled {at} (jitter)"
        );
        assert_eq!(dir, forward, "step {k}: DIR not settled before the edge");
    }
}

#[test]
fn twenty_khz_move_has_zero_jitter_with_late_task_and_interrupt() {
    // 4000 steps cruising at 20 kHz; the task is up to 900 µs late, the interrupt up to 6 ticks.
    let steps = schedule(5_000, 4_000, 20_000, 200_000, true);
    let run = simulate(&steps, &|k| (k as u64 * 7919) % 900, &|t| t % 7);
    assert_exact(&steps, &run);
    // The pipeline delay: the first push's lead minus the pulse width, plus that push's lateness.
    let offset = run.edges[0].0 - steps[0].0;
    assert_eq!(offset, u64::from(PIPELINE - PULSE_TICKS));
}

#[test]
fn moves_back_and_forth_keep_direction_per_step() {
    let mut steps = schedule(1_000, 500, 20_000, 200_000, true);
    let restart = steps.last().unwrap().0 + 50_000;
    steps.extend(schedule(restart, 500, 10_000, 100_000, false));
    let run = simulate(&steps, &|_| 37, &|_| 2);
    // Each move is exact relative to its own start.
    let (a, b) = steps.split_at(500);
    let (ea, eb) = run.edges.split_at(500);
    for (part, edges) in [(a, ea), (b, eb)] {
        let offset = edges[0].0 - part[0].0;
        for ((edge, dir), (at, forward)) in edges.iter().zip(part) {
            assert_eq!(edge - at, offset);
            assert_eq!(dir, forward);
        }
    }
    assert_eq!(run.counted, 1_000);
}

#[test]
fn slow_steps_from_idle_land_on_schedule_too() {
    // 200 steps/s: the timer stops between steps; each restart takes the rest of the pipeline
    // lead, so the task's varying lateness does not show in the pulses.
    let steps = schedule(0, 50, 200, 400, true);
    let run = simulate(&steps, &|k| (k as u64 * 13) % 50, &|_| 1);
    assert_exact(&steps, &run);
    assert_eq!(
        run.edges[0].0 - steps[0].0,
        u64::from(PIPELINE - PULSE_TICKS)
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Any profile (slow starts, 20 kHz cruise, reversals between moves) is reproduced with zero
    /// jitter, whatever the task's lateness (below the pipeline) and the interrupt latency.
    #[test]
    fn fast_profiles_are_exact(
        steps in 2u32..1_500,
        speed in 2_000u32..=20_000,
        accel in 20_000u32..=400_000,
        seed in 0u64..1_000,
    ) {
        let schedule = schedule(1_000, steps, speed, accel, seed % 2 == 0);
        let run = simulate(
            &schedule,
            &|k| (k as u64 * 2_654_435_761 + seed) % 900,
            &|t| (t ^ seed) % 6,
        );
        assert_exact(&schedule, &run);
    }
}
