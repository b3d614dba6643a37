//! [`SimLink`]: the simulated rig stepped inline behind a faulty wire, in virtual time.

use std::time::{Duration, Instant};

use super::VirtualRig;
use crate::link::{ByteLink, FaultConfig, FaultStats, LinkError, VirtualWire};

/// A [`ByteLink`] whose far end is a [`VirtualRig`] stepped inline with a virtual clock.
///
/// Nothing sleeps: `recv` jumps virtual time to the next thing that happens (a byte arriving, a rig
/// deadline, the caller's timeout). A [`crate::rig::RigClient`] on a `SimLink` runs every
/// retransmission timeout, heartbeat, move and exposure in virtual time, deterministically for a
/// given seed: a 10,000-command session over a lossy wire takes well under a second of wall time,
/// and [`SimLink::elapsed`] says how long it would have taken on the rig.
#[derive(Debug)]
pub struct SimLink {
    rig: VirtualRig,
    to_rig: VirtualWire,
    to_host: VirtualWire,
    base: Instant,
    now: Instant,
    scratch: Vec<u8>,
    pending: Vec<u8>,
}

impl SimLink {
    /// `rig` behind a wire with `to_rig` faults on the host → rig direction and `to_host` on the
    /// way back. Virtual time starts at zero, as the rig's clock does.
    pub fn new(rig: VirtualRig, to_rig: FaultConfig, to_host: FaultConfig) -> Self {
        let base = Instant::now();
        Self {
            rig,
            to_rig: VirtualWire::new(to_rig),
            to_host: VirtualWire::new(to_host),
            base,
            now: base,
            scratch: Vec::new(),
            pending: Vec::new(),
        }
    }

    /// A clean wire with no latency.
    pub fn clean(rig: VirtualRig) -> Self {
        Self::new(rig, FaultConfig::clean(), FaultConfig::clean())
    }

    /// The simulated rig (its hardware logs, position, laser and trigger history).
    pub fn rig(&self) -> &VirtualRig {
        &self.rig
    }

    /// The simulated rig, mutably (e.g. to press the emergency stop or open the interlock).
    pub fn rig_mut(&mut self) -> &mut VirtualRig {
        &mut self.rig
    }

    /// Virtual time since the link was created.
    pub fn elapsed(&self) -> Duration {
        self.now.duration_since(self.base)
    }

    /// Faults injected on the host → rig and rig → host directions so far.
    pub fn fault_stats(&self) -> (FaultStats, FaultStats) {
        (self.to_rig.stats(), self.to_host.stats())
    }

    /// Let virtual time pass with the host silent (the rig keeps running; heartbeats stop).
    pub fn advance(&mut self, by: Duration) {
        let until = self.now + by;
        loop {
            self.step_rig();
            if self.now >= until {
                return;
            }
            self.now = self.next_wake().map_or(until, |t| t.min(until));
        }
    }

    fn rig_us(&self) -> u64 {
        u64::try_from(self.now.duration_since(self.base).as_micros()).unwrap_or(u64::MAX)
    }

    /// Deliver what reached the rig, let it run up to `now`, put its output on the wire.
    fn step_rig(&mut self) {
        let now_us = self.rig_us();
        self.scratch.clear();
        if self.to_rig.receive(self.now, &mut self.scratch) > 0 {
            self.rig.handle_input(now_us, &self.scratch);
        }
        self.rig.advance(now_us);
        self.scratch.clear();
        self.rig.drain_output(&mut self.scratch);
        if !self.scratch.is_empty() {
            self.to_host.send(self.now, &self.scratch);
        }
    }

    /// The earliest future moment something happens: an arrival on either wire or a rig deadline.
    fn next_wake(&self) -> Option<Instant> {
        let rig = self
            .rig
            .next_deadline_us()
            .map(|us| self.base + Duration::from_micros(us));
        [self.to_rig.next_arrival(), self.to_host.next_arrival(), rig]
            .into_iter()
            .flatten()
            .min()
            // Never stand still: a deadline that is already due is handled one microsecond on.
            .map(|t| t.max(self.now + Duration::from_micros(1)))
    }
}

impl ByteLink for SimLink {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.to_rig.send(self.now, bytes);
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        let deadline = self.now + timeout;
        loop {
            self.step_rig();
            self.to_host.receive(self.now, &mut self.pending);
            if !self.pending.is_empty() {
                let n = buf.len().min(self.pending.len());
                buf[..n].copy_from_slice(&self.pending[..n]);
                self.pending.drain(..n);
                return Ok(n);
            }
            if self.now >= deadline {
                return Ok(0);
            }
            self.now = self.next_wake().map_or(deadline, |t| t.min(deadline));
        }
    }

    fn describe(&self) -> String {
        "the simulated rig (in-process, virtual time)".into()
    }

    fn now(&self) -> Instant {
        self.now
    }
}
