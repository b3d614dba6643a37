//! Serving the simulated rig in real time over any [`ByteLink`]: a pseudo-terminal, a memory link.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::{SimParams, VirtualRig};
use crate::link::{ByteLink, FaultConfig, LinkError, MemoryLink};

/// Longest the serving loop blocks before it looks at its stop flag again.
const MAX_WAIT: Duration = Duration::from_millis(20);

/// Serve `rig` over `link` with the wall clock until `stop` is set or the link closes.
///
/// Garbage on the link is the decoder's business (dropped and counted, like on the board); only
/// an I/O error of the link ends serving with an error. The rig is locked only while it is
/// stepped, so another thread can read its logs meanwhile.
pub fn serve<L: ByteLink>(
    mut link: L,
    rig: &Mutex<VirtualRig>,
    stop: &AtomicBool,
) -> Result<(), LinkError> {
    let start = Instant::now();
    let mut buf = vec![0u8; 4096];
    let mut out = Vec::new();
    let now_us = |start: Instant| u64::try_from(start.elapsed().as_micros()).unwrap_or(u64::MAX);
    while !stop.load(Ordering::Relaxed) {
        let wait = {
            let mut rig = lock(rig);
            let now = now_us(start);
            rig.advance(now);
            out.clear();
            rig.drain_output(&mut out);
            rig.next_deadline_us()
                .map_or(MAX_WAIT, |d| Duration::from_micros(d.saturating_sub(now)))
                .min(MAX_WAIT)
        };
        if !out.is_empty() {
            link.send(&out)?;
        }
        let n = match link.recv(&mut buf, wait) {
            Ok(n) => n,
            Err(LinkError::Closed { .. }) => return Ok(()),
            Err(e) => return Err(e),
        };
        if n > 0 {
            let mut rig = lock(rig);
            rig.handle_input(now_us(start), &buf[..n]);
        }
    }
    Ok(())
}

fn lock(rig: &Mutex<VirtualRig>) -> MutexGuard<'_, VirtualRig> {
    // A panic elsewhere while holding the lock leaves a rig that is still consistent enough to
    // read its logs; the serving loop itself never panics.
    rig.lock().unwrap_or_else(|e| e.into_inner())
}

/// Serve a new simulated rig over `link` until the process is killed or the link closes.
pub fn serve_forever<L: ByteLink>(link: L, options: SimParams) -> Result<(), LinkError> {
    let rig = Mutex::new(VirtualRig::new(options));
    serve(link, &rig, &AtomicBool::new(false))
}

/// A simulated rig served by a background thread (see [`spawn`] and [`spawn_in_memory`]).
///
/// Dropping the handle stops the thread.
#[derive(Debug)]
pub struct SimServer {
    rig: Arc<Mutex<VirtualRig>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<Result<(), LinkError>>>,
}

impl SimServer {
    /// Look at the rig (its logs) while it is being served.
    pub fn with_rig<T>(&self, f: impl FnOnce(&mut VirtualRig) -> T) -> T {
        f(&mut lock(&self.rig))
    }

    /// Stop serving and return how serving ended.
    pub fn stop(mut self) -> Result<(), LinkError> {
        self.shutdown()
    }

    fn shutdown(&mut self) -> Result<(), LinkError> {
        self.stop.store(true, Ordering::Relaxed);
        match self.thread.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(LinkError::Closed {
                link: "simulated rig thread (it panicked)".into(),
            }),
            None => Ok(()),
        }
    }
}

impl Drop for SimServer {
    fn drop(&mut self) {
        let _ = self.shutdown();
    }
}

/// Serve a new simulated rig over `link` on a background thread.
pub fn spawn<L: ByteLink + 'static>(link: L, options: SimParams) -> std::io::Result<SimServer> {
    let rig = Arc::new(Mutex::new(VirtualRig::new(options)));
    let stop = Arc::new(AtomicBool::new(false));
    let thread = std::thread::Builder::new()
        .name("subsurf-sim-rig".into())
        .spawn({
            let rig = Arc::clone(&rig);
            let stop = Arc::clone(&stop);
            move || serve(link, &rig, &stop)
        })?;
    Ok(SimServer {
        rig,
        stop,
        thread: Some(thread),
    })
}

/// A simulated rig on a background thread behind a clean in-memory link; returns the host's end.
pub fn spawn_in_memory(options: SimParams) -> std::io::Result<(MemoryLink, SimServer)> {
    let (host, rig_end) = MemoryLink::pair(FaultConfig::clean(), FaultConfig::clean());
    let server = spawn(rig_end, options)?;
    Ok((host, server))
}
