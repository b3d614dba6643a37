//! The board's log on the motion path, deferred.
//!
//! A defmt line is a critical section: defmt-rtt masks every interrupt while it encodes and
//! writes the line, and when a probe holds the RTT channel in blocking mode it waits there until
//! the probe has read it. Inside a motion that delays the step interrupt (TIM2, alone above every
//! other handler) by the whole line, long enough to fault `StepLate` for nothing. So nothing on
//! the motion path logs: interrupts and the rig task's motion-time code only [`note`] what
//! happened (a few words into a queue under a short critical section, or a counter), and the rig
//! task writes the log lines ([`drain`]) only while no step is being emitted.
use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};

use embassy_sync::blocking_mutex::CriticalSectionMutex;
use heapless::Deque;
use subsurf_protocol::{Fault, HaltReason};

/// Something worth a log line, noted during motion.
#[derive(Clone, Copy, Debug)]
pub enum Note {
    /// Laser channels (mask) whose line idles at the level the profile calls on: not driven.
    LaserPolarity(u8),
    /// A write to the external galvo DAC failed.
    GalvoWrite,
    /// The core halted (its `Halted` event went out).
    Halt(HaltReason),
    /// The core's fault changed.
    Fault(Option<Fault>),
    /// Step interrupts later than one period (the train stopped).
    StepLate(u32),
    /// Steps that missed their time, and the segments still queued.
    StepStall(u32, usize),
    /// The motor driver was energised (`true`) or released.
    Motor(bool),
    /// A timed exposure started: trigger rise and fall, laser off, ns after the start.
    TimedExposure(u64, u64, u64),
    /// An exposure window the timers cannot time (software edges instead).
    Untimeable(crate::exposure::ExposureError),
    /// A reply or event too big for a frame (dropped).
    Oversized,
    /// A link write or read failed.
    Link,
}

/// What is counted rather than queued (from interrupts).
#[derive(Clone, Copy, Debug)]
pub enum Counter {
    /// Camera edges dropped because their queue was full.
    EdgesDropped,
}

const QUEUE_LEN: usize = 16;
static QUEUE: CriticalSectionMutex<RefCell<Deque<Note, QUEUE_LEN>>> =
    CriticalSectionMutex::new(RefCell::new(Deque::new()));
/// Notes lost because the queue was full.
static LOST: AtomicU32 = AtomicU32::new(0);
static EDGES_DROPPED: AtomicU32 = AtomicU32::new(0);

/// Queue a note (from a task or an interrupt); no log is written here.
pub fn note(n: Note) {
    QUEUE.lock(|q| {
        let Ok(mut q) = q.try_borrow_mut() else {
            LOST.fetch_add(1, Ordering::Relaxed);
            return;
        };
        if q.push_back(n).is_err() {
            LOST.fetch_add(1, Ordering::Relaxed);
        }
    });
}

/// Count an event (from an interrupt).
pub fn count(c: Counter) {
    match c {
        Counter::EdgesDropped => EDGES_DROPPED.fetch_add(1, Ordering::Relaxed),
    };
}

fn pop() -> Option<Note> {
    QUEUE.lock(|q| q.try_borrow_mut().ok().and_then(|mut q| q.pop_front()))
}

/// Write the noted lines. The rig task calls it only while the step timer is idle, so no log's
/// critical section overlaps a motion.
pub fn drain() {
    while let Some(n) = pop() {
        match n {
            Note::LaserPolarity(mask) => defmt::error!(
                "lasers {=u8:b}: their lines idle at the level the profile calls on; not driven",
                mask
            ),
            Note::GalvoWrite => defmt::warn!("galvo DAC write failed"),
            Note::Halt(reason) => defmt::warn!("halt: {}", reason),
            Note::Fault(fault) => defmt::warn!("fault: {}", fault),
            Note::StepLate(n) => {
                defmt::error!(
                    "step interrupt later than one period ({} times): stopped",
                    n
                )
            }
            Note::StepStall(missed, queued) => defmt::error!(
                "step stall: {} steps missed their time ({} segments queued)",
                missed,
                queued
            ),
            Note::Motor(on) => {
                defmt::info!("motor driver {}", if on { "energised" } else { "released" })
            }
            Note::TimedExposure(rise, fall, off) => defmt::debug!(
                "timed exposure: trigger {}..{} ns, laser off {} ns",
                rise,
                fall,
                off
            ),
            Note::Untimeable(e) => {
                defmt::warn!("exposure window not timeable ({}); software edges", e)
            }
            Note::Oversized => defmt::error!("message does not fit a frame; dropped"),
            Note::Link => defmt::warn!("link read or write failed"),
        }
    }
    let lost = LOST.swap(0, Ordering::Relaxed);
    if lost > 0 {
        defmt::warn!("{} log notes lost (queue full)", lost);
    }
    let edges = EDGES_DROPPED.swap(0, Ordering::Relaxed);
    if edges > 0 {
        defmt::warn!("camera edge queue full: {} oldest edges dropped", edges);
    }
}
