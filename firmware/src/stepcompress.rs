//! Step compression: ideal step times in, `(interval, count, add)` runs out, each step within a
//! stated error of its ideal time.
//!
//! The board's step timer emits a run as Klipper's `queue_step` does: after the last step at
//! `last`, step `j` (1-based) of the run comes at `last + j·interval + add·j·(j−1)/2`, i.e. the
//! first gap is `interval` and every later gap is `add` longer than the one before. A constant
//! speed is one run, an acceleration ramp a handful, because a run need not match the ideal
//! times exactly: every step may come up to [`MAX_STEP_ERROR_US`] early, never late, and never
//! earlier than half-way to the step before it (so the order and the spacing of steps survive).
//! That is Klipper's rule (`klippy/chelper/stepcompress.c`); the search here is our own: for a
//! candidate `add` the feasible intervals are one range, narrowed point by point until it
//! empties, and the point that emptied it says whether `add` was too small or too large, so
//! `add` is bisected. Two runs that both stay within `e` of the same `c` points differ in `add`
//! by at most about 11.7·e/c² (Klipper's bound), which shrinks the search range after every try.
//! Hand-written: the core is `no_std` without a heap, and no crate does this.

/// Largest timing error of any step, µs: a step comes at most this much before its ideal time
/// (never after it). At 20 000 steps/s that is a tenth of a step.
pub const MAX_STEP_ERROR_US: u64 = 5;

/// A run of steps relative to the step before it (see the module docs), times in ticks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    /// Steps in the run (≥ 1).
    pub count: u16,
    /// Gap from the step before the run to its first step, ticks.
    pub interval: u64,
    /// Change of the gap from one step to the next, ticks.
    pub add: i32,
}

impl Run {
    /// Time of step `j` (1-based) after `last`.
    pub fn step_at(&self, last: u64, j: u64) -> u64 {
        let quad = i128::from(self.add) * i128::from(j) * i128::from(j.saturating_sub(1)) / 2;
        let t = i128::from(last) + i128::from(self.interval) * i128::from(j) + quad;
        u64::try_from(t).unwrap_or(0)
    }
}

/// Gaps longer than this (ticks) are a run of their own: no `add` would bridge them to the next
/// gap, and the arithmetic stays inside `i64`.
const FAR_GAP: u64 = 1 << 31;

/// Longest run (steps). With `add` an `i32` and gaps below [`FAR_GAP`], every product of the
/// search stays far inside `i64` (below 2^55).
pub const MAX_RUN: usize = 4_096;

/// The longest run that keeps every step of `ideal` (absolute times, ascending, in ticks) within
/// `[ideal − err, ideal]` (`err` at most half the gap to the step before), after the last step at
/// `last`; no gap shorter than `min_gap` ticks. `ideal` must not be empty. When even the first
/// step cannot be placed (it is due sooner than `min_gap` after `last`: a schedule faster than the
/// hardware) the run is that one step at `min_gap`, late.
pub fn compress(ideal: &[u64], last: u64, err: u64, min_gap: u64) -> Run {
    let first = ideal.first().map_or(0, |t| t.saturating_sub(last));
    let single = Run {
        count: 1,
        interval: first.max(min_gap),
        add: 0,
    };
    if ideal.len() < 2 || first >= FAR_GAP {
        return single;
    }
    let window = Window {
        ideal,
        last,
        err: i64::try_from(err).unwrap_or(i64::MAX),
        min_gap: i64::try_from(min_gap).unwrap_or(i64::MAX),
        max: ideal.len().min(MAX_RUN),
    };
    // Start from the `add` that joins the first and the last point exactly: on a smooth ramp
    // it is close to the best one for the whole window, so the search mostly confirms it.
    let c = window.max;
    let guess = match (ideal.first(), ideal.get(c - 1)) {
        (Some(&t1), Some(&tc)) if c > 1 => {
            let (t1, tc) = (
                i128::from(t1) - i128::from(last),
                i128::from(tc) - i128::from(last),
            );
            let c = i128::try_from(c).unwrap_or(1);
            i64::try_from(2 * (tc - c * t1) / (c * (c - 1))).unwrap_or(0)
        }
        _ => 0,
    };
    let (mut lo, mut hi) = (i64::from(i32::MIN), i64::from(i32::MAX));
    let mut add = guess.clamp(lo, hi);
    let mut best: Option<(usize, i64, i64)> = None;
    // Bounded: the range of `add` at least halves on every pass (64 passes is far more than the
    // 32 bits of `add` need).
    for _ in 0..64 {
        let fit = window.fit(add);
        if fit.count > 0 && best.is_none_or(|(c, _, _)| fit.count > c) {
            best = Some((fit.count, fit.interval, add));
        }
        if fit.count >= window.max {
            break;
        }
        if fit.short {
            lo = lo.max(add + 1);
        } else {
            hi = hi.min(add - 1);
        }
        if fit.count > 1 {
            let c = i64::try_from(fit.count).unwrap_or(i64::MAX);
            let dev = window.err.saturating_mul(12) / (c * c) + 1;
            lo = lo.max(add - dev);
            hi = hi.min(add + dev);
        }
        if lo > hi {
            break;
        }
        add = lo + (hi - lo) / 2;
    }
    match best {
        Some((count, interval, add)) if count > 1 || interval >= window.min_gap => Run {
            count: u16::try_from(count).unwrap_or(u16::MAX),
            interval: u64::try_from(interval).unwrap_or(0),
            add: i32::try_from(add).unwrap_or(0),
        },
        _ => single,
    }
}

struct Window<'a> {
    ideal: &'a [u64],
    last: u64,
    err: i64,
    min_gap: i64,
    max: usize,
}

/// The longest prefix a given `add` reaches.
struct Fit {
    /// Steps that fit.
    count: usize,
    /// The latest first gap that keeps them all in their windows.
    interval: i64,
    /// The next step could not be reached (a larger `add` might); otherwise it was overshot.
    short: bool,
}

impl Window<'_> {
    /// Step `j` (1-based)'s time relative to `last` (0 for `j = 0`).
    fn point(&self, j: usize) -> i64 {
        match j.checked_sub(1).and_then(|k| self.ideal.get(k)) {
            // Ideal times are after `last` and within `FAR_GAP` of each other for the points
            // a run may take (`compress` checks the first), so this fits.
            Some(&t) => t.wrapping_sub(self.last) as i64,
            None => 0,
        }
    }

    /// The longest prefix `add` reaches. Every product stays far inside `i64`: `j` is at most
    /// [`MAX_RUN`], `add` an `i32`, the first gap below `FAR_GAP` (`high` starts there), so
    /// `add·j·(j−1)/2` and `gap·j` are below 2^55.
    fn fit(&self, add: i64) -> Fit {
        // Feasible first gaps [low, high]; the gap before step j is interval + (j − 1)·add, so
        // the hardware's shortest gap bounds `low` too.
        let mut low = self.min_gap;
        let mut high = FAR_GAP as i64;
        let mut count = 0;
        let mut before = 0i64;
        for j in 1..=self.max {
            let point = self.point(j);
            // Window [point − e, point], e at most half the gap to the step before.
            let e = self.err.min((point - before) / 2).max(0);
            let (min, max) = (point - e, point);
            before = point;
            let jj = j as i64;
            let quad = add * (jj * (jj - 1) / 2);
            let mut new_low = low.max(self.min_gap - add * (jj - 1));
            if new_low * jj + quad < min {
                new_low = div_ceil(min - quad, jj);
            }
            let mut new_high = high;
            if new_high * jj + quad > max {
                new_high = (max - quad).div_euclid(jj);
            }
            if new_low > new_high {
                // With the latest first gap the run still falls short of step j: a larger add
                // would reach it. Otherwise even the earliest overshoots.
                return Fit {
                    count,
                    interval: high,
                    short: high * jj + quad < min,
                };
            }
            low = new_low;
            high = new_high;
            count = j;
        }
        Fit {
            count,
            interval: high,
            short: true,
        }
    }
}

fn div_ceil(n: i64, d: i64) -> i64 {
    let q = n.div_euclid(d);
    if n.rem_euclid(d) == 0 { q } else { q + 1 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::profile::Profile;
    use proptest::prelude::*;
    use std::vec::Vec;

    /// Compress a whole schedule run by run; check every step against its window.
    fn check_all(ideal: &[u64], err: u64, min_gap: u64) -> usize {
        let mut last = 0u64;
        let mut at = 0usize;
        let mut runs = 0;
        while at < ideal.len() {
            let run = compress(&ideal[at..], last, err, min_gap);
            assert!(run.count >= 1);
            let mut prev = last;
            for j in 1..=u64::from(run.count) {
                let t = run.step_at(last, j);
                let g = at + usize::try_from(j).unwrap() - 1;
                let want = ideal[g];
                let before = if j >= 2 { ideal[g - 1] } else { last };
                let e = err.min((want - before) / 2);
                assert!(
                    t <= want && t + e >= want,
                    "step {}: {t} outside [{} - {e}, {want}]",
                    at + j as usize,
                    want
                );
                assert!(t - prev >= min_gap, "gap {} below {min_gap}", t - prev);
                prev = t;
            }
            last = prev;
            at += usize::from(run.count);
            runs += 1;
        }
        runs
    }

    /// A profile's step times in ticks, made strictly increasing as the planner does (the
    /// profile is monotone only up to a µs of rounding where it changes regime).
    fn schedule(steps: u32, speed: u32, accel: u32, ticks_per_us: u64) -> Vec<u64> {
        let p = Profile::new(steps, speed, accel).unwrap();
        let mut prev = 0;
        (1..=steps)
            .map(|k| {
                prev = ((1_000 + p.step_time_us(k)) * ticks_per_us).max(prev + 1);
                prev
            })
            .collect()
    }

    #[test]
    fn constant_speed_is_one_run() {
        // 3 000 steps/s: 333.33 µs per step, not a whole number of µs, but 28 000 ticks of 84 MHz.
        let ideal: Vec<u64> = (1..=1_000u64).map(|k| k * 28_000).collect();
        assert_eq!(
            compress(&ideal, 0, 5 * 84, 840),
            Run {
                count: 1_000,
                interval: 28_000,
                add: 0
            }
        );
    }

    #[test]
    fn a_whole_move_compresses_to_a_few_runs_within_the_error() {
        // The default move (20 000 steps/s, 200 000 steps/s², one revolution): 16 000 steps.
        let ideal = schedule(16_000, 20_000, 200_000, 84);
        let runs = check_all(&ideal, MAX_STEP_ERROR_US * 84, 10 * 84);
        assert!(runs < 120, "{runs} runs for 16 000 steps");
    }

    #[test]
    fn a_far_first_step_is_a_run_of_its_own() {
        let ideal = [10_000_000_000u64, 10_000_000_100, 10_000_000_200];
        let run = compress(&ideal, 0, 5, 10);
        assert_eq!(run.count, 1);
        assert_eq!(run.step_at(0, 1), 10_000_000_000);
    }

    #[test]
    fn a_step_due_too_soon_comes_late_not_never() {
        let run = compress(&[105], 100, 5, 10);
        assert_eq!(run.step_at(100, 1), 110);
        // Ideal times already behind the last step (a schedule the hardware fell behind):
        // late, one at a time, never a panic.
        let run = compress(&[90, 95, 130], 100, 5, 10);
        assert_eq!((run.count, run.step_at(100, 1)), (1, 110));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn every_profile_stays_within_the_error(
            steps in 1u32..3_000,
            speed in 100u32..=50_000,
            accel in 1_000u32..=2_000_000,
            ticks in prop_oneof![Just(1u64), Just(84u64)],
        ) {
            let ideal = schedule(steps, speed, accel, ticks);
            check_all(&ideal, MAX_STEP_ERROR_US * ticks, 10 * ticks);
        }
    }
}
