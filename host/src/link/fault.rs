//! Seeded fault injection: the lossy serial line the protocol must survive, without I/O or clock.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Frames longer than this are not remembered for duplication (garbage without delimiters).
const MAX_REMEMBERED_FRAME: usize = 4096;

/// What goes wrong on one direction of a link, and how often.
///
/// Probabilities are per byte (drop, corrupt) or per delimited frame (duplicate); the frame
/// delimiter is the protocol's `0x00`. The same seed gives the same faults for the same traffic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultConfig {
    /// Probability that a byte is lost.
    pub drop_byte: f64,
    /// Probability that a byte arrives with some bits flipped.
    pub corrupt_byte: f64,
    /// Probability that a whole frame (up to and including its `0x00`) arrives twice.
    pub duplicate_frame: f64,
    /// Fixed delay between sending and arrival.
    pub latency: Duration,
    /// Extra uniformly distributed delay in `0..jitter` (order is preserved).
    pub jitter: Duration,
    /// Seed of the fault generator.
    pub seed: u64,
}

impl FaultConfig {
    /// A perfect wire: nothing lost, nothing delayed.
    pub const fn clean() -> Self {
        Self {
            drop_byte: 0.0,
            corrupt_byte: 0.0,
            duplicate_frame: 0.0,
            latency: Duration::ZERO,
            jitter: Duration::ZERO,
            seed: 0,
        }
    }

    /// The acceptance scenario: 1% of bytes dropped, 1% corrupted, 1% of frames duplicated.
    pub const fn lossy(seed: u64) -> Self {
        Self {
            drop_byte: 0.01,
            corrupt_byte: 0.01,
            duplicate_frame: 0.01,
            latency: Duration::ZERO,
            jitter: Duration::ZERO,
            seed,
        }
    }

    /// The same faults with a fixed latency and jitter.
    pub const fn with_delay(mut self, latency: Duration, jitter: Duration) -> Self {
        self.latency = latency;
        self.jitter = jitter;
        self
    }
}

impl Default for FaultConfig {
    fn default() -> Self {
        Self::clean()
    }
}

/// Counts of what a [`FaultInjector`] did, to check in tests that faults really happened.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Bytes offered to the injector.
    pub bytes_in: u64,
    /// Bytes it let through (including duplicates).
    pub bytes_out: u64,
    /// Bytes dropped.
    pub dropped: u64,
    /// Bytes corrupted.
    pub corrupted: u64,
    /// Frames sent twice.
    pub duplicated_frames: u64,
}

/// Applies a [`FaultConfig`] to a byte stream. Sans-IO: bytes in, bytes out.
#[derive(Debug, Clone)]
pub struct FaultInjector {
    config: FaultConfig,
    rng: StdRng,
    frame: Vec<u8>,
    stats: FaultStats,
}

impl FaultInjector {
    /// A new injector; its random sequence depends only on `config.seed`.
    pub fn new(config: FaultConfig) -> Self {
        Self {
            config,
            rng: StdRng::seed_from_u64(config.seed),
            frame: Vec::new(),
            stats: FaultStats::default(),
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &FaultConfig {
        &self.config
    }

    /// What has been done so far.
    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    /// Pass `input` through the faulty wire, appending what comes out to `out`.
    pub fn apply(&mut self, input: &[u8], out: &mut Vec<u8>) {
        let start = out.len();
        for &byte in input {
            self.stats.bytes_in += 1;
            if self.config.drop_byte > 0.0 && self.rng.random_bool(self.config.drop_byte) {
                self.stats.dropped += 1;
                continue;
            }
            let mut byte = byte;
            if self.config.corrupt_byte > 0.0 && self.rng.random_bool(self.config.corrupt_byte) {
                let mask: u8 = self.rng.random_range(1..=255);
                byte ^= mask;
                self.stats.corrupted += 1;
            }
            out.push(byte);
            if self.frame.len() < MAX_REMEMBERED_FRAME {
                self.frame.push(byte);
            }
            if byte == 0 {
                if self.config.duplicate_frame > 0.0
                    && self.rng.random_bool(self.config.duplicate_frame)
                {
                    out.extend_from_slice(&self.frame);
                    self.stats.duplicated_frames += 1;
                }
                self.frame.clear();
            }
        }
        self.stats.bytes_out += (out.len() - start) as u64;
    }

    /// The delay of the next chunk: latency plus a uniform draw from the jitter.
    pub fn delay(&mut self) -> Duration {
        let jitter = if self.config.jitter.is_zero() {
            Duration::ZERO
        } else {
            let nanos = u64::try_from(self.config.jitter.as_nanos()).unwrap_or(u64::MAX);
            Duration::from_nanos(self.rng.random_range(0..nanos))
        };
        self.config.latency + jitter
    }
}

/// One direction of a faulty wire in virtual time: bytes sent at `now` arrive after the delay.
///
/// Sans-IO and clock-free: the caller says what time it is. Used directly by deterministic tests
/// (step both ends, jump to [`VirtualWire::next_arrival`]) and by [`super::MemoryLink`] with the
/// wall clock.
#[derive(Debug, Clone)]
pub struct VirtualWire {
    injector: FaultInjector,
    in_flight: VecDeque<(Instant, Vec<u8>)>,
    last_arrival: Option<Instant>,
}

impl VirtualWire {
    /// A wire with the given faults.
    pub fn new(config: FaultConfig) -> Self {
        Self {
            injector: FaultInjector::new(config),
            in_flight: VecDeque::new(),
            last_arrival: None,
        }
    }

    /// Put `bytes` on the wire at time `now`.
    pub fn send(&mut self, now: Instant, bytes: &[u8]) {
        let mut out = Vec::with_capacity(bytes.len() + 8);
        self.injector.apply(bytes, &mut out);
        if out.is_empty() {
            return;
        }
        let mut arrival = now + self.injector.delay();
        // Serial lines do not reorder: a chunk never overtakes the previous one.
        if let Some(last) = self.last_arrival {
            arrival = arrival.max(last);
        }
        self.last_arrival = Some(arrival);
        self.in_flight.push_back((arrival, out));
    }

    /// Move every byte that has arrived by `now` into `out`; returns how many.
    pub fn receive(&mut self, now: Instant, out: &mut Vec<u8>) -> usize {
        let start = out.len();
        while let Some((arrival, _)) = self.in_flight.front() {
            if *arrival > now {
                break;
            }
            if let Some((_, bytes)) = self.in_flight.pop_front() {
                out.extend_from_slice(&bytes);
            }
        }
        out.len() - start
    }

    /// When the next chunk arrives, if any is in flight.
    pub fn next_arrival(&self) -> Option<Instant> {
        self.in_flight.front().map(|(t, _)| *t)
    }

    /// Whether nothing is in flight.
    pub fn is_idle(&self) -> bool {
        self.in_flight.is_empty()
    }

    /// Lose everything in flight (a cable pulled for a moment).
    pub fn drop_in_flight(&mut self) {
        self.in_flight.clear();
    }

    /// What the injector has done so far.
    pub fn stats(&self) -> FaultStats {
        self.injector.stats()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clean_wire_passes_everything_unchanged() {
        let mut inj = FaultInjector::new(FaultConfig::clean());
        let data: Vec<u8> = (0..=255).collect();
        let mut out = Vec::new();
        inj.apply(&data, &mut out);
        assert_eq!(out, data);
        assert_eq!(inj.stats().dropped + inj.stats().corrupted, 0);
    }

    #[test]
    fn lossy_wire_rates_are_close_to_configured() {
        let mut inj = FaultInjector::new(FaultConfig::lossy(7));
        // 20,000 frames of 9 bytes + delimiter.
        let frame = [1u8, 2, 3, 4, 5, 6, 7, 8, 9, 0];
        let mut out = Vec::new();
        for _ in 0..20_000 {
            inj.apply(&frame, &mut out);
        }
        let s = inj.stats();
        assert_eq!(s.bytes_in, 200_000);
        let rate = |n: u64| n as f64 / 200_000.0;
        assert!((0.008..0.012).contains(&rate(s.dropped)), "{s:?}");
        assert!((0.008..0.012).contains(&rate(s.corrupted)), "{s:?}");
        assert!((150..260).contains(&s.duplicated_frames), "{s:?}");
        assert_eq!(s.bytes_out, out.len() as u64);
    }

    #[test]
    fn same_seed_same_faults() {
        let data: Vec<u8> = (0..5000u32).map(|i| (i % 7) as u8).collect();
        let run = |seed| {
            let mut inj = FaultInjector::new(FaultConfig::lossy(seed));
            let mut out = Vec::new();
            inj.apply(&data, &mut out);
            out
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
    }

    #[test]
    fn duplicated_frame_repeats_the_whole_frame() {
        let config = FaultConfig {
            duplicate_frame: 1.0,
            ..FaultConfig::clean()
        };
        let mut inj = FaultInjector::new(config);
        let mut out = Vec::new();
        inj.apply(&[5, 6, 0, 7], &mut out);
        inj.apply(&[0], &mut out);
        assert_eq!(out, vec![5, 6, 0, 5, 6, 0, 7, 0, 7, 0]);
    }

    #[test]
    fn virtual_wire_delays_and_keeps_order() {
        let t0 = Instant::now();
        let config =
            FaultConfig::clean().with_delay(Duration::from_millis(5), Duration::from_millis(10));
        let mut wire = VirtualWire::new(config);
        for i in 0..50u8 {
            wire.send(t0 + Duration::from_micros(u64::from(i)), &[i]);
        }
        let mut out = Vec::new();
        assert_eq!(wire.receive(t0 + Duration::from_millis(4), &mut out), 0);
        let first = wire.next_arrival().expect("bytes in flight");
        assert!(first >= t0 + Duration::from_millis(5));
        wire.receive(t0 + Duration::from_millis(100), &mut out);
        assert_eq!(out, (0..50u8).collect::<Vec<_>>());
        assert!(wire.is_idle());
    }
}
