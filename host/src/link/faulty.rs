//! Faults on any link: wraps a [`ByteLink`] and passes both directions through [`FaultInjector`]s.

use std::time::Duration;

use super::{ByteLink, FaultConfig, FaultInjector, FaultStats, LinkError};

/// Any [`ByteLink`] with injected drops, corruption and duplicated frames in both directions.
///
/// Latency and jitter in the configurations are ignored here (the inner link has its own timing);
/// use [`super::MemoryLink`] or [`super::VirtualWire`] for delays.
#[derive(Debug)]
pub struct FaultyLink<L> {
    inner: L,
    outgoing: FaultInjector,
    incoming: FaultInjector,
    buf: Vec<u8>,
    pending: Vec<u8>,
}

impl<L: ByteLink> FaultyLink<L> {
    /// Wrap `inner`: what we send goes through `send_faults`, what we receive through
    /// `recv_faults`.
    pub fn new(inner: L, send_faults: FaultConfig, recv_faults: FaultConfig) -> Self {
        Self {
            inner,
            outgoing: FaultInjector::new(send_faults),
            incoming: FaultInjector::new(recv_faults),
            buf: vec![0; 4096],
            pending: Vec::new(),
        }
    }

    /// Faults applied to sent bytes so far.
    pub fn sent_stats(&self) -> FaultStats {
        self.outgoing.stats()
    }

    /// Faults applied to received bytes so far.
    pub fn received_stats(&self) -> FaultStats {
        self.incoming.stats()
    }

    /// The wrapped link.
    pub fn inner(&self) -> &L {
        &self.inner
    }

    /// The wrapped link, unwrapped.
    pub fn into_inner(self) -> L {
        self.inner
    }
}

impl<L: ByteLink> ByteLink for FaultyLink<L> {
    fn send(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        let mut out = Vec::with_capacity(bytes.len() + 8);
        self.outgoing.apply(bytes, &mut out);
        if out.is_empty() {
            return Ok(());
        }
        self.inner.send(&out)
    }

    fn recv(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, LinkError> {
        if self.pending.is_empty() {
            // Everything received may be dropped: then report a timeout-free empty read, as a
            // serial port would after its timeout.
            let n = self.inner.recv(&mut self.buf, timeout)?;
            let chunk = self.buf.get(..n).unwrap_or_default();
            self.incoming.apply(chunk, &mut self.pending);
        }
        let n = buf.len().min(self.pending.len());
        buf[..n].copy_from_slice(&self.pending[..n]);
        self.pending.drain(..n);
        Ok(n)
    }

    fn describe(&self) -> String {
        format!("{} (with injected faults)", self.inner.describe())
    }

    fn now(&self) -> std::time::Instant {
        self.inner.now()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::MemoryLink;

    #[test]
    fn faults_apply_in_both_directions() {
        let (a, mut b) = MemoryLink::pair(FaultConfig::clean(), FaultConfig::clean());
        let drop_all = FaultConfig {
            drop_byte: 1.0,
            ..FaultConfig::clean()
        };
        let mut a = FaultyLink::new(a, drop_all, FaultConfig::clean());
        a.send(&[1, 2, 3]).expect("send");
        let mut buf = [0u8; 8];
        assert_eq!(b.recv(&mut buf, Duration::from_millis(5)).expect("recv"), 0);
        b.send(&[4, 5]).expect("send");
        assert_eq!(
            a.recv(&mut buf, Duration::from_millis(50)).expect("recv"),
            2
        );
        assert_eq!(a.sent_stats().dropped, 3);
    }
}
