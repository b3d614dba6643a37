//! Trapezoidal stepper motion profiles in integer arithmetic.
//!
//! A move of `n` steps starts and ends at rest, accelerates at `a` steps/s² up to at most `v`
//! steps/s, cruises, and decelerates symmetrically (a triangle when `n` is too short to reach `v`).
//! [`Profile::step_time_us`] gives the exact time of every step from the closed-form position
//! curve, so rounding never accumulates over long moves and the step count is exact by
//! construction. Hand-written (no crate computes step times in integer µs for `no_std`); all
//! intermediate values are `u128`, so no target in `i32` range can overflow.

/// Microseconds per second.
const US: u128 = 1_000_000;

/// Step timing of one move: step `k` (1-based) is due [`Profile::step_time_us`] after the start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Profile {
    steps: u32,
    speed: u32,
    accel: u32,
    /// Whether the cruise speed is reached (trapezoid) or not (triangle).
    trapezoid: bool,
    /// Time of the last step, µs.
    total_us: u64,
    /// Every intermediate value of [`Profile::step_time_us`] fits 64 bits: it then runs without
    /// 128-bit arithmetic, which a Cortex-M4 only has as library calls (the planner computes this
    /// for every step).
    narrow: bool,
}

fn to_u64(x: u128) -> u64 {
    u64::try_from(x).unwrap_or(u64::MAX)
}

/// `n / d` (d > 0), in 64-bit arithmetic when both fit: a Cortex-M4 has no 128-bit divide, and
/// this runs once per step. Moves shorter than ~9 million steps always take the fast path.
fn div(n: u128, d: u128) -> u128 {
    match (u64::try_from(n), u64::try_from(d)) {
        (Ok(n), Ok(d)) => u128::from(n.checked_div(d).unwrap_or(u64::MAX)),
        _ => n.checked_div(d).unwrap_or(u128::MAX),
    }
}

/// `floor(sqrt(x))`, in 64-bit arithmetic when `x` fits.
fn isqrt(x: u128) -> u128 {
    match u64::try_from(x) {
        Ok(x) => u128::from(x.isqrt()),
        Err(_) => x.isqrt(),
    }
}

impl Profile {
    /// A profile for `steps` steps at cruise speed `speed` (steps/s) and acceleration `accel`
    /// (steps/s²); `None` if the speed or acceleration is zero.
    pub fn new(steps: u32, speed: u32, accel: u32) -> Option<Self> {
        if speed == 0 || accel == 0 {
            return None;
        }
        let (n, v, a) = (u128::from(steps), u128::from(speed), u128::from(accel));
        // Full speed is reached iff the acceleration distance v²/2a is below half the move.
        let trapezoid = v * v < a * n;
        let total_us = if trapezoid {
            // T = n/v + v/a
            to_u64(div(US * (n * a + v * v), a * v))
        } else {
            // T = 2·sqrt(n/a)
            to_u64(isqrt(div(4 * n * US * US, a)))
        };
        let max = u128::from(u64::MAX);
        let narrow = 2 * n * US * US <= max && US * (2 * a * n + v * v) <= max && 2 * a * v <= max;
        Some(Self {
            steps,
            speed,
            accel,
            trapezoid,
            total_us,
            narrow,
        })
    }

    /// Number of steps in the move.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Time from the start of the move to its last step, µs.
    pub fn duration_us(&self) -> u64 {
        self.total_us
    }

    /// Steps of the acceleration ramp (= of the deceleration ramp): `v²/2a` for a trapezoid,
    /// half the move for a triangle. A move stopped after `k` steps needs `min(k, ramp)` more
    /// steps to come to rest.
    pub fn ramp_steps(&self) -> u32 {
        let half = self.steps / 2;
        if !self.trapezoid {
            return half;
        }
        let (v, a) = (u128::from(self.speed), u128::from(self.accel));
        u32::try_from(div(v * v, 2 * a))
            .unwrap_or(u32::MAX)
            .min(half)
    }

    /// Time of step `k` (1..=steps) after the start of the move, µs. `k` past the end gives the
    /// duration; `k = 0` gives 0.
    pub fn step_time_us(&self, k: u32) -> u64 {
        let k = k.min(self.steps);
        if k == 0 {
            return 0;
        }
        if self.narrow {
            return self.step_time_narrow(k);
        }
        let (n, v, a) = (
            u128::from(self.steps),
            u128::from(self.speed),
            u128::from(self.accel),
        );
        let k = u128::from(k);
        let rest = n - k;
        // Time to cover s steps from rest at acceleration a: sqrt(2s/a).
        let from_rest = |s: u128| to_u64(isqrt(div(2 * s * US * US, a)));
        if self.trapezoid {
            if 2 * a * k <= v * v {
                from_rest(k)
            } else if 2 * a * rest <= v * v {
                self.total_us.saturating_sub(from_rest(rest))
            } else {
                // Cruise: t = k/v + v/2a.
                to_u64(div(US * (2 * a * k + v * v), 2 * a * v))
            }
        } else if 2 * k <= n {
            from_rest(k)
        } else {
            self.total_us.saturating_sub(from_rest(rest))
        }
    }
}

impl Profile {
    /// [`Profile::step_time_us`] for `1 <= k <= steps` when every product fits 64 bits: the same
    /// formulas, the same results.
    fn step_time_narrow(&self, k: u32) -> u64 {
        const US: u64 = 1_000_000;
        let (n, v, a, k) = (
            u64::from(self.steps),
            u64::from(self.speed),
            u64::from(self.accel),
            u64::from(k),
        );
        let rest = n - k;
        let vv = v * v;
        let from_rest = |s: u64| (2 * s * US * US / a).isqrt();
        if self.trapezoid {
            if 2 * a * k <= vv {
                from_rest(k)
            } else if 2 * a * rest <= vv {
                self.total_us.saturating_sub(from_rest(rest))
            } else {
                // US·(2ak + v²)/(2av) = US·k/v + US·v/(2a), floored as one sum: the second term
                // and the divisors are 32-bit, so no 64-by-64 division runs per step.
                let (qx, rx) = (US * k / v, US * k % v);
                let (qy, ry) = (US * v / (2 * a), US * v % (2 * a));
                // frac(x) + frac(y) >= 1  <=>  rx·2a + ry·v >= 2av (all below 2^64: narrow).
                let carry = (rx * 2 * a)
                    .checked_add(ry * v)
                    .is_none_or(|f| f >= 2 * a * v);
                qx + qy + u64::from(carry)
            }
        } else if 2 * k <= n {
            from_rest(k)
        } else {
            self.total_us.saturating_sub(from_rest(rest))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn times(p: &Profile) -> impl Iterator<Item = u64> + '_ {
        (1..=p.steps()).map(|k| p.step_time_us(k))
    }

    #[test]
    fn zero_speed_or_accel_is_rejected() {
        assert_eq!(Profile::new(10, 0, 5), None);
        assert_eq!(Profile::new(10, 5, 0), None);
    }

    #[test]
    fn trapezoid_matches_hand_computation() {
        // v = 1000 steps/s, a = 10_000 steps/s²: accelerating takes 0.1 s and 50 steps.
        let p = Profile::new(1000, 1000, 10_000).unwrap();
        assert_eq!(p.duration_us(), 1_100_000); // 1000/1000 + 1000/10000 s
        assert_eq!(p.step_time_us(50), 100_000); // sqrt(2·50/10000) s
        assert_eq!(p.step_time_us(500), 550_000); // 500/1000 + 0.05 s
        assert_eq!(p.step_time_us(1000), 1_100_000);
        assert_eq!(p.step_time_us(950), 1_000_000);
    }

    #[test]
    fn triangle_matches_hand_computation() {
        // 100 steps at a = 10_000: never reaches 1000 steps/s; T = 2·sqrt(100/10000) = 0.2 s.
        let p = Profile::new(100, 1000, 10_000).unwrap();
        assert_eq!(p.duration_us(), 200_000);
        assert_eq!(p.step_time_us(50), 100_000);
        assert_eq!(p.step_time_us(100), 200_000);
    }

    #[test]
    fn longest_possible_move_does_not_overflow() {
        // i32::MIN → i32::MAX is u32::MAX steps.
        for (v, a) in [(1, 1), (u32::MAX, u32::MAX), (1, u32::MAX), (u32::MAX, 1)] {
            let p = Profile::new(u32::MAX, v, a).unwrap();
            let mut prev = 0;
            for k in [1, 2, u32::MAX / 2, u32::MAX - 1, u32::MAX] {
                let t = p.step_time_us(k);
                assert!(t + 1 >= prev, "v={v} a={a} k={k}");
                prev = t;
            }
            assert_eq!(p.step_time_us(u32::MAX), p.duration_us());
        }
    }

    /// The 64-bit path gives the 128-bit path's results to the µs.
    fn wide(p: &Profile, k: u32) -> u64 {
        Profile {
            narrow: false,
            ..*p
        }
        .step_time_us(k)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn narrow_arithmetic_is_exact(steps in 1u32..200_000, speed in 1u32..=100_000, accel in 1u32..=20_000_000, k in any::<u32>()) {
            let p = Profile::new(steps, speed, accel).unwrap();
            prop_assert!(p.narrow);
            let k = k % steps + 1;
            prop_assert_eq!(p.step_time_us(k), wide(&p, k));
        }

        #[test]
        fn steps_are_ordered_bounded_and_end_on_time(
            steps in 1u32..3000,
            speed in 1u32..200_000,
            accel in 1u32..2_000_000,
        ) {
            let p = Profile::new(steps, speed, accel).unwrap();
            prop_assert_eq!(times(&p).count() as u32, steps);
            prop_assert_eq!(p.step_time_us(steps), p.duration_us());
            let min_gap = 1_000_000 / u64::from(speed);
            let mut prev = 0u64;
            for (i, t) in times(&p).enumerate() {
                // Monotone up to one µs of rounding where the curve changes regime.
                prop_assert!(t + 1 >= prev, "step {} at {} before {}", i + 1, t, prev);
                // Never faster than the cruise speed (one µs of rounding each side).
                if i > 0 {
                    prop_assert!(t + 2 >= prev + min_gap, "step {} too soon: {} after {}", i + 1, t, prev);
                }
                prev = prev.max(t);
            }
        }

        #[test]
        fn symmetric_accel_and_decel(steps in 2u32..2000, speed in 1u32..50_000, accel in 1u32..500_000) {
            let p = Profile::new(steps, speed, accel).unwrap();
            let t = |k| p.step_time_us(k);
            // Time from step k to the end mirrors the time from the start to step n - k.
            for k in 1..steps {
                let tail = p.duration_us() - t(k);
                let head = t(steps - k);
                prop_assert!(tail.abs_diff(head) <= 2, "k={}: tail {} head {}", k, tail, head);
            }
        }

        #[test]
        fn any_i32_move_is_safe(from in any::<i32>(), to in any::<i32>(), v in 1u32.., a in 1u32.., k in any::<u32>()) {
            let steps = (i64::from(to) - i64::from(from)).unsigned_abs();
            let steps = u32::try_from(steps).unwrap();
            let p = Profile::new(steps, v, a).unwrap();
            prop_assert!(p.step_time_us(k) <= p.duration_us());
        }
    }
}
