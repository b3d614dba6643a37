//! An in-memory duplex byte link with fault injection, for threaded tests and the in-process sim.

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::{ByteLink, FaultConfig, FaultStats, LinkError, VirtualWire};

/// One direction: a [`VirtualWire`] driven by the wall clock, plus "the sender has gone".
#[derive(Debug)]
struct Pipe {
    state: Mutex<PipeState>,
    arrived: Condvar,
}

#[derive(Debug)]
struct PipeState {
    wire: VirtualWire,
    closed: bool,
}

impl Pipe {
    fn new(config: FaultConfig) -> Arc<Self> {
        Arc::new(Self {
            state: Mutex::new(PipeState {
                wire: VirtualWire::new(config),
                closed: false,
            }),
            arrived: Condvar::new(),
        })
    }

    fn lock(&self) -> MutexGuard<'_, PipeState> {
        // A poisoned lock only means another thread panicked mid-test; the queue is still valid.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn close(&self) {
        self.lock().closed = true;
        self.arrived.notify_all();
    }
}

/// One end of an in-memory duplex created by [`MemoryLink::pair`].
///
/// Each direction has its own [`FaultConfig`]; latency is real (wall clock). Dropping one end makes
/// the other's `recv` return [`LinkError::Closed`] once everything in flight has been read.
#[derive(Debug)]
pub struct MemoryLink {
    name: String,
    outgoing: Arc<Pipe>,
    incoming: Arc<Pipe>,
    pending: Vec<u8>,
}

impl MemoryLink {
    /// Two connected ends: bytes sent on `.0` go through `a_to_b` and arrive at `.1`, and back.
    pub fn pair(a_to_b: FaultConfig, b_to_a: FaultConfig) -> (Self, Self) {
        let ab = Pipe::new(a_to_b);
        let ba = Pipe::new(b_to_a);
        (
            Self {
                name: "memory link (end A)".into(),
                outgoing: Arc::clone(&ab),
                incoming: Arc::clone(&ba),
                pending: Vec::new(),
            },
            Self {
                name: "memory link (end B)".into(),
                outgoing: ba,
                incoming: ab,
                pending: Vec::new(),
            },
        )
    }

    /// Faults injected so far on what this end sent.
    pub fn sent_stats(&self) -> FaultStats {
        self.outgoing.lock().wire.stats()
    }
}

impl Drop for MemoryLink {
    fn drop(&mut self) {
        self.outgoing.close();
        self.incoming.close();
    }
}

impl ByteLink for MemoryLink {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let mut state = self.outgoing.lock();
        if state.closed {
            return Err(LinkError::Closed {
                link: self.name.clone(),
            });
        }
        state.wire.send(Instant::now(), bytes);
        drop(state);
        self.outgoing.arrived.notify_all();
        Ok(())
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        let deadline = Instant::now() + timeout;
        if self.pending.is_empty() {
            let mut state = self.incoming.lock();
            loop {
                let now = Instant::now();
                if state.wire.receive(now, &mut self.pending) > 0 {
                    break;
                }
                if state.closed && state.wire.is_idle() {
                    return Err(LinkError::Closed {
                        link: self.name.clone(),
                    });
                }
                if now >= deadline {
                    return Ok(0);
                }
                let wake = state
                    .wire
                    .next_arrival()
                    .map_or(deadline, |t| t.min(deadline));
                let wait = wake.saturating_duration_since(now);
                state = self
                    .incoming
                    .arrived
                    .wait_timeout(state, wait)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
        let n = buf.len().min(self.pending.len());
        buf[..n].copy_from_slice(&self.pending[..n]);
        self.pending.drain(..n);
        Ok(n)
    }

    fn describe(&self) -> String {
        self.name.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bytes_cross_both_ways_and_timeout_returns_zero() {
        let (mut a, mut b) = MemoryLink::pair(FaultConfig::clean(), FaultConfig::clean());
        a.send(b"hello").expect("send");
        let mut buf = [0u8; 3];
        assert_eq!(
            b.recv(&mut buf, Duration::from_millis(50)).expect("recv"),
            3
        );
        assert_eq!(&buf, b"hel");
        assert_eq!(
            b.recv(&mut buf, Duration::from_millis(50)).expect("recv"),
            2
        );
        assert_eq!(&buf[..2], b"lo");
        b.send(b"x").expect("send");
        assert_eq!(
            a.recv(&mut buf, Duration::from_millis(50)).expect("recv"),
            1
        );
        assert_eq!(b.recv(&mut buf, Duration::from_millis(1)).expect("recv"), 0);
    }

    #[test]
    fn latency_is_honoured_across_threads() {
        let cfg = FaultConfig::clean().with_delay(Duration::from_millis(20), Duration::ZERO);
        let (mut a, mut b) = MemoryLink::pair(cfg, FaultConfig::clean());
        // The delay is a lower bound measured from before the send, so a loaded machine (a late
        // receiving thread, a slow scheduler) can only make the wait longer, never fail the test.
        let t = std::thread::spawn(move || {
            let mut buf = [0u8; 8];
            let n = b.recv(&mut buf, Duration::from_secs(10)).expect("recv");
            (n, Instant::now())
        });
        let sent = Instant::now();
        a.send(&[1, 2]).expect("send");
        let (n, received) = t.join().expect("thread");
        assert_eq!(n, 2);
        let waited = received.duration_since(sent);
        assert!(waited >= Duration::from_millis(20), "{waited:?}");
    }

    #[test]
    fn dropping_one_end_closes_the_other() {
        let (mut a, b) = MemoryLink::pair(FaultConfig::clean(), FaultConfig::clean());
        drop(b);
        let mut buf = [0u8; 4];
        assert!(matches!(
            a.recv(&mut buf, Duration::from_millis(10)),
            Err(LinkError::Closed { .. })
        ));
        assert!(matches!(a.send(&[1]), Err(LinkError::Closed { .. })));
    }
}
